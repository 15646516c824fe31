"""Differentiable-rendering recovery: round trips, the paper's mode, batching and bad input."""

import math

import numpy as np
import pytest

from place_safe.recovery import make_estimator
from place_safe.recovery.differentiable import DifferentiableEstimator, SolverOptions
from place_safe.recovery.blend import axis_state
from place_safe.recovery.forward import ForwardParams
from place_safe.evaluation.metrics import angular_error, linear_error, point_error
from place_safe.sensor.frame import Frame
from place_safe.evaluation.synthetic import SyntheticSpec, make_frames


@pytest.fixture(scope="module")
def frames():
    return make_frames(12, seed=11)


def _errors(ests, frames):
    ang = [math.degrees(angular_error(e.plane, f.truth)) for e, f in zip(ests, frames)]
    lin = [linear_error(e.plane, f.truth) * 1e3 for e, f in zip(ests, frames)]
    pt = [point_error(e.plane, f.truth) * 1e3 for e, f in zip(ests, frames)]
    return np.array(ang), np.array(lin), np.array(pt)


def test_round_trip_fast(frames):
    est = DifferentiableEstimator()
    ests = [est.estimate(f) for f in frames]
    assert all(e.ok for e in ests)
    ang, lin, pt = _errors(ests, frames)
    assert ang.mean() < 0.3 and lin.mean() < 0.2 and pt.mean() < 0.3
    # the model explains the histograms to the noise level: residual near 1
    assert np.median([e.residual for e in ests]) < 3.0
    # albedo recovered
    true_albedo = np.array([f.extra["meta"]["albedo"] for f in frames])
    got = np.array([e.albedo for e in ests])
    assert np.median(np.abs(got / true_albedo - 1)) < 0.1


def test_better_than_peak_initialisation(frames):
    diff = _errors(DifferentiableEstimator().estimate_many(frames), frames)[2].mean()
    peak = _errors(make_estimator("peak").estimate_many(frames), frames)[2].mean()
    assert diff < peak


def test_batch_equals_single(frames):
    est = DifferentiableEstimator()
    batch = est.estimate_batch(frames[:4])
    for f, b in zip(frames[:4], batch):
        s = est.estimate(f)
        np.testing.assert_allclose(s.plane.normal, b.plane.normal, atol=1e-6)
        assert s.plane.offset == pytest.approx(b.plane.offset, abs=1e-7)


def test_a_frame_does_not_depend_on_its_batch():
    """A frame 3 cm away solved alone and together with one 30 cm away (whose later peak widens the batch's
    window) gives the same plane: each frame's residual covers its own window only."""
    from place_safe.evaluation.independent import SceneSpec, make_frames as independent_frames

    near = independent_frames(1, seed=3, scene=SceneSpec((0.03, 0.031), (0.2, 0.25)))
    far = independent_frames(1, seed=4, scene=SceneSpec((0.29, 0.30), (0.0, 0.1)))
    est = DifferentiableEstimator()
    alone = est.estimate(near[0])
    together = est.estimate_many(near + far)[0]
    assert alone.ok and together.ok
    np.testing.assert_allclose(together.plane.normal, alone.plane.normal, atol=1e-9)
    assert together.plane.offset == pytest.approx(alone.plane.offset, abs=1e-10)
    assert together.residual == pytest.approx(alone.residual, rel=1e-9)


def test_residual_is_tested_on_the_bins_near_the_returns(frames):
    """The fit covers window_after_peak bins; the residual (the chi-square test) only test_window of them, so
    a longer fitted tail of faint bins does not dilute the test."""
    short = DifferentiableEstimator(options=SolverOptions(window_after_peak=24, test_window=24)).estimate(frames[0])
    long = DifferentiableEstimator(options=SolverOptions(window_after_peak=90, test_window=24)).estimate(frames[0])
    diluted = DifferentiableEstimator(options=SolverOptions(window_after_peak=90, test_window=90)).estimate(frames[0])
    assert long.residual == pytest.approx(short.residual, rel=0.3)
    assert diluted.residual < long.residual


@pytest.mark.slow
def test_paper_mode_agrees_with_fast():
    frames = make_frames(3, seed=5, spec=SyntheticSpec(z_range=(0.05, 0.25), theta_range=(0.0, 0.3)))
    fast = DifferentiableEstimator().estimate_many(frames)
    paper = DifferentiableEstimator(mode="paper", options=SolverOptions(paper_rays=512)).estimate_many(frames)
    assert all(e.ok for e in paper)
    for a, b, f in zip(fast, paper, frames):
        assert math.degrees(angular_error(a.plane, b.plane)) < 3.0
        assert abs(a.plane.z0 - b.plane.z0) < 3e-3
    ang_f, lin_f, _ = _errors(fast, frames)
    ang_p, lin_p, _ = _errors(paper, frames)
    assert ang_f.mean() <= ang_p.mean() + 0.05 and lin_f.mean() <= lin_p.mean() + 0.05


def test_mode_is_checked():
    with pytest.raises(ValueError):
        DifferentiableEstimator(mode="magic")


def _bad_frames(good: Frame):
    nan = good.hists.copy()
    nan[3, 20] = np.nan
    neg = good.hists.copy()
    neg[0, 0] = -5
    floor_only = np.full((9, 128), 100.0)
    saturated = good.hists.copy()
    saturated[:, 15:25] = 2 ** 24 - 1
    return {
        "nan": Frame(nan, good.reference),
        "negative": Frame(neg, good.reference),
        "floor only": Frame(floor_only, good.reference),
        "saturated": Frame(saturated, good.reference),
        "no reference": Frame(good.hists.copy(), None),
        "wrong shape": Frame(good.hists[:5].copy(), good.reference),
    }


@pytest.mark.parametrize("mode", ["fast", "paper"])
def test_bad_input_gives_reason(frames, mode):
    est = DifferentiableEstimator(mode=mode, options=SolverOptions(paper_rays=64, paper_iterations=5))
    for name, frame in _bad_frames(frames[0]).items():
        e = est.estimate(frame)
        assert e.plane is None, name
        assert e.reason, name
    many = est.estimate_many(list(_bad_frames(frames[0]).values()) + [frames[0]])
    assert [e.ok for e in many] == [False] * 6 + [True]


def test_a_degenerate_covariance_falls_back_to_peak(frames):
    """A diff plane whose covariance is zero or indefinite (a degenerate Jacobian) is not trusted: the peak
    estimate is returned, marked as such."""
    from place_safe.recovery.estimator import PlaneEstimate, Uncertainty

    est = DifferentiableEstimator(uncertainty=Uncertainty(chi2_limit=1e9))
    peak = est.init.estimate(frames[0])
    good = est.estimate(frames[0])
    assert good.method_used == "diff"
    for cov in (np.zeros((3, 3)), np.diag([1e-6, -1e-9, 1e-8]), np.full((3, 3), np.nan)):
        fake = PlaneEstimate(good.plane, albedo=good.albedo, residual=good.residual, covariance=cov,
                             method_used="diff")
        out = est._checked(fake, peak)
        assert out.method_used == "peak" and out.plane == peak.plane
    assert est._checked(good, peak) is good


def test_chi_square_fallback_returns_the_peak_estimate(frames):
    """Convention check (frames rendered by the forward model): a chi-square limit no frame meets makes
    diff return its peak initialisation, marked as such; without a limit diff reports itself."""
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.peak import PeakEstimator

    strict = DifferentiableEstimator(uncertainty=Uncertainty(chi2_limit=1e-9))
    never = DifferentiableEstimator(uncertainty=Uncertainty(chi2_limit=0.0))  # calibration: diff no better
    lenient = DifferentiableEstimator()
    peak = PeakEstimator()
    for f in frames[:3]:
        s, l, p = strict.estimate(f), lenient.estimate(f), peak.estimate(f)
        assert s.method_used == "peak" and np.allclose(s.plane.normal, p.plane.normal)
        assert s.plane.offset == pytest.approx(p.plane.offset)
        assert never.estimate(f).method_used == "peak"
        assert l.method_used == "diff"
        assert s.residual == pytest.approx(l.residual)  # diff's residual is what failed the test


@pytest.mark.parametrize("limit, tight, loose", [
    # the two estimates differ by more than the consistency limit allows under their covariances
    ("consistency_limit", 1e-12, 1e12),
    # diff keeps its plane only where its tilt variance is at most prefer_ratio times peak's
    ("prefer_ratio", 1e-12, 1e12),
])
def test_fallback_to_peak_when_peak_contradicts_or_reads_the_slope_better(frames, limit, tight, loose):
    """Convention check: a limit no frame meets returns peak's plane, marked as such; a limit every frame meets
    keeps diff."""
    from place_safe.recovery.estimator import Uncertainty

    never = DifferentiableEstimator(uncertainty=Uncertainty(**{limit: tight}))
    always = DifferentiableEstimator(uncertainty=Uncertainty(**{limit: loose}))
    for f in frames[:3]:
        n, a = never.estimate(f), always.estimate(f)
        assert n.method_used == "peak" and n.plane is not None
        assert a.method_used == "diff"


def test_covariance_is_symmetric_positive_and_shrinks_with_signal():
    """Convention check: the fit covariance of (n_x, n_y, d) is a valid covariance, and a brighter surface
    (more photons, less shot noise) gives a smaller one."""
    from place_safe.recovery.forward import ForwardParams

    est = DifferentiableEstimator(ForwardParams(model_error=0.0))
    dim = make_frames(1, seed=5, spec=SyntheticSpec(z_range=(0.25, 0.25), albedo_range=(0.3, 0.3)))[0]
    bright = make_frames(1, seed=5, spec=SyntheticSpec(z_range=(0.25, 0.25), albedo_range=(1.5, 1.5)))[0]
    covs = [est.estimate(f).covariance for f in (dim, bright)]
    for c in covs:
        assert c.shape == (3, 3) and np.allclose(c, c.T) and np.all(np.linalg.eigvalsh(c) > 0)
    assert np.trace(covs[1][:2, :2]) < np.trace(covs[0][:2, :2])


@pytest.mark.filterwarnings("ignore")
def test_diff_keeps_its_plane_only_when_every_fallback_test_passes():
    """Safety invariant (hypothesis): for any calibrated limits and any pair of estimates, diff returns its own
    plane (or, with ``blend``, its plane blended with peak's) only when its chi-square is under the limit, its
    covariance is positive definite, it agrees with peak, (without ``blend``) peak does not read the slope better and
    (with a calibrated fallback, or a blend) peak's plane is not closer than NEAR_FALLBACK_RANGE; otherwise exactly
    peak's plane and covariance, marked "peak". A blend lies between the two planes, component by component."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from place_safe.geometry import Plane
    from place_safe.recovery.diff_settings import BLENDED, NEAR_FALLBACK_RANGE
    from place_safe.recovery.differentiable import _positive_definite
    from place_safe.recovery.estimator import PlaneEstimate, Uncertainty

    est = DifferentiableEstimator()
    pos = st.floats(1e-9, 1e3, allow_nan=False)

    @settings(max_examples=300, deadline=None)
    @given(chi2_limit=st.one_of(st.just(math.inf), st.floats(0.0, 1e3)), consistency=st.one_of(st.just(math.inf), pos),
           prefer=st.one_of(st.just(math.inf), pos), residual=st.floats(0.0, 1e3), tilt=st.floats(0.0, 1.2),
           var_diff=st.floats(1e-12, 1.0), var_peak=st.floats(1e-12, 1.0), shift=st.floats(-0.2, 0.2),
           offset=st.floats(0.005, 0.4), blend=st.booleans())
    def check(chi2_limit, consistency, prefer, residual, tilt, var_diff, var_peak, shift, offset, blend):
        unc = Uncertainty(chi2_limit=chi2_limit, consistency_limit=consistency, prefer_ratio=prefer, blend=blend)
        est.uncertainty = unc
        d = PlaneEstimate(Plane.from_angles(tilt, 0.3, offset), albedo=1.0, residual=residual,
                          covariance=np.diag([var_diff, var_diff, var_diff * 1e-3]), method_used="diff")
        p = PlaneEstimate(Plane.from_angles(tilt + shift, 0.3, offset + shift * 0.01), residual=1e-4,
                          covariance=np.diag([var_peak, var_peak, var_peak * 1e-3]), method_used="peak")
        out = est._checked(d, p)
        near = (not math.isinf(chi2_limit) or blend) and p.plane.offset < NEAR_FALLBACK_RANGE
        gates = residual ** 2 <= chi2_limit and _positive_definite(d.covariance) and unc.consistent(d, p) and not near
        if gates and blend and out.method_used == BLENDED:  # both usable: between the two, with a covariance
            for k in range(3):  # (n_x, n_y, z0): the state the blend combines
                lo, hi = sorted((axis_state(d.plane)[0][k], axis_state(p.plane)[0][k]))
                assert lo - 1e-12 <= axis_state(out.plane)[0][k] <= hi + 1e-12
            assert np.all(np.linalg.eigvalsh(out.covariance) > 0) and out.residual == d.residual
        elif gates and (unc.prefers(d, p) or blend):  # kept (a blend whose weight is all diff's returns diff's own)
            assert out is d or (blend and out.plane is p.plane and out.covariance is p.covariance)
        else:
            assert out.method_used == "peak" and out.plane is p.plane and out.covariance is p.covariance

    check()


def test_a_calibrated_diff_returns_peak_closer_than_the_near_fallback_range():
    """Convention check (frames rendered by the forward model, which diff fits well): with a calibrated fallback,
    a frame closer than NEAR_FALLBACK_RANGE gets peak's plane although every other test passes; farther, diff's."""
    from place_safe.recovery.diff_settings import NEAR_FALLBACK_RANGE
    from place_safe.recovery.estimator import Uncertainty

    calibrated = DifferentiableEstimator(uncertainty=Uncertainty(chi2_limit=1e12, consistency_limit=1e12,
                                                                 prefer_ratio=1e12))
    near = make_frames(2, seed=3, spec=SyntheticSpec(z_range=(0.035, 0.04)))
    far = make_frames(2, seed=3, spec=SyntheticSpec(z_range=(0.15, 0.2)))
    for f in near:
        e = calibrated.estimate(f)
        assert e.ok and e.plane.offset < NEAR_FALLBACK_RANGE and e.method_used == "peak"
    assert all(calibrated.estimate(f).method_used == "diff" for f in far)


def test_the_albedo_series_scales_the_reported_albedo_and_leaves_the_plane(frames):
    """``RangeCorrection.albedo`` (a log-albedo series in z0) multiplies the reported albedo by ``exp(series(z0))``
    at the solver's z0 and moves nothing else; a factor beyond e^3 is not a correction and is refused."""
    from place_safe.exceptions import CalibrationError
    from place_safe.recovery.differentiable import RangeCorrection

    plain = DifferentiableEstimator()
    series = RangeCorrection(domain=[0.05, 0.40], albedo=[0.2, -0.3])
    scaled = DifferentiableEstimator(correction=series)
    for f in frames[:3]:
        a, b = plain.estimate(f), scaled.estimate(f)
        assert a.ok and b.ok and a.albedo is not None
        assert np.array_equal(a.plane.normal, b.plane.normal) and a.plane.offset == b.plane.offset
        # the solver's z0 is the uncorrected plane's axis crossing (no plane series here)
        assert b.albedo == pytest.approx(a.albedo * math.exp(series.log_albedo(a.plane.z0)), rel=1e-9)
    assert series.log_albedo(0.01) == series.log_albedo(0.05) == pytest.approx(0.5)  # outside: the nearer end
    assert series.log_albedo(math.sqrt(0.05 * 0.40)) == pytest.approx(0.2)  # a series in ln z0
    with pytest.raises(CalibrationError):
        RangeCorrection.from_dict({"domain": [0.05, 0.4], "albedo": [3.5]})


def test_a_valid_albedo_series_never_costs_the_plane(frames):
    """The largest albedo correction a file may hold moves the reported albedo by at most e^3 and leaves the plane."""
    from place_safe.config import field_interval
    from place_safe.recovery.differentiable import RangeCorrection

    _, hi = field_interval(RangeCorrection, "albedo")
    plain = DifferentiableEstimator()
    scaled = DifferentiableEstimator(correction=RangeCorrection(domain=[0.0, 0.01], albedo=[hi]))
    for f in frames[:2]:
        a, b = plain.estimate(f), scaled.estimate(f)
        assert a.ok and b.ok and b.plane.offset == a.plane.offset
        assert b.albedo == pytest.approx(a.albedo * math.exp(hi), rel=1e-9)


def test_with_the_ambient_option_the_plane_comes_back_from_frames_whose_ambient_piles_up():
    """Frames whose ambient (120 counts a bin as it arrives) went through the pile-up with the return: the solver
    with ``SolverOptions(ambient=True)`` compares the model with the counts above that ambient and finds the plane
    (the renderer's ambient term: tests/recovery/test_plane_renderer.py); without the option the same frame's
    residual is far above the noise (noise-free frame: 1.76 against 0.02)."""
    import torch

    from place_safe.evaluation.synthetic import default_reference
    from place_safe.geometry import Plane
    from place_safe.recovery.forward import ForwardModel, ForwardParams, ZoneRays

    params = ForwardParams(pileup=1e-6)
    model = ForwardModel(params, ZoneRays.stratified(8))
    truth = Plane.from_slopes(0.05, -0.03, 0.15)
    ref = np.asarray(default_reference(), dtype=float)
    ambient = np.full(9, 120.0)
    with torch.no_grad():
        h = model.render_plane(torch.as_tensor(truth.normal)[None], torch.as_tensor([truth.offset]),
                               torch.as_tensor([params.albedo]), torch.as_tensor(ref)[None],
                               ambient=torch.as_tensor(ambient)[None])[0].numpy()
    frame = Frame(hists=np.round(h + ambient[:, None]), reference=ref, truth=truth)
    est = DifferentiableEstimator(params, options=SolverOptions(ambient=True)).estimate(frame)
    assert est.ok and math.degrees(angular_error(est.plane, truth)) < 0.05
    assert abs(est.plane.offset - truth.offset) < 1e-4
    # the residual (the chi-square test) sees the ambient's shadow only when it is modelled
    plain = DifferentiableEstimator(params).estimate(frame)
    assert est.residual < 0.1 < 1.0 < plain.residual


def test_an_albedo_the_frame_does_not_determine_is_not_reported():
    """A saturated return (bright table 5 cm away, independent generator) no longer grows with the albedo: the solver's
    log albedo has no posterior bound and ran to its upper bound (1e4); diff reports no albedo there, its plane still,
    and keeps reporting the albedo of unsaturated returns."""
    from place_safe.evaluation.independent import SceneSpec
    from place_safe.evaluation.independent import make_frames as independent_frames

    tilt = (0.15, 0.25)
    near = independent_frames(4, seed=4, scene=SceneSpec(z_range=(0.05, 0.055), theta_range=tilt,
                                                         albedo_range=(1.45, 1.5)))
    far = independent_frames(4, seed=5, scene=SceneSpec(z_range=(0.15, 0.25), theta_range=tilt,
                                                        albedo_range=(0.8, 1.0)))
    est = DifferentiableEstimator()
    for f in near:
        e = est.estimate(f)
        assert e.plane is not None and e.albedo is None
    for f in far:
        e = est.estimate(f)
        assert e.plane is not None and e.albedo is not None and math.isfinite(e.albedo) and e.albedo > 0


def test_the_unit_ambient_slope_sets_the_floor_diff_subtracts():
    """With a calibrated ``ambient_slope`` diff compares the model with the counts above the sloping floor: the first
    bins of a frame whose ambient slopes that way hold nothing but noise; with a flat floor they hold the slope."""
    from place_safe.recovery.forward import ForwardParams

    rng = np.random.default_rng(1)
    u = np.arange(128) / 127.0
    hists = rng.poisson(np.broadcast_to(100.0 * (1.0 - 0.3 * (u - 0.5)), (1, 9, 128))).astype(float)
    sloped, _ = DifferentiableEstimator(ForwardParams(ambient_slope=-0.3))._observed(hists)
    flat, _ = DifferentiableEstimator(ForwardParams())._observed(hists)
    assert sloped[..., :6].mean() < 8.0 < 20.0 < flat[..., :6].mean()  # (clipped noise: ~4)


def test_a_frames_own_crosstalk_mends_the_slopes_a_wrong_calibrated_crosstalk_reads_steep():
    """Convention check (the project's model renders and recovers): tilted frames of a unit whose crosstalk is 0.004 read
    by a model that holds 0.02 (what a level sweep may fit: it trades the crosstalk against the fields of view) come out
    steep; solved with each frame's own crosstalk under a prior about 0.02, the slopes come back and the fits improve. Held (crosstalk_std 0), the solver is the one without the unknown."""
    from dataclasses import replace

    true = ForwardParams(crosstalk=0.004)
    frames = make_frames(8, true, SyntheticSpec(z_range=(0.08, 0.25), theta_range=(math.radians(15), math.radians(30))),
                         seed=5)
    wrong = true.model_copy(update={"crosstalk": 0.02})
    held = DifferentiableEstimator(wrong).estimate_many(frames)
    free = DifferentiableEstimator(wrong, options=replace(SolverOptions(), crosstalk_std=0.01))
    got = free.estimate_many(frames)
    e_held = np.mean([math.degrees(angular_error(e.plane, f.truth)) for e, f in zip(held, frames)])
    e_free = np.mean([math.degrees(angular_error(e.plane, f.truth)) for e, f in zip(got, frames)])
    assert e_free < 0.5 * e_held and e_free < 0.15
    assert np.median([e.residual for e in got]) < np.median([e.residual for e in held])
    same = DifferentiableEstimator(wrong, options=replace(SolverOptions(), crosstalk_std=0.0)).estimate_many(frames)
    assert all(np.allclose(a.plane.normal, b.plane.normal, rtol=0, atol=1e-12) for a, b in zip(same, held))


def test_a_solve_that_fails_numerically_costs_its_own_frame_only_and_falls_back_where_calibrated(monkeypatch):
    """A numerical failure in diff's batch solve (a calibration's saturation of 1e308 did it to every frame) is
    retried frame by frame: the other frames of the batch keep diff's planes, and the failing one gets peak's plane
    where a fallback is calibrated, or no plane and the reason where not -- never the batch lost."""
    import json
    from pathlib import Path

    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.sensor.frame import Frame

    raw = json.loads((Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json").read_text())
    frames = [Frame.from_dict(d) for d in raw[20:23]]
    bad = frames[1]
    real = DifferentiableEstimator._solve_fast

    def solve(self, sub, inits):
        if any(f is bad for f in sub):
            raise np.linalg.LinAlgError("SVD did not converge")
        return real(self, sub, inits)

    monkeypatch.setattr(DifferentiableEstimator, "_solve_fast", solve)
    plain = DifferentiableEstimator().estimate_many(frames)
    assert plain[0].ok and plain[2].ok and plain[1].plane is None and "numerically" in plain[1].reason
    calibrated = DifferentiableEstimator(uncertainty=Uncertainty(chi2_limit=1e6)).estimate_many(frames)
    assert calibrated[1].ok and calibrated[1].method_used == "peak"
    assert calibrated[0].method_used != "peak" or calibrated[2].method_used != "peak"
