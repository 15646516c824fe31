"""A command that runs an estimator without its calibration says so: on the first line of its output and in
every output record (``[uncalibrated]`` on table rows, ``"calibrated": false`` in JSON); standard error
keeps its one-line-error contract and ``--jsonl`` output stays JSON objects only."""

from __future__ import annotations

import json

import pytest

from place_safe.cli.app import main
from place_safe.cli.common import UNCALIBRATED_MARK, uncalibrated_note

pytestmark = pytest.mark.fast


@pytest.fixture(scope="module")
def peak_calibration(tmp_path_factory, sweep_path):
    out = tmp_path_factory.mktemp("cal") / "cal.json"
    assert main(["calibrate", str(sweep_path), "--method", "peak", "-o", str(out), "-q"]) == 0
    return out


def _lines(text: str) -> list[str]:
    return [x for x in text.splitlines() if x.strip()]


def test_a_row_is_marked_only_when_uncalibrated():
    from place_safe.calibration import mark

    assert mark("peak  1.00", True) == "peak  1.00"
    assert mark("peak  1.00", False) == "peak  1.00  " + UNCALIBRATED_MARK


def test_note_names_the_cause_and_the_cure(peak_calibration):
    from place_safe.calibration import Calibration

    assert uncalibrated_note("peak", None).startswith("UNCALIBRATED: no --calibration")
    assert "place-safe calibrate" in uncalibrated_note("peak", None)
    cal = Calibration.load(peak_calibration)
    assert uncalibrated_note("peak", cal) is None
    assert "no forward section" in uncalibrated_note("diff", cal, str(peak_calibration))
    assert "naive baseline" in uncalibrated_note("peak-naive", cal)
    assert uncalibrated_note(["peak", "diff"], cal) is not None and uncalibrated_note(["peak"], cal) is None


def test_recover_table_and_jsonl(synthetic_file, capsys):
    assert main(["recover", str(synthetic_file), "--method", "peak", "-q"]) == 0
    out = _lines(capsys.readouterr().out)
    assert out[0].startswith("UNCALIBRATED:")
    assert all(row.endswith(UNCALIBRATED_MARK) for row in out[2:]) and len(out) > 2
    assert main(["recover", str(synthetic_file), "--method", "peak", "--jsonl", "-q"]) == 0
    cap = capsys.readouterr()
    records = [json.loads(x) for x in _lines(cap.out)]  # every line is a JSON object
    assert records and all(isinstance(r, dict) and r["calibrated"] is False for r in records)
    assert cap.err == ""


def test_recover_with_its_calibration_is_not_marked(sweep_path, peak_calibration, capsys):
    assert main(["recover", str(sweep_path), "--method", "peak", "--calibration", str(peak_calibration), "-q"]) == 0
    out = capsys.readouterr().out
    assert not out.startswith("UNCALIBRATED") and UNCALIBRATED_MARK not in out
    assert main(["recover", str(sweep_path), "--method", "peak", "--calibration", str(peak_calibration),
                 "--jsonl", "-q"]) == 0
    assert all(json.loads(x)["calibrated"] is True for x in _lines(capsys.readouterr().out))


def test_recover_with_a_calibration_lacking_the_method_is_marked(synthetic_file, peak_calibration, capsys):
    assert main(["recover", str(synthetic_file), "--method", "proprietary", "--calibration",
                 str(peak_calibration), "-q"]) == 0
    out = _lines(capsys.readouterr().out)
    assert out[0].startswith("UNCALIBRATED:") and "no proprietary section" in out[0]


def test_error_after_the_note_is_still_one_line_on_stderr(tmp_path, synthetic_frames, capsys):
    from place_safe.io.frame_file import write_frames

    path = tmp_path / "broken.json"
    write_frames(path, synthetic_frames[:2])
    path.write_text(path.read_text()[:-20])  # the file breaks after its first frame
    assert main(["recover", str(path), "--method", "peak", "-q"]) == 2
    cap = capsys.readouterr()
    assert cap.out.startswith("UNCALIBRATED:")
    assert len(cap.err.strip().splitlines()) == 1 and cap.err.startswith("place-safe: error:")


def test_stream_file_replay(synthetic_file, capsys):
    assert main(["stream", str(synthetic_file), "--method", "peak", "--rate", "1000", "--max-frames", "3"]) == 0
    out = _lines(capsys.readouterr().out)
    assert out[0].startswith("UNCALIBRATED:") and out[1].endswith(UNCALIBRATED_MARK)
    assert main(["stream", str(synthetic_file), "--method", "peak", "--rate", "1000", "--max-frames", "3",
                 "--jsonl"]) == 0
    records = [json.loads(x) for x in _lines(capsys.readouterr().out)]
    assert records and all(r["calibrated"] is False for r in records)


def test_sensor_stream_emulator(capsys):
    assert main(["sensor", "stream", "emu:synthetic:3", "--max-frames", "3"]) == 0
    out = _lines(capsys.readouterr().out)
    assert out[0].startswith("UNCALIBRATED:")
    assert len(out) == 4 and all(row.endswith(UNCALIBRATED_MARK) for row in out[1:])
    assert main(["sensor", "stream", "emu:synthetic:3", "--max-frames", "3", "--jsonl"]) == 0
    records = [json.loads(x) for x in _lines(capsys.readouterr().out)]
    assert len(records) == 3 and all(r["calibrated"] is False for r in records)


def test_sensor_stream_with_calibration(peak_calibration, capsys):
    assert main(["sensor", "stream", "emu:synthetic:2", "--max-frames", "2", "--calibration",
                 str(peak_calibration), "--jsonl"]) == 0
    records = [json.loads(x) for x in _lines(capsys.readouterr().out)]
    assert len(records) == 2 and all(r["calibrated"] is True for r in records)


def test_evaluate_marks_each_uncalibrated_method(sweep_path, peak_calibration, tmp_path, capsys):
    report = tmp_path / "r.json"
    assert main(["evaluate", str(sweep_path), "--methods", "peak", "proprietary", "--calibration",
                 str(peak_calibration), "--no-plots", "-q", "--json", str(report)]) == 0
    out = _lines(capsys.readouterr().out)
    assert out[0].startswith("UNCALIBRATED:") and "proprietary" in out[0]
    rows = {r.split()[0]: r for r in out[1:] if r.split()[0] in ("peak", "proprietary") and "mean" not in r
            and "NEES" not in r}
    assert rows["proprietary"].endswith(UNCALIBRATED_MARK) and not rows["peak"].endswith(UNCALIBRATED_MARK)
    methods = json.loads(report.read_text())["methods"]
    assert methods["peak"]["calibrated"] is True and methods["proprietary"]["calibrated"] is False


def test_bench_marks_its_runs(tmp_path, capsys):
    report = tmp_path / "b.json"
    assert main(["bench", "recovery", "--frames", "3", "--paper-frames", "0", "--methods", "peak", "-q",
                 "--json", str(report)]) == 0
    out = _lines(capsys.readouterr().out)
    assert out[0].startswith("UNCALIBRATED:")
    assert any(r.startswith("peak") and r.endswith(UNCALIBRATED_MARK) for r in out)
    assert all(m["calibrated"] is False for m in json.loads(report.read_text())["methods"])
