"""Calibrating the uncertainty floors: maximum likelihood recovers a known floor; NEES is 1 after."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.calibration.uncertainty import PREFER_RATIOS, chi2_candidates, fit_floor, nees, select_fallback
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


def test_frames_that_want_no_floor_still_get_an_entry_that_loads():
    """Covariances twice the errors' (diff's on the whole real sweep: NEES per dof 0.59 before a floor) want no floor
    term; the entry then states the 1 um offset floor, shrinks by its scale, and a calibration file holding it loads
    (an entry stating no floor at all is refused on load, and was, for `calibrate` of the whole real sweep)."""
    from place_safe.calibration import Calibration
    from place_safe.calibration.uncertainty import MIN_OFFSET_FLOOR

    ests, truths = _estimates(300, 0.0, 0.0, 0.0, own=1e-6)
    wide = [PlaneEstimate(e.plane, covariance=4.0 * e.covariance) for e in ests]
    unc, rep = fit_floor(wide, truths)
    assert not unc.states_no_floor() and unc.offset_std == MIN_OFFSET_FLOOR
    assert unc.tilt_std == unc.tilt_range_std == unc.offset_rel == 0.0
    assert unc.scale == pytest.approx(0.25, rel=0.2) and "floor_held" in rep
    assert rep["nees_per_dof_after"] == pytest.approx(1.0, abs=1e-6)
    from place_safe.calibration import FORMAT
    cal = Calibration.from_dict({"format": FORMAT, "uncertainty": {"peak": unc.to_dict()}})
    assert cal.uncertainty("peak").offset_std == MIN_OFFSET_FLOOR
    # the frames wanting a floor are unchanged by it
    unc2, rep2 = fit_floor(*_estimates(400, 0.002, 1e-4, 2e-4))
    assert "floor_held" not in rep2 and unc2.offset_std > 1e-4


def test_chi2_limit_admits_the_frames_diff_explains_and_helps():
    """Diff is better on the well-explained frames (low chi-square) and worse beyond: the limit lands between."""
    chi2 = np.array([0.9, 1.0, 1.1, 1.2, 1.3, 5.0, 6.0, 7.0, np.inf])
    diff = np.array([[0.1, 0.1]] * 5 + [[3.0, 3.0]] * 3 + [[10.0, 10.0]])
    peak = np.ones((9, 2))
    ok, ratio = np.ones(9, dtype=bool), np.full(9, 0.5)
    limit, prefer, table = select_fallback(chi2, ok, ratio, diff, peak, [1.3, 7.0, 14.0])
    assert limit == pytest.approx(1.3) and prefer == 1.0
    assert len(table) == 3 * len(PREFER_RATIOS)
    # diff better everywhere: the largest candidate
    assert select_fallback(chi2, ok, ratio, diff * 0.1, peak, [1.3, 7.0, 14.0])[0] == 14.0


def test_a_score_better_by_less_than_its_standard_error_does_not_take_diff_away():
    """Level frames both methods read about as well, diff's errors on the farther half scattering about peak's (a
    little worse on the whole, by chance): the limits that keep diff everywhere score within one standard error of the
    best, paired frame by frame, and win (a level sweep cannot show what the narrower limit would cost on tilted
    planes). The same frames with diff worse there by a steady few per cent, or clearly: diff is kept on none of them
    (paired, a steady difference is not noise)."""
    rng = np.random.default_rng(4)
    n = 40
    chi2 = np.linspace(1.0, 3.0, n)
    peak = rng.uniform(0.5, 1.5, (n, 2))
    far = chi2 > 2.0
    ok, ratio = np.ones(n, dtype=bool), np.full(n, 0.5)
    diff = peak.copy()
    diff[far] *= rng.uniform(0.5, 1.6, (int(far.sum()), 2))
    diff[far] *= 1.03 * peak[far].mean(axis=0) / diff[far].mean(axis=0)  # 3 % worse there on the whole
    limit, prefer, table = select_fallback(chi2, ok, ratio, diff, peak, [2.0, 3.0])
    best = min(t["score"] for t in table)
    assert [t for t in table if t["score"] == best][0]["chi2_limit"] == 2.0  # the best score alone: the narrower one
    assert limit == 3.0 and prefer >= 0.5
    for worse in (0.05, 3.0):
        diff = peak.copy()
        diff[far] += worse
        limit, prefer, table = select_fallback(chi2, ok, ratio, diff, peak, [2.0, 3.0])
        assert not np.any(far & (chi2 <= limit) & ~(ratio > prefer)), worse
        assert prefer >= 0.5  # ... and still on the nearer frames, where it is as good


def test_a_pair_that_parts_from_the_best_on_one_frame_only_is_within_its_standard_error():
    """One level frame cannot tell two pairs apart: the open limit, which returns diff's plane on one frame more than
    the best (where diff reads it worse), is within one (sample) standard error of the best, paired, and wins; two such
    frames, both worse, are a steady difference and it is not."""
    rng = np.random.default_rng(7)
    n = 40
    chi2 = np.r_[np.linspace(1.0, 2.0, n - 2), 2.5, 2.6]
    peak = rng.uniform(0.5, 1.5, (n, 2))
    diff = peak * 0.98  # a little better than peak on the frames both pairs return it
    ok, ratio = np.ones(n, dtype=bool), np.full(n, 0.5)
    one = diff.copy()
    one[-2] = peak[-2] * 1.5  # diff worse on one frame beyond the narrower limit
    one[-1] = peak[-1]        # and as good on the other
    limit, _, table = select_fallback(chi2, ok, ratio, one, peak, [2.0, 3.0])
    assert min(table, key=lambda t: t["score"])["chi2_limit"] == 2.0  # the best score alone: the narrower one
    assert limit == 3.0
    two = one.copy()
    two[-1] = peak[-1] * 1.5
    assert select_fallback(chi2, ok, ratio, two, peak, [2.0, 3.0])[0] == 2.0


def test_a_larger_limit_is_not_taken_with_a_ratio_that_returns_peak_everywhere():
    """A frame both methods fail (capped errors) and diff worse beyond chi-square 2: the best pair keeps diff on the
    nearer frames (ratio 0.5); a larger limit with ratio 0.25 keeps it nowhere and is not the more open pair: the pick
    keeps diff on some frames, and on none where it reads worse."""
    n = 40
    chi2 = np.linspace(1.0, 3.0, n)
    peak = np.ones((n, 2))
    diff = np.full((n, 2), 0.9)
    diff[chi2 > 2.0] = 2.5
    diff[-1] = peak[-1] = 10.0
    ok, ratio = np.ones(n, dtype=bool), np.full(n, 0.5)
    limit, prefer, table = select_fallback(chi2, ok, ratio, diff, peak, [2.0, 3.0, 6.0])
    best = min(table, key=lambda t: t["score"])
    chosen = [t for t in table if t["chi2_limit"] == limit and t["prefer_ratio"] == prefer][0]
    assert chosen["frames_using_diff"] > 0 and best["frames_using_diff"] > 0
    assert limit == 2.0 and prefer >= 0.5
    # the same, the pairs' scores made equal (a steady cost nowhere): the larger limits with ratio 0.25 tie with the
    # best, and still the pick keeps diff on some frame
    diff[chi2 > 2.0] = 1.0
    diff[chi2 <= 2.0] = 1.0
    diff[-1] = 10.0
    limit, prefer, table = select_fallback(chi2, ok, ratio, diff, peak, [2.0, 3.0, 6.0])
    chosen = [t for t in table if t["chi2_limit"] == limit and t["prefer_ratio"] == prefer][0]
    assert chosen["frames_using_diff"] > 0 and limit == 6.0


def test_preference_ratio_keeps_diff_where_its_covariance_says_it_reads_better():
    """Frames where diff's tilt variance is below peak's are the ones diff reads better: ratio 1 returns the
    better plane on every frame; a ratio that keeps diff everywhere, or nowhere, scores worse."""
    ratio = np.array([0.1, 0.2, 0.3, 3.0, 5.0, 8.0])
    diff = np.array([[0.5, 0.5]] * 3 + [[2.0, 2.0]] * 3)
    peak = np.ones((6, 2))
    limit, prefer, table = select_fallback(np.ones(6), np.ones(6, dtype=bool), ratio, diff, peak, [2.0],
                                           ratios=(0.05, 1.0, 10.0))
    assert prefer == 1.0 and limit == 2.0
    scores = {t["prefer_ratio"]: t["score"] for t in table}
    assert scores[1.0] < scores[0.05] and scores[1.0] < scores[10.0]


def test_never_a_limit_that_always_falls_back():
    """A level sweep where peak is better on every frame: diff's covariance already says so (ratio > 1), the
    limits stay open (no candidate forces the fallback) and frames where diff's covariance is the smaller
    would still keep diff."""
    chi2 = np.array([1.0, 1.2, 1.4, 1.6, 2.0, 2.5])
    diff, peak = np.full((6, 2), 3.0), np.ones((6, 2))
    cands = chi2_candidates(chi2)
    assert min(cands) > 0 and max(cands) == pytest.approx(5.0) and math.isinf(chi2_candidates(np.array([np.inf]))[0])
    limit, prefer, _ = select_fallback(chi2, np.ones(6, dtype=bool), np.full(6, 9.0), diff, peak, cands)
    assert limit == pytest.approx(5.0) and prefer >= 1.0


def test_errors_that_cannot_be_compared_give_the_stated_defaults():
    chi2 = np.array([0.5, 0.7, 0.9, 1.1])
    diff = np.full((4, 2), np.nan)
    limit, prefer, _ = select_fallback(chi2, np.ones(4, dtype=bool), np.ones(4), diff, np.ones((4, 2)), [1.1, 2.2])
    assert limit == 2.2 and prefer == 1.0


def test_peak_calibration_states_the_tilt_term(sweep_path):
    """A level sweep cannot show peak's tilt error: the peak section carries the stated term."""
    from place_safe.calibration.uncertainty import PEAK_TILT_REL, fit_peak_uncertainty
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery.points import PeakParams

    frames = [f for f in load_frames(sweep_path) if 0.05 <= f.truth.z0 <= 0.4]
    unc, _ = fit_peak_uncertainty(frames, PeakParams.default_peak())
    assert unc.tilt_rel == PEAK_TILT_REL > 0


def test_peaks_stated_tilt_term_follows_the_frames_tilts():
    """Peak's stated term is for frames that cannot show its tilt error: mostly tilted calibration frames fit the edge
    and corner scales and the floor holds the rest (no term on top: with it the packaged mismatched calibration read
    0-12 deg planes at NEES per dof 2.56); a level sweep with TILT_TERM_MIN_FRAMES or more tilted frames sizes it on
    them (factors within TILT_TERM_SCALES), the floor from the level ones."""
    from place_safe.calibration.uncertainty import (PEAK_TILT_REL, TILT_TERM_MIN_FRAMES, TILT_TERM_SCALES,
                                                    fit_peak_uncertainty)
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.points import PeakParams

    tilted = make_frames(TILT_TERM_MIN_FRAMES + 4, seed=2, scene=SceneSpec(z_range=(0.06, 0.30),
                                                                             theta_range=(0.2, 0.4)))
    level = make_frames(30, seed=1, scene=SceneSpec(z_range=(0.06, 0.30), theta_range=(0.0, 0.0)))
    unc, report = fit_peak_uncertainty(level[:3] + tilted, PeakParams.default_peak())
    assert unc.tilt_rel == 0.0 and unc.tilt_offset_rel == 0.0 and report["tilt_term"].startswith("none")
    unc, report = fit_peak_uncertainty(level + tilted, PeakParams.default_peak())
    sized = report["tilt_term_sized"]
    assert report["tilt_term"].startswith("stated") and sized["frames"] >= TILT_TERM_MIN_FRAMES
    lo, hi = TILT_TERM_SCALES
    assert lo * PEAK_TILT_REL <= unc.tilt_rel <= hi * PEAK_TILT_REL and unc.tilt_offset_rel > 0
    assert math.isclose(unc.tilt_rel, PEAK_TILT_REL * sized["tilt_factor"])
    assert report["frames"] <= len(level)  # the floor from the level frames alone
    unc, report = fit_peak_uncertainty(level, PeakParams.default_peak())  # level alone: stated as it is
    assert unc.tilt_rel == PEAK_TILT_REL and "tilt_term_sized" not in report
    # level frames peak cannot read (saturated) leave too few for a floor: it is fitted on all the frames peak reads
    from dataclasses import replace
    unread = [replace(f, extra={**(f.extra or {}), "saturated": True}) for f in level[2:20]]
    unc, report = fit_peak_uncertainty(level[:2] + unread + tilted, PeakParams.default_peak())
    assert report["frames"] >= 3 and "why" not in report


def test_the_forward_models_mount_widens_peaks_offset_on_level_sweeps_only():
    """Peak's stated term gets an offset part PEAK_MOUNT_OFFSET_REL x |mount tilt| of the unit's forward model, for
    level calibration frames only (tilted frames show the error and the floor holds it); no mount, or one that is not a
    finite pair, gives none. ``update_calibration`` takes the mount from a valid forward section, and a broken one
    does not stop the peak method."""
    from place_safe.calibration import Calibration
    from place_safe.calibration.uncertainty import (PEAK_MOUNT_OFFSET_REL, PEAK_TILT_REL, fit_peak_uncertainty,
                                                    peak_tilt_term, update_calibration)
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    tilt = [0.012, -0.009]
    term = peak_tilt_term(tilt)
    assert term.tilt_rel == PEAK_TILT_REL and math.isclose(term.tilt_offset_rel, PEAK_MOUNT_OFFSET_REL * 0.015)
    for bad in (None, [math.nan, 0.0], [math.inf, 0.0], [0.1], "x", [[1, 2], [3, 4]]):
        assert peak_tilt_term(bad).tilt_offset_rel == 0.0, bad
    level = make_frames(30, seed=1, scene=SceneSpec(z_range=(0.06, 0.30), theta_range=(0.0, 0.0)))
    tilted = make_frames(30, seed=2, scene=SceneSpec(z_range=(0.06, 0.30), theta_range=(0.2, 0.4)))
    unc, report = fit_peak_uncertainty(level, PeakParams.default_peak(), mount_tilt=tilt)
    assert math.isclose(unc.tilt_offset_rel, term.tilt_offset_rel) and "mount tilt" in report["tilt_offset_from"]
    unc, report = fit_peak_uncertainty(level[:3] + tilted, PeakParams.default_peak(), mount_tilt=tilt)
    assert unc.tilt_rel == 0.0 and unc.tilt_offset_rel == 0.0 and "tilt_offset_from" not in report
    cal = Calibration(sections={"forward": ForwardParams(mount_tilt=tilt).to_dict()})
    rep = update_calibration(cal, level, "peak")
    assert math.isclose(cal.sections["uncertainty"]["peak"]["tilt_offset_rel"], term.tilt_offset_rel)
    assert "0.86 deg" in rep["peak"]["note"]  # a peak-only calibration says whose mount it took
    assert "not calibrated" in rep["peak"]["note"] and "--incidences" in rep["peak"]["note"]  # nor slopes' scale
    rep = update_calibration(Calibration(), level, "peak")  # no forward model: the slopes' note alone
    assert rep["peak"]["note"].startswith("peak's slopes on tilted planes are not calibrated")
    assert "note" not in update_calibration(Calibration(), level[:3] + tilted, "peak")["peak"]  # tilted: measured
    assert "note" not in update_calibration(cal, level, "diff")["peak"]  # diff's calibration fitted it just before
    broken = Calibration.from_dict({"format": cal.to_dict()["format"], "forward": {"mount_tilt": [math.nan, 0.0]}})
    assert "forward" in broken.errors
    rep = update_calibration(broken, level, "peak")  # no traceback: the peak method needs no forward model
    assert broken.sections["uncertainty"]["peak"].get("tilt_offset_rel", 0.0) == 0.0
    assert rep["peak"]["tilt_offset_from"].startswith("no forward model")


@pytest.mark.parametrize("blend", [True, False])
def test_a_frame_no_method_reads_does_not_break_the_diff_uncertainty(sweep_path, monkeypatch, blend):
    """One unusable frame (all-zero histograms) among calibration frames: it counts as failed for both methods
    and the limit is chosen on the rest (it made peak's median error NaN, and calibration stopped). With the blend
    (the default) only the chi-square limit is chosen and ``prefer_ratio`` is null; without it, a ratio too."""
    from dataclasses import replace

    import place_safe.calibration.uncertainty as uncertainty
    from place_safe.calibration.uncertainty import fit_diff_uncertainty

    monkeypatch.setattr(uncertainty, "BLEND", blend)
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    frames = [f for f in load_frames(sweep_path) if 0.08 <= f.truth.z0 <= 0.2][:6]
    frames.append(replace(frames[0], hists=np.zeros_like(np.asarray(frames[0].hists, dtype=float))))
    unc, report = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak())
    assert unc.chi2_limit > 0.0 and report["frames_using_diff"] + report["frames_using_peak"] == len(frames)
    assert math.isfinite(report["point_mm"]["selected"]) and report["folds"] >= 2
    assert unc.consistency_limit < math.inf and unc.blend is blend
    assert unc.prefer_ratio == math.inf if blend else unc.prefer_ratio in PREFER_RATIOS
    assert report["blend"].startswith("diff's plane blended" if blend else "none")
    assert math.isfinite(report["angular_deg"]["blend"])
    # a level sweep cannot show diff's tilt error either: the diff section carries the stated terms
    from place_safe.calibration.uncertainty import DIFF_TILT_OFFSET_REL, DIFF_TILT_PIVOT, DIFF_TILT_REL
    assert (unc.tilt_rel, unc.tilt_offset_rel, unc.tilt_pivot) == (DIFF_TILT_REL, DIFF_TILT_OFFSET_REL, DIFF_TILT_PIVOT)
    assert DIFF_TILT_REL > 0 and DIFF_TILT_OFFSET_REL > 0


def test_frames_beyond_the_fallback_range_do_not_choose_diffs_limits():
    """A level sweep out to 1 m: its frames beyond FALLBACK_MAX_RANGE take no part in choosing the fallback limits
    (their low chi-square made the limit a distance cut), while enough frames are left in range; with too few, all
    frames from 5 cm on choose them."""
    from place_safe.calibration.uncertainty import FALLBACK_MAX_RANGE, FALLBACK_MIN_FRAMES, fit_diff_uncertainty
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    near = make_frames(FALLBACK_MIN_FRAMES, seed=1, scene=SceneSpec(z_range=(0.06, 0.35), theta_range=(0.0, 0.0)))
    far = make_frames(4, seed=2, scene=SceneSpec(z_range=(FALLBACK_MAX_RANGE + 0.05, 0.9), theta_range=(0.0, 0.0)))
    _, report = fit_diff_uncertainty(near + far, ForwardParams(), PeakParams.default_peak())
    assert report["frames_beyond_range"] == len(far)
    assert report["frames_using_diff"] + report["frames_using_peak"] == len(near)
    _, few = fit_diff_uncertainty(near[:4] + far, ForwardParams(), PeakParams.default_peak())
    assert few["frames_beyond_range"] == 0 and few["frames_choosing"].startswith("all")
    assert report["frames_choosing"].startswith(f"the {len(near)} frames")
    assert few["frames_using_diff"] + few["frames_using_peak"] == 4 + len(far)


def test_tilted_calibration_frames_hold_diffs_tilt_error_without_the_stated_term():
    """Frames whose tilts spread 5 deg or more show diff's tilt error: the floor fitted on them holds it, and the
    stated term (for level sweeps) is not added on top."""
    from place_safe.calibration.uncertainty import fit_diff_uncertainty
    from place_safe.evaluation.independent import make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    frames = make_frames(8, seed=1)
    tilts = [math.acos(abs(float(f.truth.normal[2]))) for f in frames]
    assert np.ptp(tilts) >= math.radians(5.0)
    unc, report = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak())
    assert unc.tilt_rel == 0.0 and unc.tilt_offset_rel == 0.0 and report["tilt_term"].startswith("none")


def test_a_level_sweep_with_a_few_tilted_frames_keeps_the_stated_term():
    """A few tilted frames among level ones spread the tilts past 5 deg, but the floor fitted on all follows the
    level ones: under DIFF_TILTED_SHARE tilted, the stated term stays (the independent generator's level sweep
    with 30 tilted frames of 180 held out NEES 2.65 without it, 0.42 with it)."""
    from place_safe.calibration.uncertainty import DIFF_TILT_REL, DIFF_TILTED_SHARE, fit_diff_uncertainty
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    level = make_frames(7, seed=1, scene=SceneSpec(z_range=(0.06, 0.30), theta_range=(0.0, 0.0)))
    tilted = make_frames(2, seed=2, scene=SceneSpec(z_range=(0.06, 0.30), theta_range=(0.2, 0.4)))
    frames = level + tilted
    assert len(tilted) / len(frames) < DIFF_TILTED_SHARE
    unc, report = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak())
    assert unc.tilt_rel == DIFF_TILT_REL and report["tilt_term"].startswith("stated")
    # calibrate prints the report's note: the term is stated, not measured, and how to capture for one that is
    assert "not measured" in report["note"] and "--incidences" in report["note"]


def _tilted_estimates(n: int, kt: float, ko: float, seed: int = 0, scale: float = 1.0):
    """``n`` diff-like estimates of planes tilted 8-30 deg, 5-30 cm, with a small fit covariance, whose errors are
    drawn from that covariance plus the stated term (tilt_rel 0.01, tilt_offset_rel 0.002) with its tilt part times
    ``kt`` and its offset part times ``ko``, all times ``scale``; the term and the truths."""
    from place_safe.geometry import Plane
    from place_safe.recovery.estimator import PlaneEstimate, Uncertainty

    rng = np.random.default_rng(seed)
    term = Uncertainty(tilt_rel=0.01, tilt_offset_rel=0.002)
    ests, truths = [], []
    for _ in range(n):
        normal = _tilted(rng.uniform(8.0, 30.0), rng.uniform(0.0, 2 * math.pi))
        truth = Plane(normal, rng.uniform(0.05, 0.3))
        fit = np.diag([1e-6, 1e-6, 1e-8])
        tilt_part = term.replace(tilt_offset_rel=0.0).tilt_floor(normal, truth.offset)
        offset_part = term.tilt_floor(normal, truth.offset) - tilt_part
        cov = fit + kt * kt * tilt_part + ko * ko * offset_part
        e = scale * rng.multivariate_normal(np.zeros(3), cov)
        nx, ny = normal[0] + e[0], normal[1] + e[1]
        plane = Plane(np.array([nx, ny, math.sqrt(1.0 - nx * nx - ny * ny)]), truth.offset + e[2])
        ests.append(PlaneEstimate(plane, covariance=fit, method_used="diff"))
        truths.append(truth)
    return ests, truths, term


def test_a_few_tilted_frames_size_the_stated_tilt_term():
    """Tilted calibration frames among level ones scale the stated term's tilt and offset parts by maximum
    likelihood (convention check on drawn errors: the factors they were drawn with come back, the frames' NEES per
    component is then 1); within TILT_TERM_SCALES when the frames read better or worse than any factor explains."""
    from place_safe.calibration.uncertainty import TILT_TERM_SCALES, size_tilt_term

    ests, truths, term = _tilted_estimates(600, 2.0, 3.0, seed=1)
    sized, rep = size_tilt_term(ests, truths, term)
    assert rep["frames"] == 600
    assert 1.8 <= rep["tilt_factor"] <= 2.2 and 2.6 <= rep["offset_factor"] <= 3.4
    assert math.isclose(sized.tilt_rel, term.tilt_rel * rep["tilt_factor"])
    assert math.isclose(sized.tilt_offset_rel, term.tilt_offset_rel * rep["offset_factor"])
    assert abs(rep["nees_tilt_after"] - 1.0) < 0.02 and abs(rep["nees_offset_after"] - 1.0) < 0.02
    assert rep["nees_offset_before"] > 3.0
    ests, truths, term = _tilted_estimates(20, 1.0, 1.0, seed=2, scale=1e-3)  # read far better than the term says
    _, rep = size_tilt_term(ests, truths, term)
    assert (rep["tilt_factor"], rep["offset_factor"]) == (TILT_TERM_SCALES[0], TILT_TERM_SCALES[0])
    ests, truths, term = _tilted_estimates(20, 1.0, 1.0, seed=3, scale=20.0)  # far worse (20 > 10 times)
    _, rep = size_tilt_term(ests, truths, term)
    assert (rep["tilt_factor"], rep["offset_factor"]) == (TILT_TERM_SCALES[1], TILT_TERM_SCALES[1])


def test_a_part_of_the_tilt_term_that_is_zero_is_sized_from_the_unknown_model_errors_value():
    """A unit whose model error is 0 has no offset part (diff_tilt_term(0)): the tilted frames size it from the value
    for a model error not known, rather than leaving it at 0 and reporting a factor of 1; frames without a finite
    covariance are left out, and with none the term is returned as it was."""
    from dataclasses import replace

    from place_safe.calibration.uncertainty import DIFF_TILT_OFFSET_REL, size_tilt_term

    ests, truths, term = _tilted_estimates(400, 1.0, 3.0, seed=5)
    zero = term.replace(tilt_offset_rel=0.0)
    sized, rep = size_tilt_term(ests, truths, zero)
    assert sized.tilt_offset_rel > 0 and abs(rep["nees_offset_after"] - 1.0) < 0.02
    assert math.isclose(sized.tilt_offset_rel, DIFF_TILT_OFFSET_REL * rep["offset_factor"])
    bad = [replace(e, covariance=np.full((3, 3), np.nan)) for e in ests[:5]] + [replace(ests[5], covariance=None)]
    same, rep = size_tilt_term(bad, truths[:6], term)
    assert same == term and rep["frames"] == 0 and rep["why"]


def test_diff_uncertainty_from_near_frames_only_does_not_break():
    """Calibration frames all closer than the near fallback range (5 cm): none takes part in diff's limits, and the
    tilt rule has no frames to look at (an empty array's minimum stopped calibrate there)."""
    from place_safe.calibration.uncertainty import fit_diff_uncertainty
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    frames = make_frames(3, seed=1, scene=SceneSpec(z_range=(0.025, 0.04), theta_range=(0.0, 0.3)))
    assert all(f.truth.z0 < 0.05 for f in frames)
    unc, report = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak())
    assert unc is not None and "tilt_term_sized" not in report


def test_a_level_sweep_with_enough_tilted_frames_sizes_the_stated_term_on_them():
    """TILT_TERM_MIN_FRAMES or more tilted frames, still under DIFF_TILTED_SHARE of the frames: the term stays stated
    (the floor from the level frames alone) and is sized on the tilted ones; the report says so."""
    from place_safe.calibration.uncertainty import (DIFF_TILTED_SHARE, TILT_TERM_MIN_FRAMES, TILT_TERM_SCALES,
                                                    diff_tilt_term, fit_diff_uncertainty)
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    level = make_frames(22, seed=1, scene=SceneSpec(z_range=(0.06, 0.30), theta_range=(0.0, 0.0)))
    tilted = make_frames(TILT_TERM_MIN_FRAMES + 4, seed=2, scene=SceneSpec(z_range=(0.06, 0.30),
                                                                             theta_range=(0.2, 0.4)))
    frames = level + tilted
    assert len(tilted) / len(frames) < DIFF_TILTED_SHARE
    unc, report = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak())
    sized = report["tilt_term_sized"]
    assert report["tilt_term"].startswith("stated") and "then by the tilted frames" in report["tilt_term"]
    assert sized["frames"] >= TILT_TERM_MIN_FRAMES, sized
    stated = diff_tilt_term(None)
    lo, hi = TILT_TERM_SCALES
    assert lo * stated.tilt_rel <= unc.tilt_rel <= hi * stated.tilt_rel
    assert math.isclose(unc.tilt_rel, stated.tilt_rel * sized["tilt_factor"])
    assert math.isclose(unc.tilt_offset_rel, stated.tilt_offset_rel * sized["offset_factor"])
    for part in ("tilt", "offset"):  # each factor makes its frames' NEES 1, or sits at a bound
        k, after = sized[f"{part}_factor"], sized[f"nees_{part}_after"]
        assert k in TILT_TERM_SCALES or abs(after - 1.0) < 0.02, (part, k, after)
    assert report["frames"] <= len(level)  # the floor from the level frames alone
    assert "note" not in report  # measured: nothing to add


def _tilted(deg: float, azimuth: float = 0.3) -> np.ndarray:
    t, a = math.radians(deg), azimuth
    return np.array([math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)])


def test_a_unit_the_model_fits_worse_gets_a_wider_covariance_on_tilted_planes_and_the_same_on_level_ones():
    """Diff's stated tilt term grows with the unit's relative model error: on a plane tilted 20 deg the covariance of
    a unit the model misses by 8 % of the counts exceeds that of a unit it misses by 2 % (the difference positive
    definite: tilt components and offset); on a level plane the two are the same. Without a model error the stated
    values stand."""
    from place_safe.calibration.uncertainty import (DIFF_TILT_OFFSET_REL, DIFF_TILT_REL, diff_tilt_term)

    fit = np.diag([1e-6, 1e-6, 1e-8])
    good, bad = diff_tilt_term(0.02), diff_tilt_term(0.08)
    n, d = _tilted(20.0), 0.2
    more = bad.apply(fit, d, n) - good.apply(fit, d, n)
    assert np.linalg.eigvalsh(more).min() > 0.0
    assert bad.apply(fit, d, np.array([0.0, 0.0, 1.0])) == pytest.approx(good.apply(fit, d, np.array([0.0, 0.0, 1.0])))
    assert good.tilt_rel < bad.tilt_rel and good.tilt_offset_rel < bad.tilt_offset_rel
    for unknown in (None, math.nan, -0.1, math.inf):
        t = diff_tilt_term(unknown)
        assert (t.tilt_rel, t.tilt_offset_rel) == (DIFF_TILT_REL, DIFF_TILT_OFFSET_REL)


@settings(max_examples=80, deadline=None)
@given(st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)), st.floats(0.0, 89.0),
       st.floats(-math.pi, math.pi), st.floats(1e-3, 5.0), st.floats(1e-12, 1e-2), st.floats(0.0, 0.5))
def test_diffs_tilted_covariance_is_finite_and_positive_definite_for_any_model_error(e, deg, azimuth, offset, var, more):
    """For any model error (none, negative, NaN, infinite, huge) and any plane in front of the sensor, the covariance
    diff reports with the tilt term is finite, symmetric and positive definite, and a larger model error never
    shrinks it."""
    from place_safe.calibration.uncertainty import diff_tilt_term

    fit = np.diag([var, var, var * 1e-2])
    n = _tilted(deg, azimuth)
    c = diff_tilt_term(e).apply(fit, offset, n)
    assert np.all(np.isfinite(c)) and np.allclose(c, c.T) and np.linalg.eigvalsh(c).min() > 0.0
    if e is not None and math.isfinite(e) and e >= 0.0:
        bigger = diff_tilt_term(e + more).apply(fit, offset, n)
        assert np.linalg.eigvalsh(bigger - c).min() >= -1e-12 * np.abs(c).max()


def test_the_blend_holds_unless_the_choice_scores_clearly_better():
    """Calibration keeps the blend unless choosing diff's plane or peak's scores better on the held-out frames by more
    than both the paired standard error and 2 % of the blend's score."""
    from place_safe.calibration.uncertainty import _blend_holds

    rng = np.random.default_rng(0)
    base = rng.uniform(0.5, 1.5, size=(60, 2))
    assert _blend_holds(base, base)[0]  # a tie: the blend
    assert _blend_holds(base, base * 0.99)[0]  # 1 % better, consistently: within FALLBACK_SCORE_REL
    holds, scores = _blend_holds(base, base * 0.9)  # 10 % better on every frame
    assert not holds and scores["choice_score"] < scores["blend_score"]
    noisy = base * 0.95 + rng.normal(0.0, 1.0, size=base.shape)  # 5 % better on average, but scattered
    assert _blend_holds(base, noisy)[0]
    assert _blend_holds(base, base * 1.2)[0]  # the choice worse


def test_the_crosstalk_a_level_sweep_leaves_widens_diffs_tilt_term():
    """The forward fit's crosstalk, where a level sweep traded it against the fields of view, adds
    DIFF_TILT_PER_CROSSTALK times it to the tilt part and DIFF_TILT_OFFSET_PER_CROSSTALK times it to the offset part, in
    quadrature; the pivot stays; no crosstalk (None, NaN, negative, a bool) adds nothing, and a crosstalk of 0 neither."""
    from place_safe.calibration.uncertainty import (DIFF_TILT_OFFSET_PER_CROSSTALK, DIFF_TILT_PER_CROSSTALK,
                                                     diff_tilt_term)

    base = diff_tilt_term(0.02)
    wide = diff_tilt_term(0.02, 0.02)
    assert wide.tilt_rel == pytest.approx(math.hypot(base.tilt_rel, DIFF_TILT_PER_CROSSTALK * 0.02))
    assert wide.tilt_offset_rel == pytest.approx(math.hypot(base.tilt_offset_rel, DIFF_TILT_OFFSET_PER_CROSSTALK * 0.02))
    assert wide.tilt_pivot == base.tilt_pivot
    for none in (None, math.nan, -0.1, True, 0.0):
        assert diff_tilt_term(0.02, none) == base
    assert diff_tilt_term(None, 0.02).tilt_rel > diff_tilt_term(None).tilt_rel
    assert diff_tilt_term(1.0, 0.5).tilt_rel == 1.0  # the forward fit's largest crosstalk: held at the field's bound


def test_the_model_error_sizes_diffs_tilt_term_and_leaves_its_limits_alone(sweep_path):
    """Calibrated on the same level frames, a unit with a larger model error gets the larger tilt term, and the same
    fallback limits and scale: the planes diff returns do not depend on it (only their covariance on tilted planes)."""
    from place_safe.calibration.uncertainty import diff_tilt_term, fit_diff_uncertainty
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    frames = [f for f in load_frames(sweep_path) if 0.08 <= f.truth.z0 <= 0.2][:6]
    low, rep_low = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak(), model_error=0.02)
    high, rep_high = fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak(), model_error=0.08)
    assert (low.tilt_rel, low.tilt_offset_rel) == (diff_tilt_term(0.02).tilt_rel, diff_tilt_term(0.02).tilt_offset_rel)
    assert (high.tilt_rel, high.tilt_offset_rel) == (diff_tilt_term(0.08).tilt_rel, diff_tilt_term(0.08).tilt_offset_rel)
    assert (low.chi2_limit, low.prefer_ratio, low.consistency_limit) == (high.chi2_limit, high.prefer_ratio,
                                                                         high.consistency_limit)
    assert low.scale == pytest.approx(high.scale, rel=0.01) and rep_high["tilt_model_error"] == 0.08


# -- the peak method's near-range law (issue 26) ------------------------------------------------------------------

def _near_rows(n, scale, power, seed=0, shared=0.0, depths=(0.025, 0.09)):
    """Level planes at ``depths`` (m; default 2.5-9 cm) read through 9 zone points whose ranges err by the law's
    std, the part ``shared`` of its variance common to the zones of a frame, the rest independent."""
    from place_safe.calibration.uncertainty import near_std_law
    from place_safe.recovery.estimator import tilt_offset
    from place_safe.recovery.points import PeakParams, plane_through

    rng = np.random.default_rng(seed)
    dirs = PeakParams.default_peak().directions()
    rows = []
    for _ in range(n):
        d = rng.uniform(*depths)
        r = d / dirs[:, 2]
        mix = math.sqrt(1.0 - shared) * rng.normal(0.0, 1.0, 9) + math.sqrt(shared) * rng.normal()
        r = r + mix * near_std_law(r * dirs[:, 2], scale, power)
        points = r[:, None] * dirs
        valid = np.ones(9, dtype=bool)
        plane, _ = plane_through(points, valid)
        rows.append((points, valid, plane, tilt_offset(plane) - np.array([0.0, 0.0, d]), None))
    return rows


def test_near_law_grows_toward_the_internal_return_and_is_tabulated_through_the_table_end():
    from place_safe.calibration.uncertainty import NEAR_REFERENCE_DEPTH, near_law_depths, near_std_law
    from place_safe.recovery.too_close import OVERLAP_RANGE

    d = np.array([OVERLAP_RANGE + 0.004, 0.03, NEAR_REFERENCE_DEPTH, 0.09])
    s = near_std_law(d, 1e-4, 1.5)
    assert np.all(np.diff(s) < 0) and math.isclose(s[2], 1e-4)
    assert near_std_law(OVERLAP_RANGE - 0.005, 1e-4, 1.5) == near_std_law(OVERLAP_RANGE, 1e-4, 1.5)  # held, finite
    depths = near_law_depths(0.09, knots=[0.02, 0.035, 0.09])
    assert depths[-1] == 0.09 and np.all(np.diff(depths) > 0) and 0.035 in depths and depths[0] > OVERLAP_RANGE


def test_closer_than_its_nearest_frame_the_near_law_grows_at_least_as_the_real_sensors_did():
    """A sweep that starts at 5 cm cannot measure how fast the error grows toward the internal return: closer than
    the nearest fitted frame the law continues from its value there with the power at least NEAR_PRIOR_POWER; a
    steeper fitted law, and everything at or beyond the nearest frame, stay as fitted."""
    from place_safe.calibration.uncertainty import NEAR_PRIOR_POWER, fit_near_law, near_std_law
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.points import PeakParams
    from place_safe.recovery.too_close import OVERLAP_RANGE

    d = np.array([0.02, 0.03, 0.05, 0.07])
    flat = near_std_law(d, 1e-4, 0.3, nearest=0.05)
    assert np.allclose(flat[2:], near_std_law(d[2:], 1e-4, 0.3))  # at and beyond the nearest frame: as fitted
    gaps = d[:2] - OVERLAP_RANGE
    assert np.allclose(flat[:2] / flat[2], (gaps / (0.05 - OVERLAP_RANGE)) ** -NEAR_PRIOR_POWER)
    assert np.all(flat[:2] > near_std_law(d[:2], 1e-4, 0.3))
    assert np.allclose(near_std_law(d, 1e-4, 1.5, nearest=0.05), near_std_law(d, 1e-4, 1.5))  # steeper: unchanged

    params = PeakParams.default_peak()
    rows = _near_rows(40, 1e-4, 0.3, seed=4, depths=(0.05, 0.09))
    unc, rep = fit_near_law(rows, Uncertainty(), params, 0.09)
    assert rep["power"] < NEAR_PRIOR_POWER and rep["power_closer"] == NEAR_PRIOR_POWER
    nearest = rep["nearest_fitted_mm"] * 1e-3
    assert 0.05 <= nearest < 0.055
    s_near, s_2cm = unc.near_std(np.array([nearest, 0.02]))
    want = ((0.02 - OVERLAP_RANGE) / (nearest - OVERLAP_RANGE)) ** -NEAR_PRIOR_POWER
    assert s_2cm / s_near >= 0.95 * want  # (the table is read linearly between its depths)


def test_interpolation_measure_is_zero_at_the_knots_and_largest_mid_gap():
    from place_safe.calibration.uncertainty import interpolation_measure

    knots = [0.02, 0.035, 0.05, 0.09]
    m = interpolation_measure(np.array([0.02, 0.0275, 0.035, 0.04, 0.05, 0.07, 0.095]), knots)
    assert m[0] == m[2] == m[4] == 0.0 == m[6]
    assert math.isclose(m[1], 0.0075 ** 2) and 0 < m[3] < m[1] and math.isclose(m[5], 0.02 ** 2)
    assert interpolation_measure(0.015, knots) > 0  # before the first knot the table holds its value: not exact


def test_near_law_maximum_likelihood_recovers_a_known_law_and_makes_nees_one():
    from place_safe.calibration.uncertainty import fit_near_law
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.peak import PeakEstimator
    from place_safe.recovery.points import PeakParams

    params = PeakParams.default_peak()
    rows = _near_rows(80, 1e-4, 1.0, seed=1)  # zone errors well below the zones' spread: a linear regime
    unc, rep = fit_near_law(rows, Uncertainty(), params, 0.09)
    assert 0.7e-4 <= rep["std_at_reference_mm"] * 1e-3 <= 1.4e-4 and 0.5 <= rep["power"] <= 1.5
    assert rep["share_independent_of_knots"] == 1.0  # no table: nothing to interpolate
    assert rep["shared_by_zones"] < 0.3  # the zones erred independently
    test = _near_rows(80, 1e-4, 1.0, seed=2)
    est = PeakEstimator(params, unc)
    v = [r[3] @ np.linalg.solve(est.covariance(r[0], r[1], r[2]), r[3]) / 3 for r in test]
    assert 0.75 <= float(np.mean(v)) <= 1.3


def test_the_near_law_says_when_no_held_out_frame_lay_in_a_gap_as_narrow_as_a_new_frames():
    """A plain sweep's frames, left out, lie mid-way in gaps twice the table's spacing: the law's error at a new
    frame's gap is then extrapolated from them (through the held share) and the report says so, with the capture that
    fixes it (a second pass between the first's distances, whose frames held out lie at a new frame's gap)."""
    from place_safe.calibration.uncertainty import (NARROW_GAP_NOTE, NEAR_KNOT_SHARE, fit_near_law, near_std_law,
                                                    new_frame_measure)
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.points import PeakParams

    knots = [0.025, 0.029, 0.033, 0.037, 0.041, 0.045, 0.09]
    params = PeakParams.default_peak().replace(near_depths=knots, near_errors=[0.0] * (9 * len(knots)))
    m_new = new_frame_measure(knots)
    assert math.isclose(m_new, 0.002 ** 2)
    base = _near_rows(40, 1e-4, 1.0, seed=6)
    plain = [r[:4] + (m,) for r, m in zip(base, [m_new] + [4 * m_new, 9 * m_new] * 20)]  # one at the table's end
    unc, rep = fit_near_law(plain, Uncertainty(), params, 0.09)
    assert rep["held_out_at_new_frame_gaps"] == 1 and rep["note"] == NARROW_GAP_NOTE
    # the share that carries the wider gaps' error to a new frame's is held, not fitted: at a knot the stated
    # variance is NEAR_KNOT_SHARE of the law's (the zones' own variation does not shrink there)
    assert rep["share_independent_of_knots"] == NEAR_KNOT_SHARE and rep["share_how"] == "held (NEAR_KNOT_SHARE)"
    at = np.array([0.033])
    law = near_std_law(at, rep["std_at_reference_mm"] * 1e-3, rep["power"], rep["nearest_fitted_mm"] * 1e-3)
    stated = np.hypot(unc.near_std(at), unc.near_common(at))
    assert np.allclose(stated ** 2, NEAR_KNOT_SHARE * law ** 2, rtol=1e-6)
    interleaved = [r[:4] + (m,) for r, m in zip(base, np.resize([m_new, 4 * m_new, 9 * m_new], len(base)))]
    _, rep = fit_near_law(interleaved, Uncertainty(), params, 0.09)
    assert rep["held_out_at_new_frame_gaps"] == 14 and "note" not in rep
    assert math.isclose(rep["new_frame_measure_mm2"], 4.0)


def test_the_near_law_is_finite_when_most_held_out_rows_lie_on_a_knot():
    """Rows whose frame lies on a knot (or past the table's end) have measure 0; were most rows there, the median
    measure the factor divides by was 0 and calibrate stopped on a NaN near-range std (found in review)."""
    from place_safe.calibration.uncertainty import fit_near_law, new_frame_measure
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.points import PeakParams

    knots = [0.025, 0.029, 0.033, 0.037, 0.041, 0.045, 0.09]
    params = PeakParams.default_peak().replace(near_depths=knots, near_errors=[0.0] * (9 * len(knots)))
    base = _near_rows(10, 1e-4, 1.0, seed=6)
    m = new_frame_measure(knots)
    for measures in ([0.0] * 6 + [4 * m] * 4, [0.0] * 10):
        rows = [r[:4] + (v,) for r, v in zip(base, measures)]
        unc, rep = fit_near_law(rows, Uncertainty(), params, 0.09)
        assert np.all(np.isfinite(unc.near_range_std)) and np.all(np.isfinite(unc.near_common_std))
        assert math.isfinite(rep["nees_per_dof_held_out"]) and rep["reference_measure_mm2"] > 0


def test_near_law_finds_the_error_the_zones_share_and_keeps_tilt_and_offset_honest():
    """Zones that err together move the plane's offset, not its tilt: a law of independent zones would have to
    overstate the tilt error to cover the offset's (issue 26: the real sweep at 5-9 cm)."""
    from place_safe.calibration.uncertainty import fit_near_law
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.peak import PeakEstimator
    from place_safe.recovery.points import PeakParams

    params = PeakParams.default_peak()
    unc, rep = fit_near_law(_near_rows(80, 1e-4, 1.0, seed=3, shared=0.6), Uncertainty(), params, 0.09)
    assert 0.35 <= rep["shared_by_zones"] <= 0.85 and len(unc.near_common_std) == len(unc.near_depths)
    est = PeakEstimator(params, unc)
    test = _near_rows(120, 1e-4, 1.0, seed=4, shared=0.6)
    cov = [est.covariance(r[0], r[1], r[2]) for r in test]
    tilt = np.mean([r[3][:2] @ np.linalg.solve(c[:2, :2], r[3][:2]) / 2 for r, c in zip(test, cov)])
    offset = np.mean([r[3][2] ** 2 / c[2, 2] for r, c in zip(test, cov)])
    assert 0.7 <= tilt <= 1.4 and 0.7 <= offset <= 1.4


def test_the_common_part_never_takes_the_whole_near_law():
    """Zones whose errors are almost all common (a level sweep shows it through the offset alone) still keep at
    least (1 - NEAR_MAX_SHARED) of the law's variance each: the tilt is never stated from the offset's evidence."""
    from place_safe.calibration.uncertainty import NEAR_MAX_SHARED, fit_near_law
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.points import PeakParams

    unc, rep = fit_near_law(_near_rows(60, 1e-4, 1.0, seed=5, shared=0.99), Uncertainty(),
                            PeakParams.default_peak(), 0.09)
    assert rep["shared_by_zones"] <= NEAR_MAX_SHARED + 1e-12
    indep, common = np.array(unc.near_range_std), np.array(unc.near_common_std)
    assert np.all(indep ** 2 >= (1.0 - NEAR_MAX_SHARED) * (indep ** 2 + common ** 2) * (1 - 1e-9))


def test_a_range_error_the_zones_share_moves_the_offset_as_sampling_says():
    from place_safe.recovery.estimator import tilt_offset
    from place_safe.recovery.points import PeakParams, plane_covariance, plane_through

    dirs = PeakParams.default_peak().directions()
    r0 = 0.04 / dirs[:, 2]
    valid = np.ones(9, dtype=bool)
    plane, _ = plane_through(r0[:, None] * dirs, valid)
    indep, common = np.full(9, 2e-4), np.full(9, 3e-4)
    cov = plane_covariance(r0[:, None] * dirs, valid, plane, indep, replace_fit=True, common_std=common)
    rng = np.random.default_rng(5)
    samples = []
    for _ in range(4000):
        r = r0 + indep * rng.normal(size=9) + common * rng.normal()
        samples.append(tilt_offset(plane_through(r[:, None] * dirs, valid)[0]))
    sampled = np.cov(np.array(samples).T)
    assert np.allclose(np.diag(cov), np.diag(sampled), rtol=0.12)
    alone = plane_covariance(r0[:, None] * dirs, valid, plane, indep, replace_fit=True)
    assert cov[2, 2] > 5 * alone[2, 2] and np.allclose(cov[:2, :2], alone[:2, :2], rtol=0.05, atol=1e-12)


def test_calibrated_near_errors_replace_the_fit_residual():
    """Closer than the table's end the zones' calibrated errors stand for the fit's residual (a systematic pattern
    over the zones, which the residual of independent zones overstates as tilt); farther the fit's own."""
    from place_safe.recovery.points import PeakParams, plane_covariance, plane_through

    dirs = PeakParams.default_peak().directions()
    points = (0.03 / dirs[:, 2])[:, None] * dirs
    points[4] += 0.002 * dirs[4]  # a bowl: the centre reads 2 mm far
    valid = np.ones(9, dtype=bool)
    plane, _ = plane_through(points, valid)
    fit = plane_covariance(points, valid, plane)
    larger = plane_covariance(points, valid, plane, 1e-5)
    replaced = plane_covariance(points, valid, plane, 1e-5, replace_fit=True)
    assert np.allclose(larger, fit) and np.all(np.diag(replaced) < np.diag(fit) / 100)


# -- the near law's tabulation and parameters (issue 26c) ---------------------------------------------------------

from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=60, deadline=None)
@given(gaps=st.lists(st.floats(0.003, 0.02), min_size=1, max_size=12), first=st.floats(0.0165, 0.04),
       scale=st.floats(1e-5, 1e-3), power=st.floats(0.0, 4.0), shared=st.floats(0.0, 0.75), share=st.floats(0.0, 1.0),
       m_ref=st.floats(1e-6, 1e-3))
def test_the_stated_near_error_never_narrows_below_the_law_at_a_gap_midpoint(gaps, first, scale, power, shared,
                                                                              share, m_ref):
    """Read linearly between its depths, the tabulated law states at least what the law says at the midpoint of
    every gap between a table's knots, where a frame's interpolation error is largest (a logarithmic grid alone
    stated up to a third less there with 4 mm gaps)."""
    from place_safe.calibration.uncertainty import (interpolation_measure, knot_factor, near_law_table,
                                                    near_std_law)
    from place_safe.recovery.estimator import NEAR_MAX_STD, Uncertainty

    knots = list(first + np.concatenate([[0.0], np.cumsum(gaps)]))
    end = 0.09
    knots = [k for k in knots if k < end - 0.003] + [end]
    if len(knots) < 2:
        return
    unc = near_law_table(Uncertainty(), end, knots, scale, power, shared, share, m_ref)
    mid = (np.array(knots[:-1]) + np.array(knots[1:])) / 2
    stated = np.hypot(unc.near_std(mid), unc.near_common(mid))
    law = near_std_law(mid, scale, power) * np.sqrt(knot_factor(interpolation_measure(mid, knots), m_ref, share))
    assert np.all(stated >= np.minimum(law, NEAR_MAX_STD) * (1 - 1e-9))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1e4, 1e4), min_size=3, max_size=3))
def test_the_near_law_parameters_are_finite_and_bounded_wherever_the_optimiser_steps(x):
    """A far-out simplex vertex once overflowed math.exp and stopped `calibrate` on a simulated unit (seed 21)."""
    from place_safe.calibration.uncertainty import NEAR_MAX_POWER, NEAR_MAX_SHARED, near_law_parameters

    scale, power, shared = near_law_parameters(x)
    assert 0.0 <= scale <= 1.0 and 0.0 <= power <= NEAR_MAX_POWER and 0.0 <= shared <= NEAR_MAX_SHARED


def test_two_readings_a_level_sweep_left_widen_diffs_tilt_term_by_their_difference():
    """Where a level sweep did not tell its two readings of the zones' geometry apart, diff's stated tilt term takes, in
    quadrature, how differently it reads tilted planes under the other reading (reading_disagreement): the slope scale
    on the tilt part, the offset bias on the offset part; a sweep that told them apart, or a disagreement not known,
    adds nothing."""
    from place_safe.calibration.uncertainty import diff_tilt_term

    base = diff_tilt_term(0.02)
    wide = diff_tilt_term(0.02, None, {"slope_scale": -0.08, "offset_bias": 0.03})
    assert wide.tilt_rel == pytest.approx(math.hypot(base.tilt_rel, 0.08))
    assert wide.tilt_offset_rel == pytest.approx(math.hypot(base.tilt_offset_rel, 0.03))
    assert wide.tilt_pivot == base.tilt_pivot
    for none in (None, {}, {"frames": 3, "why": "too few"}, {"slope_scale": math.nan, "offset_bias": None}):
        assert diff_tilt_term(0.02, None, none) == base
    assert diff_tilt_term(0.02, None, {"slope_scale": 5.0, "offset_bias": -5.0}).tilt_rel == 1.0  # the field's bound


def test_the_other_reading_rendered_shows_how_diff_misreads_its_slopes():
    """reading_disagreement renders the same tilted planes with the kept forward model and with the other reading (here:
    edge and corner zones seen 15 % farther off the axis) and reads both with diff on the kept one: the other reading's
    planes come out steeper (its zones' ranges part more on a slope than the kept geometry expects), the kept one's as
    they are (a convention check of the comparison: both models are the renderer's own)."""
    from place_safe.calibration.uncertainty import DISAGREEMENT_FRAMES, reading_disagreement
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    kept = ForwardParams()
    level = make_frames(4, params=kept, spec=SyntheticSpec(theta_range=(0.0, 0.0)), seed=1)
    same = reading_disagreement(level, kept, kept, PeakParams.default_peak())
    assert same["frames"] >= DISAGREEMENT_FRAMES // 2 and abs(same["slope_scale"]) < 1e-6
    wide = reading_disagreement(level, kept, ForwardParams(edge_fov_scale=1.15, corner_fov_scale=1.15),
                                PeakParams.default_peak())
    assert 0.05 < wide["slope_scale"] < 0.2 and wide["angle_deg"] > 0.5


def test_diffs_tilt_term_takes_the_readings_only_where_the_sweep_left_both(monkeypatch):
    """The readings' disagreement is asked for only where the forward report says the level sweep did not tell them
    apart and keeps the other's params (other_reading), and then only where the term is stated from them: a sweep that
    told them apart, or with enough tilted frames (they show diff's slopes), gets none."""
    import place_safe.calibration.uncertainty as u
    from place_safe.calibration import Calibration
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    level = make_frames(12, spec=SyntheticSpec(theta_range=(0.0, 0.0)), seed=2)
    tilted = make_frames(12, spec=SyntheticSpec(theta_range=(0.2, 0.4)), seed=3)
    other = ForwardParams(edge_fov_scale=1.1).to_dict()
    for geometry, wanted in (({"told_apart": False, "other_params": other}, True),
                             ({"told_apart": True, "other_params": other}, False),
                             ({"told_apart": False}, False),
                             ({"told_apart": False, "other_params": {"edge_fov_scale": "wide"}}, False),
                             ({"told_apart": None, "other_params": other}, False),
                             ({"told_apart": 0, "other_params": other}, False),
                             ("free", False), ([1, 2], False), (None, False)):
        cal = Calibration(sections={"forward": ForwardParams().to_dict()}, reports={"forward": {"geometry": geometry}})
        got = u.other_reading(cal)
        assert (got is not None) is wanted
        if wanted:
            assert got.edge_fov_scale == 1.1
    for report in ("broken", None, []):  # a report of another shape: no readings, no error
        assert u.other_reading(Calibration(sections={"forward": ForwardParams().to_dict()},
                                           reports={"forward": report})) is None

    asked = []
    monkeypatch.setattr(u, "reading_disagreement", lambda *a, **k: asked.append(a) or {"slope_scale": 0.1})
    sweep = level + make_frames(18, spec=SyntheticSpec(theta_range=(0.0, 0.0)), seed=4)
    for frames, wanted in ((level, True), (sweep + tilted[:10], False)):  # 10 tilted among 40: level, term sized
        asked.clear()
        unc, rep = u.fit_diff_uncertainty(frames, ForwardParams(), PeakParams.default_peak(), model_error=0.02,
                                          other_reading=ForwardParams(edge_fov_scale=1.1))
        assert bool(asked) is wanted and (rep["tilt_readings"] == {"slope_scale": 0.1}) is wanted
        if wanted:
            assert unc.tilt_rel == pytest.approx(u.diff_tilt_term(0.02, None, {"slope_scale": 0.1}).tilt_rel)
        else:
            assert "tilt_term_sized" in rep and "tilt_factor" in rep["tilt_term_sized"]  # the tilted frames sized it


def test_a_mounted_units_frames_render_in_its_optical_frame_and_keep_their_truth_in_the_reported_one():
    """make_frames of a forward model with a mount tilt: the frames' truth is in the reported frame, so diff with the
    same model reads them as it reads an unmounted model's, and reading_disagreement of two readings that differ only
    by a mount the diff model holds is the mount's plain rotation, not a slope scale (a convention check of the
    comparison's rendering: both models are the renderer's own)."""
    from place_safe.calibration.uncertainty import reading_disagreement
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams

    spec = SyntheticSpec(z_range=(0.08, 0.25), theta_range=(0.1, 0.4), specular_weight_range=(0.0, 0.0), noise=False)
    mounted = ForwardParams(mount_tilt=[0.03, -0.02])  # 2 deg
    frames = make_frames(8, params=mounted, spec=spec, seed=6)
    est = DifferentiableEstimator(mounted, PeakParams.default_peak())
    for e, f in zip(est.estimate_many(frames), frames):
        assert e.ok and math.degrees(math.acos(min(1.0, float(e.plane.normal @ f.truth.normal)))) < 0.1
    level = make_frames(4, params=mounted, spec=SyntheticSpec(theta_range=(0.0, 0.0)), seed=1)
    same = reading_disagreement(level, mounted, mounted, PeakParams.default_peak())
    assert abs(same["slope_scale"]) < 1e-6 and same["angle_deg"] < 1e-4


def test_a_sweeps_own_tilt_centres_the_stated_tilt_terms():
    """sweep_slopes: the level frames' mean slopes (the tilted ones left out), 0 for a level table and below
    LEVEL_SLOPE; a peak calibration of frames whose table sat off the sensor's axis centres its stated term there."""
    from place_safe.calibration.uncertainty import LEVEL_SLOPE, fit_peak_uncertainty, sweep_slopes
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.geometry import Plane
    from place_safe.recovery.points import PeakParams

    normals = np.array([Plane.from_slopes(0.01, -0.004, 0.2).normal] * 3 + [Plane.from_slopes(0.3, 0.0, 0.2).normal])
    assert sweep_slopes(normals, np.array([False, False, False, True])) == pytest.approx([0.01, -0.004])
    assert sweep_slopes(np.array([[0.0, LEVEL_SLOPE / 2, 1.0]]), np.array([False])) == [0.0, 0.0]
    frames = make_frames(12, spec=SyntheticSpec(theta_range=(0.0, 0.0), z_range=(0.05, 0.3)), seed=4)
    for f in frames:
        f.truth = Plane(Plane.from_slopes(0.008, 0.0, f.truth.offset).normal, f.truth.offset)
    unc, _ = fit_peak_uncertainty(frames, PeakParams.default_peak())
    assert unc.tilt_about == pytest.approx([0.008, 0.0]) and unc.tilt_rel > 0


def test_a_mount_the_adopted_time_scales_may_have_taken_up_widens_both_methods_offsets_on_tilted_planes(monkeypatch):
    """Where calibrate adopted each zone's own time scale with the mount held level, the mount the free reading saw
    (mount_left) widens diff's offset part by ADOPTED_MOUNT_OFFSET_REL times it, in quadrature, and peak's mount term
    takes it as the unit's mount; a kept free reading, or a report of another shape, adds nothing."""
    import place_safe.calibration.uncertainty as u
    from place_safe.calibration import Calibration
    from place_safe.calibration.uncertainty import ADOPTED_MOUNT_OFFSET_REL, diff_tilt_term, mount_left
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.recovery.forward import ForwardParams

    def cal(geometry):
        return Calibration(sections={"forward": ForwardParams().to_dict()}, reports={"forward": {"geometry": geometry}})

    adopted = {"adopted": "nominal_time_scales", "told_apart": True, "free": {"mount_tilt_deg": [1.2, -0.9]}}
    assert mount_left(cal(adopted)) == pytest.approx(math.radians(1.5))
    for other in ({**adopted, "adopted": "free"}, {**adopted, "free": {"mount_tilt_deg": [math.nan, 0.0]}},
                  {**adopted, "free": "level"}, {"adopted": "nominal_time_scales"}, "broken", None):
        assert mount_left(cal(other)) is None
    base = diff_tilt_term(0.02)
    wide = diff_tilt_term(0.02, None, None, 0.02)
    assert wide.tilt_offset_rel == pytest.approx(math.hypot(base.tilt_offset_rel, ADOPTED_MOUNT_OFFSET_REL * 0.02))
    assert wide.tilt_rel == base.tilt_rel and diff_tilt_term(0.02, None, None, None) == base

    from place_safe.recovery.points import PeakParams

    seen = []
    real_fit = u.fit_peak_uncertainty
    frames = make_frames(10, spec=SyntheticSpec(theta_range=(0.0, 0.0), z_range=(0.05, 0.3)), seed=8)

    def spy(frames, peak, min_range=None, mount_tilt=None):
        seen.append(mount_tilt)
        return real_fit(frames, peak, min_range, mount_tilt)

    monkeypatch.setattr(u, "fit_peak_uncertainty", spy)
    for geometry, want in ((adopted, math.radians(1.5)), ({**adopted, "adopted": "free"}, 0.0)):
        c = cal(geometry)
        c.sections["peak"] = PeakParams.default_peak().to_dict()
        u.update_calibration(c, frames, "peak")
        assert float(np.hypot(*seen[-1])) == pytest.approx(want)


def test_a_sweep_with_few_near_frames_says_so_and_one_with_enough_does_not(sweep_path):
    """The near-range report counts the calibration frames read closer than the table's end (each by a table and far
    mapping fitted without it) and, with fewer than NEAR_LAW_FEW_FRAMES, carries the note that the covariance there
    rests on few frames (what calibrate prints): the real even half (27 frames, 4 of them read at 3.5-8 cm) gets it,
    the whole sweep (53 frames) does not."""
    from place_safe.calibration.points import fit_peak
    from place_safe.calibration.uncertainty import NEAR_LAW_FEW_FRAMES, fit_peak_uncertainty
    from place_safe.io.frame_file import load_frames

    frames = load_frames(sweep_path)
    for part, few in ((frames[0::2], True), (frames, False)):
        params, _ = fit_peak(part, progress=False)
        _, report = fit_peak_uncertainty(part, params)
        near = report["near_range"]
        assert (near["frames_read"] < NEAR_LAW_FEW_FRAMES) == few
        assert ("note" in near) == few
        if few:
            assert near["note"].startswith("near range from few frames") and f"on {near['frames_read']} " in near["note"]


def test_a_calibration_with_no_near_frame_states_a_near_law_that_covers_the_real_near_frames(sweep_path):
    """The real even half's frames from 9.5 cm on calibrate peak with no frame closer than the near-range table's end:
    its uncertainty states a near law up to its nearest frame (near_prior, with the note), and the odd half's planes at
    2-9 cm read through it are covered (mean NEES per dof below 2; without the law 26 at 2-5 cm and 38 at 5-9 cm: 3-5
    deg and 1-3 mm off, stated to a few hundredths). A calibration with near frames fits its own law and states none."""
    from place_safe.calibration.points import fit_peak
    from place_safe.calibration.uncertainty import NEAR_PRIOR_NOTE, fit_peak_uncertainty
    from place_safe.evaluation.metrics import nees
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery.peak import PeakEstimator

    frames = load_frames(sweep_path)
    far = [f for f in frames[0::2] if f.truth.z0 >= 0.095]
    params, _ = fit_peak(far, progress=False)
    unc, report = fit_peak_uncertainty(far, params)
    prior = report["near_range"]["prior"]
    nearest = min(f.truth.z0 for f in far)
    assert prior["nearest_mm"] == pytest.approx(nearest * 1e3)
    assert prior["note"] == NEAR_PRIOR_NOTE.format(cm=nearest * 100)
    assert unc.near_depths[-1] == pytest.approx(nearest) and unc.near_std(np.array([0.03]))[0] > 0.0
    near = [f for f in frames[1::2] if 0.02 <= f.truth.z0 < 0.09]
    est = PeakEstimator(params, unc)
    ests = [est.estimate(f) for f in near]
    used = [(e, f.truth) for e, f in zip(ests, near) if e.ok]
    assert len(used) >= 4
    assert float(np.mean(nees([e for e, _ in used], [t for _, t in used]))) < 2.0
    params_all, _ = fit_peak(frames[0::2], progress=False)
    _, report_all = fit_peak_uncertainty(frames[0::2], params_all)
    assert "prior" not in report_all["near_range"]


def test_the_zones_scatter_is_pooled_from_fits_through_all_nine_zones_and_read_by_fewer(sweep_path):
    """``pooled_zone_std``: the root of the mean residual variance of peak's own nine-zone fits less a tilted plane's
    part (no truth needed; frames with fewer zones left out), 0 with too few fits; ``fit_peak_uncertainty`` writes it,
    and a fit through three zones, whose own residual is zero, states it (without it only the floor, which is
    smaller)."""
    from place_safe.calibration import Calibration
    from place_safe.calibration.fit import fit_method
    from place_safe.calibration.uncertainty import ZONE_STD_MIN_FRAMES, fit_peak_uncertainty, pooled_zone_std
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator
    from place_safe.recovery.peak import zone_tilt_variance
    from place_safe.recovery.points import plane_fit_geometry, plane_through
    from place_safe.sensor.frame import Frame

    sweep = load_frames(sweep_path)
    cal = Calibration()
    fit_method(cal, sweep, "peak", progress=False, log=None)
    est = make_estimator("peak", cal)
    far = [f for f in sweep if 0.1 <= f.truth.z0 <= 0.4]
    s2 = []
    for f in far:
        points, valid = est.zone_points(f)
        assert valid.all()
        plane = plane_through(points, valid)[0]
        s2.append(float(plane_fit_geometry(points, valid, plane).sigma2) - zone_tilt_variance(plane))
    h = np.zeros_like(far[0].hists)
    h[:4] = far[0].hists[:4]
    std, report = pooled_zone_std(far + [Frame(h, far[0].reference)], est.params)  # (the four-zone frame left out)
    assert std == pytest.approx(math.sqrt(np.mean(s2)), rel=1e-12) and report["frames"] == len(far)
    assert pooled_zone_std(far[:ZONE_STD_MIN_FRAMES - 1], est.params)[0] == 0.0
    unc, report = fit_peak_uncertainty(sweep, cal.peak())
    assert unc.zone_std > 0.0 and report["zone_scatter"]["zone_std_mm"] == pytest.approx(unc.zone_std * 1e3)
    assert est.uncertainty.zone_std == pytest.approx(unc.zone_std, rel=1e-12)
    h = np.zeros_like(far[5].hists)
    h[[0, 1, 3]] = far[5].hists[[0, 1, 3]]
    points, valid = est.zone_points(Frame(h, far[5].reference))
    plane = plane_through(points, valid)[0]
    fit = plane_fit_geometry(points, valid, plane)
    assert fit.sigma2 == 0.0
    without = make_estimator("peak", Calibration.from_dict({**cal.to_dict(), "uncertainty": {
        **cal.to_dict()["uncertainty"], "peak": est.uncertainty.replace(zone_std=0.0).to_dict()}}))
    extra = est.covariance(points, valid, plane) - without.covariance(points, valid, plane)
    scatter = unc.zone_std ** 2 + zone_tilt_variance(plane)  # (the sweep's table sits a little off level)
    assert zone_tilt_variance(plane) < 0.1 * unc.zone_std ** 2
    assert np.allclose(extra, est.uncertainty.scale * scatter * fit.inverse, rtol=1e-9, atol=0)


def test_the_zones_scatter_of_a_sweep_with_tilted_frames_is_the_level_one():
    """A tilted plane's nine-zone residual holds the zones' tilt scatter (``ZONE_TILT_SCATTER``), which a partial fit
    states besides ``zone_std``: pooled from a sweep of level and tilted frames the scatter is the level frames' (the
    tilted ones' raw residuals read five times it); from tilted frames alone, the intercept of a line in
    ``(z0 tan)^2`` reads 0.083 mm against the level 0.041 (independent generator, one sensor; the stated tilt part
    removed on average instead read about 0.22 mm)."""
    import math as m

    from place_safe.calibration import Calibration
    from place_safe.calibration.fit import fit_method
    from place_safe.calibration.uncertainty import pooled_zone_std
    from place_safe.evaluation.independent import SceneSpec, make_frames
    from place_safe.recovery.points import plane_fit_geometry, plane_through
    from place_safe.recovery.peak import PeakEstimator

    level = make_frames(60, seed=1, scene=SceneSpec(z_range=(0.05, 0.40), theta_range=(0.0, 0.0)))
    tilted = make_frames(60, seed=2, scene=SceneSpec(z_range=(0.05, 0.30), theta_range=(m.radians(15), m.radians(30))))
    cal = Calibration()
    fit_method(cal, level, "peak", progress=False, log=None)
    params = cal.peak()
    flat, _ = pooled_zone_std(level, params)
    mixed, report = pooled_zone_std(level + tilted, params)
    steep, _ = pooled_zone_std(tilted, params)
    raw = []
    for f in tilted:
        points, valid = PeakEstimator(params).zone_points(f)
        if valid.all():
            raw.append(float(plane_fit_geometry(points, valid, plane_through(points, valid)[0]).sigma2))
    assert m.sqrt(np.mean(raw)) > 3.0 * flat
    assert mixed == pytest.approx(flat, rel=1e-9) and report["frames"] == 60
    assert flat < steep < 2.5 * flat
