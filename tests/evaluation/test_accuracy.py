"""Accuracy measured on data the project's model did not generate.

* Frames of the independent generator (:mod:`place_safe.evaluation.independent`), calibrating on
  frames of one seed and testing on frames of another.
* The real sweep of ``tests/data``: calibrate on the even frames, test on the odd ones (held out).

The bounds are the figures measured when these tests were written (see the issue-9 closing note),
kept as regression guards; the issue's targets are quoted where they are met.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from place_safe.calibration.points import fit_peak
from place_safe.calibration.uncertainty import fit_peak_uncertainty, nees
from place_safe.evaluation.independent import make_frames
from place_safe.evaluation.metrics import angular_errors, linear_errors, point_errors
from place_safe.io.frame_file import iter_frames
from place_safe.recovery.peak import PeakEstimator

SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"


def _scores(ests, frames):
    n = np.array([e.plane.normal for e in ests])
    d = np.array([e.plane.offset for e in ests])
    tn = np.array([f.truth.normal for f in frames])
    td = np.array([f.truth.offset for f in frames])
    return (float(np.degrees(angular_errors(n, tn)).mean()), float(linear_errors(n, d, tn, td).mean() * 1e3),
            float(point_errors(n, d, tn, td).mean() * 1e3))


@pytest.mark.slow
def test_calibrated_peak_on_independent_frames_meets_the_issue_targets():
    """Peak calibrated on 80 independent frames, tested on 60 others: <= 0.30 deg / 0.30 mm / 0.25 mm
    (issue 9's targets for peak), and its covariance is honest (NEES per dof within 0.6 .. 1.6)."""
    cal, test = make_frames(80, seed=11), make_frames(60, seed=12)
    params, _ = fit_peak(cal, progress=False)
    unc, _ = fit_peak_uncertainty(cal, params)
    est = PeakEstimator(params, unc)
    ests = [est.estimate(f) for f in test]
    assert all(e.ok for e in ests)
    ang, lin, pt = _scores(ests, test)
    assert ang <= 0.30 and lin <= 0.30 and pt <= 0.25
    assert 0.6 <= float(np.nanmean(nees(ests, [f.truth for f in test]))) <= 1.6


@pytest.mark.slow
def test_calibrated_peak_on_held_out_real_frames():
    """Peak calibrated on the sweep's even frames, tested on the odd ones at 5-40 cm."""
    frames = [f for f in iter_frames(SWEEP)]
    even, odd = frames[0::2], [f for f in frames[1::2] if 0.05 <= f.truth.offset <= 0.40]
    params, _ = fit_peak(even, progress=False)
    unc, _ = fit_peak_uncertainty(even, params)
    est = PeakEstimator(params, unc)
    ests = [est.estimate(f) for f in odd]
    ang, lin, pt = _scores(ests, odd)
    assert ang <= 0.35 and lin <= 0.25 and pt <= 0.30
    assert 0.5 <= float(np.nanmean(nees(ests, [f.truth for f in odd]))) <= 1.5


@pytest.mark.slow
def test_calibrated_diff_on_independent_frames_meets_the_issue_targets(tmp_path):
    """The user's path end to end: ``place-safe calibrate --method diff`` on 150 independent frames, then
    ``place-safe evaluate`` on 100 others. The forward fit converges to an RMS scaled residual <= 1.3; diff
    meets issue 9's targets (<= 0.15 deg / 0.15 mm / 0.12 mm point), is no worse than peak on any metric,
    and its covariance is honest (NEES per dof within 0.7 .. 1.5)."""
    import json

    from place_safe.cli.app import main
    from place_safe.io.frame_file import write_frames

    write_frames(tmp_path / "cal.json", make_frames(150, seed=1))
    write_frames(tmp_path / "test.json", make_frames(100, seed=3))
    cal = tmp_path / "calib.json"
    assert main(["calibrate", str(tmp_path / "cal.json"), "--method", "diff", "-o", str(cal), "-q"]) == 0
    fit = json.loads(cal.read_text())["reports"]["forward"]
    assert fit["converged"] and fit["rms_scaled_residual_after"] <= 1.3
    report = tmp_path / "report.json"
    assert main(["evaluate", str(tmp_path / "test.json"), "--calibration", str(cal), "--methods", "diff", "peak",
                 "--no-plots", "--json", str(report), "-q"]) == 0
    m = json.loads(report.read_text())["methods"]
    diff, peak = m["diff"], m["peak"]
    assert diff["failures"] == 0
    assert diff["angular_deg"]["mean"] <= 0.15 and diff["linear_mm"]["mean"] <= 0.15 and diff["point_mm"]["mean"] <= 0.12
    for metric in ("angular_deg", "linear_mm", "point_mm"):
        assert diff[metric]["mean"] <= peak[metric]["mean"]
    assert 0.7 <= diff["nees_per_dof"]["mean"] <= 1.5
