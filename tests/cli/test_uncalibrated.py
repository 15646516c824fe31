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


def test_evaluate_json_lists_the_methods_it_left_out_and_why(sweep_path, peak_calibration, tmp_path, capsys):
    """The --json report named only the methods that ran: a script reading it could not tell diff and proprietary
    were left out of the default, nor why (session 84's walkthrough). Now ``left_out`` maps each to its reason; empty
    when the methods are named."""
    report = tmp_path / "r.json"
    assert main(["evaluate", str(sweep_path), "--calibration", str(peak_calibration), "--no-plots", "-q",
                 "--min-distance", "0.35", "--json", str(report)]) == 0
    data = json.loads(report.read_text())
    assert set(data["left_out"]) == {"diff", "proprietary"} and "diff" not in data["methods"]
    assert all(isinstance(why, str) and "calibrate" in why for why in data["left_out"].values())
    capsys.readouterr()
    assert main(["evaluate", str(sweep_path), "--calibration", str(peak_calibration), "--no-plots", "-q",
                 "--min-distance", "0.35", "--methods", "peak", "--json", str(report)]) == 0
    assert json.loads(report.read_text())["left_out"] == {}


def test_evaluate_leaves_out_by_default_the_methods_its_calibration_does_not_calibrate(sweep_path, peak_calibration,
                                                                                      capsys):
    """``evaluate --calibration C`` with C from ``calibrate --method peak`` (or diff: neither fits proprietary) ran every
    method, so proprietary (and diff) ran on built-in constants beside the calibrated rows, proprietary's row the same as
    proprietary-naive's (a new user's walkthrough). By default the methods the file has no section for are left out with
    one line saying so and how to fit them; the naive baselines stay (uncalibrated by definition) and their note no
    longer asks for a calibration the user gave; naming a method with --methods still runs it, marked."""
    assert main(["evaluate", str(sweep_path), "--calibration", str(peak_calibration), "--no-plots", "-q",
                 "--min-distance", "0.35"]) == 0
    out = _lines(capsys.readouterr().out)
    rows = {r.split()[0] for r in out if "NEES" not in r and r.split()[0] in
            ("diff", "peak", "peak-naive", "proprietary", "proprietary-naive")}
    assert rows == {"peak", "peak-naive", "proprietary-naive"}
    note = [r for r in out if "left out" in r]
    assert len(note) == 1 and "diff, proprietary" in note[0] and "no forward or proprietary section" in note[0], out
    assert str(peak_calibration) in note[0] and "--method diff" in note[0] and "--methods" in note[0]
    assert out[0].startswith("UNCALIBRATED: peak-naive, proprietary-naive are naive baselines")
    assert "Fit one" not in out[0] and "use no calibration" in out[0]
    assert main(["evaluate", str(sweep_path), "--calibration", str(peak_calibration), "--no-plots", "-q",
                 "--min-distance", "0.35", "--methods", "peak", "proprietary"]) == 0
    out = _lines(capsys.readouterr().out)
    assert not any("left out" in r for r in out)
    assert any(r.startswith("proprietary") and r.endswith(UNCALIBRATED_MARK) for r in out)


def test_a_calibration_without_its_uncertainty_is_said_but_not_marked(tmp_path, sweep_path, capsys):
    """A calibration whose ``uncertainty`` section lacks the method's entry (cut, or written by hand): its planes are
    calibrated, so no UNCALIBRATED line and no marks, but ``recover``, ``evaluate`` and ``stream`` say on standard error
    that the covariances are the fit's alone (and diff's fallback gone) and that a placement refuses the file; ``-q``
    silences it, and a method whose entries are there gets no note (round 16's leftover)."""
    from place_safe.calibration import Calibration
    from place_safe.cli.common import uncertainty_note
    from place_safe.sim.tof import calibration_file

    data = json.loads(calibration_file("nominal").read_text())
    del data["uncertainty"]["diff"]
    cut = tmp_path / "cut.json"
    cut.write_text(json.dumps(data))
    cal = Calibration.load(cut)
    assert uncertainty_note("peak", cal) is None and uncertainty_note("diff", None) is None
    assert uncertainty_note("diff", Calibration.load(calibration_file("nominal"))) is None
    note = uncertainty_note(["peak", "diff"], cal, str(cut))
    assert note.startswith(f"note: {cut} has no 'uncertainty.diff' entry") and "never falls back to peak" in note
    assert "a placement refuses" in note and "--method diff" in note
    small = tmp_path / "small.json"
    small.write_text(json.dumps(json.loads(sweep_path.read_text())[10:14]))
    for argv in (["recover", str(small), "--method", "diff"],
                 ["evaluate", str(small), "--methods", "peak", "diff", "--no-plots"],
                 ["stream", str(small), "--method", "diff", "--rate", "1000"]):
        assert main(argv + ["--calibration", str(cut)]) == 0, argv
        cap = capsys.readouterr()
        assert "UNCALIBRATED" not in cap.out and UNCALIBRATED_MARK not in cap.out, argv
        assert [x for x in cap.err.splitlines() if x.startswith("note:") and "uncertainty" in x] == [note], argv
    for argv in (["recover", str(small), "--method", "diff", "-q"],
                 ["evaluate", str(small), "--methods", "diff", "--no-plots", "-q"],
                 ["recover", str(small), "--method", "peak"]):
        assert main(argv + ["--calibration", str(cut)]) == 0, argv
        assert "uncertainty" not in capsys.readouterr().err, argv
