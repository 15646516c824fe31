"""Calibrating the uncertainty floors: maximum likelihood recovers a known floor; NEES is 1 after."""

import math

import numpy as np
import pytest

from place_safe.calibration.uncertainty import MIN_DIFF_FRAMES, fit_floor, nees, select_chi2_limit
from place_safe.geometry import Plane
from place_safe.recovery.estimator import PlaneEstimate


def _estimates(n, tilt_floor, range_floor, offset_floor, own=1e-8, seed=0):
    rng = np.random.default_rng(seed)
    ests, truths = [], []
    for _ in range(n):
        d = rng.uniform(0.03, 0.3)
        truth = Plane(np.array([0, 0, 1.0]), d)
        var_t = tilt_floor ** 2 + (range_floor / d) ** 2 + own
        var_d = offset_floor ** 2 + own
        nx, ny = rng.normal(0, math.sqrt(var_t), 2)
        dd = d + rng.normal(0, math.sqrt(var_d))
        est = Plane(np.array([nx, ny, math.sqrt(1 - nx * nx - ny * ny)]), dd)
        ests.append(PlaneEstimate(est, covariance=np.eye(3) * own))
        truths.append(truth)
    return ests, truths


def test_floor_recovers_known_model_error_and_makes_nees_one():
    ests, truths = _estimates(400, 0.002, 1e-4, 2e-4)
    unc, rep = fit_floor(ests, truths)
    assert unc.tilt_std == pytest.approx(0.002, rel=0.3)
    assert unc.tilt_range_std == pytest.approx(1e-4, rel=0.3)
    assert unc.offset_std == pytest.approx(2e-4, rel=0.2)
    assert rep["nees_per_dof_after"] == pytest.approx(1.0, abs=1e-6)
    # fresh frames from the same error model: calibrated on others, NEES near 1
    test, ttruth = _estimates(400, 0.002, 1e-4, 2e-4, seed=1)
    calibrated = [PlaneEstimate(e.plane, covariance=unc.apply(e.covariance, e.plane.offset)) for e in test]
    assert np.nanmean(nees(calibrated, ttruth)) == pytest.approx(1.0, abs=0.2)


def test_no_floor_when_the_own_covariance_explains_the_errors():
    ests, truths = _estimates(300, 0.0, 0.0, 0.0, own=1e-6)
    unc, _ = fit_floor(ests, truths)
    assert unc.tilt_std < 3e-4 and unc.tilt_range_std < 3e-5 and unc.offset_std < 3e-4
    assert unc.scale == pytest.approx(1.0, abs=0.15)


def test_chi2_limit_admits_the_frames_diff_explains_and_helps():
    """Diff is better on the well-explained frames (low chi-square) and worse beyond: the limit lands between."""
    chi2 = np.array([0.9, 1.0, 1.1, 1.2, 1.3, 5.0, 6.0, 7.0, np.inf])
    diff = np.array([[0.1, 0.1]] * 5 + [[3.0, 3.0]] * 3 + [[10.0, 10.0]])
    peak = np.ones((9, 2))
    assert select_chi2_limit(chi2, diff, peak) == pytest.approx(1.3)
    assert select_chi2_limit(chi2, diff * 0.1, peak) == math.inf  # diff better everywhere: never fall back


def test_chi2_limit_is_zero_when_too_few_frames_would_use_diff():
    """One frame in many better by chance is not evidence: diff always falls back (limit 0)."""
    chi2 = np.array([1.0] + [5.0] * 20)
    diff = np.array([[0.5, 0.5]] + [[2.0, 2.0]] * 20)
    peak = np.ones((21, 2))
    assert MIN_DIFF_FRAMES > 1
    assert select_chi2_limit(chi2, diff, peak) == 0.0
    diff_worse = np.full((21, 2), 2.0)
    assert select_chi2_limit(chi2, diff_worse, peak) == 0.0  # never better: 0 too


def test_chi2_limit_only_counts_limits_enough_frames_pass():
    """A limit that only 2 frames pass cannot win, however well diff did on them; the best limit that 3 or
    more frames pass, and that still beats peak alone, does (here the one the third frame just passes)."""
    chi2 = np.array([0.5, 0.6] + [1.0 + 0.01 * i for i in range(8)] + [5.0] * 20)
    diff = np.array([[0.1, 0.1]] * 2 + [[1.05, 0.95]] * 8 + [[3.0, 3.0]] * 20)
    peak = np.ones((30, 2))
    assert select_chi2_limit(chi2, diff, peak) == pytest.approx(1.0)
    assert select_chi2_limit(np.array([]), np.zeros((0, 2)), np.zeros((0, 2))) == 0.0


def test_chi2_limit_is_zero_when_the_errors_cannot_be_compared():
    chi2 = np.array([0.5, 0.7, 0.9, 1.1])
    diff = np.full((4, 2), np.nan)
    assert select_chi2_limit(chi2, diff, np.ones((4, 2))) == 0.0


def test_a_frame_no_method_reads_does_not_break_the_diff_uncertainty(sweep_path):
    """One unusable frame (all-zero histograms) among calibration frames: it counts as failed for both methods
    and the limit is chosen on the rest (it made peak's median error NaN, and calibration stopped)."""
    from dataclasses import replace

    from place_safe.calibration.uncertainty import fit_diff_uncertainty
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    frames = [f for f in load_frames(sweep_path) if 0.08 <= f.truth.z0 <= 0.2][:6]
    frames.append(replace(frames[0], hists=np.zeros_like(np.asarray(frames[0].hists, dtype=float))))
    unc, report = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak())
    assert unc.chi2_limit >= 0.0 and report["frames_using_diff"] + report["frames_using_peak"] == len(frames)
    assert math.isfinite(report["point_mm"]["selected"])
