"""Evaluation report: table, dict, plots, unavailable methods."""

from pathlib import Path

import numpy as np
import pytest

from place_safe.calibration import Calibration
from place_safe.calibration.points import fit_peak
from place_safe.evaluation.evaluate import evaluate
from place_safe.io.frame_file import load_frames

SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"


def test_evaluate_real_sweep(tmp_path):
    sweep = load_frames(SWEEP)
    params, _ = fit_peak(sweep[0::2], progress=False)
    cal = Calibration({"peak": params.to_dict()})
    test = [f for f in sweep[1::2] if f.truth.z0 >= 0.05][:8]
    rep = evaluate(test, cal, ["peak", "peak-naive", "proprietary-naive", "no-such-method"], out_dir=tmp_path,
                   progress=False)
    table = rep.table()
    for name in ("peak", "peak-naive", "proprietary-naive", "no-such-method"):
        assert name in table
    assert "unavailable" in table
    d = rep.to_dict()
    assert d["frames"] == 8 and set(d["methods"]) == {"peak", "peak-naive", "proprietary-naive"}
    assert d["methods"]["peak"]["linear_mm"]["mean"] < 1.0
    assert d["methods"]["peak"]["linear_mm"]["mean"] < d["methods"]["peak-naive"]["linear_mm"]["mean"]
    assert d["methods"]["peak"]["failures"] == 0
    assert "no-such-method" in d["unavailable"]
    for p in rep.plots:
        assert Path(p).is_file() and Path(p).stat().st_size > 1000
    assert len(rep.plots) >= 2


def test_frames_without_truth_are_skipped():
    sweep = load_frames(SWEEP)[:3]
    sweep[0].truth = None
    rep = evaluate(sweep, None, ["peak"], progress=False)
    assert rep.skipped == 1 and len(rep.results["peak"].point) == 2
    assert np.all(np.isfinite(rep.results["peak"].seconds))


def test_a_method_that_fails_every_frame_shows_dashes_not_nan():
    from dataclasses import replace

    sweep = [replace(f, hists=np.zeros((9, 128))) for f in load_frames(SWEEP)[20:23]]
    rep = evaluate(sweep, None, ["peak"], progress=False)
    row = next(line for line in rep.table().splitlines() if line.startswith("peak"))
    assert "nan" not in row and row.split()[1:10] == ["-"] * 9 and row.split()[10] == "3"


def test_summary_reports_the_fallback_rate_and_the_albedo_spread():
    """diff's share of frames answered by peak's plane, and the recovered albedos' spread (one surface: how
    well one albedo is read over distance and angle)."""
    import numpy as np

    from place_safe.evaluation.evaluate import MethodResult

    n = 4
    res = MethodResult("diff", np.zeros(n), np.zeros(n), np.zeros(n), np.array([2.0, 2.2, 1.8, np.nan]),
                       np.zeros(n), [None] * n, used=["diff", "peak", "diff", None])
    s = res.summary()
    assert s["fallback_rate"] == pytest.approx(1 / 3)
    mixed = MethodResult("diff", np.zeros(n), np.zeros(n), np.zeros(n), np.full(n, np.nan), np.zeros(n), [None] * n,
                         used=["diff+peak", "peak", "diff", "diff+peak"])  # a blend is not a fallback
    assert mixed.summary()["fallback_rate"] == pytest.approx(1 / 4)
    assert mixed.summary()["method_used"] == {"diff": 1, "diff+peak": 2, "peak": 1}
    assert s["albedo"]["mean"] == pytest.approx(2.0)
    assert s["albedo"]["cv_percent"] == pytest.approx(10.0)
    assert s["albedo"]["count"] == 3
    none = MethodResult("peak", np.zeros(1), np.zeros(1), np.zeros(1), np.full(1, np.nan), np.zeros(1), [None])
    assert none.summary()["fallback_rate"] is None and none.summary()["albedo"] is None


def test_table_says_a_zero_fallback_rate():
    """diff that kept its own plane on every frame: the table still says so (fallback rate 0 %)."""
    import numpy as np

    from place_safe.evaluation.evaluate import EvaluationReport, MethodResult

    n = 3
    res = MethodResult("diff", np.ones(n), np.ones(n), np.ones(n), np.full(n, 2.0), np.zeros(n), [None] * n,
                       used=["diff"] * n)
    table = EvaluationReport(results={"diff": res}, z0=np.full(n, 0.1), theta=np.zeros(n)).table()
    assert "used diff 3 (fallback rate 0 %)" in table


def test_frames_skipped_before_and_frames_with_a_broken_truth_are_counted_and_reported():
    """The command's reader drops frames whose ground truth is not a plane (a zero normal, a NaN distance) before
    evaluate sees them; its JSON said ``skipped_without_truth: 0`` and its table "(5 frames with ground truth)". The
    counts by reason now reach the report: the table's last line and ``skipped`` / ``skipped_without_truth``."""
    import copy

    sweep = load_frames(SWEEP)[20:24]
    broken = copy.copy(sweep[0])
    broken.truth, broken.truth_error = None, "ground truth: the plane normal has zero length"
    rep = evaluate([broken] + sweep[1:], None, ["peak-naive"], progress=False,
                   skipped={"ground truth not a plane": 2, "outside the distance limits": 1})
    d = rep.to_dict()
    assert d["frames"] == 3 and d["skipped_without_truth"] == 3
    assert d["skipped"] == {"ground truth not a plane": 3, "outside the distance limits": 1}
    assert rep.table().splitlines()[-1] == ("(3 frames with ground truth; 4 skipped: 3 ground truth not a plane, "
                                            "1 outside the distance limits)")


def test_the_command_reports_the_frames_its_reader_skipped(tmp_path, capsys):
    import json

    from place_safe.cli.app import main

    entries = json.loads(SWEEP.read_text())[20:23]
    entries[1].pop("pose", None)
    entries[1]["plane"] = {"normal": [0, 0, 0], "offset": 0.1}
    path = tmp_path / "f.json"
    path.write_text(json.dumps(entries))
    out = tmp_path / "ev.json"
    assert main(["evaluate", str(path), "--methods", "peak-naive", "--no-plots", "-q", "--json", str(out)]) == 0
    assert "(2 frames with ground truth; 1 skipped: 1 ground truth not a plane)" in capsys.readouterr().out
    d = json.loads(out.read_text())
    assert d["frames"] == 2 and d["skipped_without_truth"] == 1 and d["skipped"] == {"ground truth not a plane": 1}


def test_a_frame_given_twice_counts_once_as_in_calibrate(tmp_path, capsys):
    """evaluate counted a frame given twice twice (session 82's leftover): the sweep pasted after itself weighted every
    frame double in the means, percentiles and NEES and reported 106 frames. An exact repeat (the same histograms and
    on-sensor distances) is one measurement: left out, as calibrate leaves it out, counted among the skipped frames in
    the table and the JSON, with one line on standard error naming the first copy. The numbers are the sweep's own."""
    import json

    from place_safe.cli.app import main

    sweep = load_frames(SWEEP)[18:26]
    once = evaluate(sweep, None, ["peak-naive"], progress=False)
    twice = evaluate(sweep + sweep[2:5], None, ["peak-naive"], progress=False)
    assert twice.to_dict()["frames"] == 8 and twice.to_dict()["skipped"] == {"repeats of an earlier frame": 3}
    assert twice.repeats_note.startswith("frame 8 repeats frame 2 exactly") and once.repeats_note is None
    assert twice.results["peak-naive"].summary() | {"ms_per_frame": 0} == once.results["peak-naive"].summary() | {
        "ms_per_frame": 0}
    assert twice.table().splitlines()[-1] == "(8 frames with ground truth; 3 skipped: 3 repeats of an earlier frame)"
    entries = json.loads(SWEEP.read_text())[20:23]
    path = tmp_path / "twice.json"
    path.write_text(json.dumps(entries + entries[:1]))
    out = tmp_path / "ev.json"
    assert main(["evaluate", str(path), "--methods", "peak-naive", "--no-plots", "--json", str(out)]) == 0
    captured = capsys.readouterr()
    assert "(3 frames with ground truth; 1 skipped: 1 repeats of an earlier frame)" in captured.out
    notes = [line for line in captured.err.splitlines() if "repeats frame" in line]
    assert len(notes) == 1 and notes[0].startswith("evaluate: frame 3 repeats frame 0 exactly"), captured.err
    assert json.loads(out.read_text())["frames"] == 3
