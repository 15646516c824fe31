"""Forward-model calibration: known parameters come back; the real sweep calibrates within targets."""

import math
from pathlib import Path

import numpy as np
import pytest

from place_safe.calibration.forward_fit import fit_forward
from place_safe.recovery.differentiable import DifferentiableEstimator
from place_safe.exceptions import CalibrationError
from place_safe.recovery.forward import ForwardParams
from place_safe.io.frame_file import load_frames
from place_safe.evaluation.metrics import angular_error, linear_error
from place_safe.evaluation.synthetic import SyntheticSpec, make_frames

SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"


@pytest.mark.slow
def test_recovers_known_parameters():
    truth = ForwardParams(bin_offset=9.1, saturation=400.0, soft_bin_sigma=0.6,
                          zone_offsets=[0.3, -0.2, 0.1, 0.0, 0.0, -0.3, 0.2, 0.4, -0.1],
                          zone_gains=[1.1, 0.9, 1.2, 1.0, 1.0, 0.8, 1.05, 0.95, 1.15],
                          mount_tilt=[0.01, -0.02])
    spec = SyntheticSpec(z_range=(0.05, 0.3), theta_range=(0.0, 0.4), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=False, rays=6)
    frames = make_frames(24, params=truth, spec=spec, seed=3)  # ground truth in the reported frame, as the fit's
    fitted = {"bin_offset": "lin", "saturation": "log", "soft_bin_sigma": "log", "zone_offsets": "lin",
              "zone_gains": "log", "mount_tilt": "lin"}
    got, report = fit_forward(frames, init=ForwardParams(), progress=False, rays=6, iterations=40, fitted=fitted)
    assert got.bin_offset == pytest.approx(truth.bin_offset, abs=0.02)
    assert got.saturation == pytest.approx(truth.saturation, rel=0.05)
    assert got.soft_bin_sigma == pytest.approx(truth.soft_bin_sigma, abs=0.02)
    np.testing.assert_allclose(got.zone_offsets, truth.zone_offsets, atol=0.02)
    np.testing.assert_allclose(got.zone_gains, truth.zone_gains, rtol=0.03)
    np.testing.assert_allclose(got.mount_tilt, truth.mount_tilt, atol=2e-3)
    assert report["rms_scaled_residual_after"] < 0.1 * report["rms_scaled_residual_before"]
    # the solver stopped on its convergence test and says so; these frames determine what they were made from
    assert report["converged"] and report["why"].startswith("converged")
    assert report["posterior_std"]["bin_offset"]["determined"]
    assert report["posterior_std"]["bin_offset"]["std"] < 0.02


def test_needs_frames_with_ground_truth():
    frames = make_frames(2, seed=1)
    with pytest.raises(CalibrationError):
        fit_forward(frames, progress=False)
    for f in frames:
        f.truth = None
    with pytest.raises(CalibrationError):
        fit_forward(frames * 3, progress=False)


@pytest.mark.slow
def test_real_sweep_cross_validated_within_targets():
    """Calibrate on the even frames of the real sweep, recover the odd ones at 5-40 cm."""
    frames = load_frames(SWEEP)
    train, test = frames[0::2], [f for f in frames[1::2] if 0.05 <= f.truth.z0 <= 0.40]
    from place_safe.calibration.points import fit_peak

    params, report = fit_forward(train, progress=False)
    peak, _ = fit_peak(train, progress=False)
    est = DifferentiableEstimator(params, peak)
    ests = est.estimate_many(test)
    assert all(e.ok for e in ests)
    ang = np.mean([math.degrees(angular_error(e.plane, f.truth)) for e, f in zip(ests, test)])
    lin = np.mean([linear_error(e.plane, f.truth) * 1e3 for e, f in zip(ests, test)])
    assert ang <= 0.8, f"mean angular error {ang:.2f} deg"
    assert lin <= 1.0, f"mean linear error {lin:.2f} mm"


@pytest.mark.slow
def test_chooses_where_the_zone_gains_act_convention_check():
    """Convention check (frames of the model itself): close frames, where the SPADs saturate, tell gains that
    saturate with the flux from gains that scale the saturated counts; the fit finds which from the middle."""
    for truth_w in (0.0, 1.0):
        truth = ForwardParams(saturate_gain=truth_w, zone_gains=[1.3, 0.8, 1.2, 0.9, 1.0, 0.7, 1.1, 0.85, 1.25])
        spec = SyntheticSpec(z_range=(0.015, 0.12), theta_range=(0.0, 0.3), specular_weight_range=(0.14681, 0.14681),
                             specular_exponent_range=(1.8378, 1.8378), noise=False, rays=5)
        frames = make_frames(16, params=truth, spec=spec, seed=5)
        fitted = {"saturate_gain": "unit", "zone_gains": "log"}
        got, report = fit_forward(frames, init=ForwardParams(saturate_gain=0.5), progress=False, rays=5, iterations=30,
                                  fitted=fitted, min_distance=0.01)
        assert got.saturate_gain == pytest.approx(truth_w, abs=0.1)
        assert report["structural_choices"]["saturate_gain"] == pytest.approx(got.saturate_gain)


@pytest.mark.slow
def test_a_level_sweep_never_fits_a_tilt_gain():
    """Over a level table the slope error is minus the estimated slope: a 'gain' of -1 would fit it exactly
    and then read every plane as the sweep's level. The gain needs true slopes that differ; the offset
    correction is still fitted."""
    from place_safe.calibration.plane_correction import fit_range_correction

    frames = load_frames(SWEEP)
    forward = ForwardParams.load(Path(__file__).resolve().parents[2] / "sim" / "sensors" / "tmf8820_real.json")
    section, report = fit_range_correction(frames, forward, progress=False)
    corr = section["range_correction"]
    assert corr["gain_a"] == [] and corr["gain_b"] == []
    assert "gain_a_why_not" in report and "gain_b_why_not" in report


def test_reference_floor_is_the_one_the_frames_fit_better_with():
    """The pulse model's reference floor is not fitted: calibration starts from the floor measured in the
    references and from the published 135 counts, and goes on with the one whose coarse fit ends lower (each also
    starts better here). Frames of the independent generator (references on a floor of 3 counts) take the measured
    one; frames rendered by the forward model itself (which subtracts 135) take 135 (a convention check)."""
    from place_safe.evaluation import independent

    indep = independent.make_frames(12, seed=4)
    _, report = fit_forward(indep, progress=False, iterations=1)
    assert report["ref_floor"]["chosen"] == "measured" and report["ref_floor"]["counts"] == pytest.approx(3.0, abs=1.0)
    own = make_frames(12, seed=4)
    _, report = fit_forward(own, progress=False, iterations=1)
    assert report["ref_floor"]["chosen"] == "published"
    assert report["ref_floor"]["counts"] == pytest.approx(ForwardParams().ref_floor)
    assert report["ref_floor"]["published"]["rms_scaled_residual_at_start"] < \
        report["ref_floor"]["measured"]["rms_scaled_residual_at_start"]


def _level_frames(n: int, albedo_range=(1.0, 1.0), seed: int = 4):
    spec = SyntheticSpec(z_range=(0.15, 0.35), theta_range=(0.0, 0.0), albedo_range=albedo_range,
                         specular_weight_range=(0.14681, 0.14681), specular_exponent_range=(1.8378, 1.8378),
                         noise=True, rays=4)
    return make_frames(n, params=ForwardParams(bin_offset=9.3), spec=spec, seed=seed)


def test_a_parameter_the_frames_cannot_determine_stays_at_its_prior():
    """Far from saturation a level sweep says nothing about the saturation level: with a prior it stays at the prior
    mean and the report says it is held there (posterior std about the prior's), while the bin offset, which the
    frames determine, moves to its true value and is not held."""
    from place_safe.calibration.forward_fit import PRIORS

    frames = _level_frames(6)
    fitted = {"bin_offset": "lin", "saturation": "log"}
    prior = {"saturation": (2000.0, 0.5), "bin_offset": (9.5, 4.0)}
    got, report = fit_forward(frames, init=ForwardParams(saturation=2000.0), progress=False, rays=3, iterations=20,
                              fitted=fitted, priors=prior, coarse_rays=0)
    assert got.bin_offset == pytest.approx(9.3, abs=0.05)
    spread = report["posterior_std"]
    assert "bin_offset" not in spread["held_at_prior"]
    if "saturation" in spread["held_at_prior"]:
        assert got.saturation == pytest.approx(2000.0, rel=0.3)
    assert report["prior_chi2"] >= 0.0
    assert set(PRIORS) >= {"crosstalk_grid", "glass_gains", "glass_delay", "echo_gain", "centre_fov_scale"}


def test_a_level_sweep_reports_the_crosstalk_and_the_fields_of_view_as_not_determined():
    """A level sweep trades the crosstalk against the edge and corner fields of view (LEVEL_SWEEP_TRADED): whatever
    their Gauss-Newton spread, the report says they are not determined there, and why; frames tilted 0-23 deg (from
    the same sensor) are judged by their spread alone."""
    from place_safe.calibration.forward_fit import LEVEL_SWEEP_TRADED

    fitted = {"bin_offset": "lin", "crosstalk": "log", "edge_fov_scale": "log", "corner_fov_scale": "log"}
    _, level = fit_forward(_level_frames(6), progress=False, rays=3, iterations=8, fitted=fitted, coarse_rays=0)
    spread = level["posterior_std"]
    for name in ("crosstalk", "edge_fov_scale", "corner_fov_scale"):
        assert not spread[name]["determined"] and spread[name]["level_sweep"] == LEVEL_SWEEP_TRADED[name]
        assert name in spread["not_determined"]
    assert "level_sweep" not in spread["bin_offset"]
    spec = SyntheticSpec(z_range=(0.05, 0.3), theta_range=(0.1, 0.4), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=True, rays=4)
    tilted = make_frames(6, params=ForwardParams(bin_offset=9.3), spec=spec, seed=5)
    _, tilt = fit_forward(tilted, progress=False, rays=3, iterations=8, fitted=fitted, coarse_rays=0)
    assert all("level_sweep" not in tilt["posterior_std"][name] for name in fitted)


def test_one_surface_is_tied_only_when_the_albedos_agree():
    """Asked to decide (``same_surface=None``), frames of one surface (a level table) have their albedos tied to one
    value; frames of surfaces drawn at random (albedo 0.3-1.7x) are not."""
    fitted = {"bin_offset": "lin"}
    _, one = fit_forward(_level_frames(5), progress=False, rays=3, iterations=5, fitted=fitted, coarse_rays=0,
                         same_surface=None)
    _, many = fit_forward(_level_frames(8, albedo_range=(0.3, 1.7), seed=9), progress=False, rays=3, iterations=5,
                          fitted=fitted, coarse_rays=0, same_surface=None)
    _, default = fit_forward(_level_frames(5), progress=False, rays=3, iterations=5, fitted=fitted, coarse_rays=0)
    assert one["one_surface"]["tied"] and one["one_surface"]["albedo_cv_after"] < 0.05
    assert not many["one_surface"]["tied"]
    assert not default["one_surface"]["tied"]  # by default each frame keeps its own albedo


def test_unit_terms_fitted_from_zero_get_derivatives():
    """An echo and a glass return fitted from an ``init`` that has none (zero, their lower bound) still move: the
    fit renders them while it differentiates."""
    from place_safe.calibration.forward_fit import UNIT_TERMS

    truth = ForwardParams(bin_offset=9.3, echo_gain=0.3, glass_gains=[40.0] * 9)
    spec = SyntheticSpec(z_range=(0.08, 0.3), theta_range=(0.0, 0.0), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=False, rays=4)
    frames = make_frames(5, params=truth, spec=spec, seed=2)
    fitted = {"echo_gain": UNIT_TERMS["echo_gain"], "glass_gains": UNIT_TERMS["glass_gains"]}
    got, _ = fit_forward(frames, init=ForwardParams(bin_offset=9.3), progress=False, rays=4, iterations=10,
                         fitted=fitted, coarse_rays=0, priors={})
    assert got.echo_gain > 0.1
    np.testing.assert_allclose(got.glass_gains, 40.0, rtol=0.2)


def test_pulse_terms_come_back_from_frames_made_with_them():
    """Frames rendered with per-bin pile-up only (no shadowing of later bins) and with wider / skewed zone pulses:
    fitted from the model as it was (Coates, the reference's shape), the terms move to what made the frames."""
    from place_safe.calibration.forward_fit import PULSE_TERMS

    widths = [0.08, -0.04, 0.1, 0.0, 0.0, 0.05, -0.02, 0.12, 0.06]
    truth = ForwardParams(bin_offset=9.3, pileup=1e-5, pileup_shadow=0.0, zone_pulse_widths=widths,
                          zone_pulse_skews=[0.05] * 9)
    spec = SyntheticSpec(z_range=(0.06, 0.3), theta_range=(0.0, 0.0), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=False, rays=4)
    frames = make_frames(6, params=truth, spec=spec, seed=2)
    got, report = fit_forward(frames, init=ForwardParams(bin_offset=9.3, pileup=1e-5), progress=False, rays=4,
                              iterations=15, fitted=dict(PULSE_TERMS), coarse_rays=0, priors={})
    assert got.pileup_shadow < 0.1
    np.testing.assert_allclose(got.zone_pulse_widths, widths, atol=0.02)
    np.testing.assert_allclose(got.zone_pulse_skews, 0.05, atol=0.02)
    assert report["rms_scaled_residual_after"] < 0.1 * report["rms_scaled_residual_before"]


def test_the_tdc_terms_come_back_from_frames_made_with_them():
    """Frames rendered with a bin-to-bin pattern of bin widths and a bowed time warp: fitted from nominal bins
    (``DNL_TERMS``, ``INL_TERMS``), the widths of the bins the returns cover and the warp where they fall come back."""
    import torch

    from place_safe.calibration.forward_fit import DNL_TERMS, INL_TERMS
    from place_safe.recovery.forward import bin_widths, warp_positions
    from place_safe.sensor.frame import N_BINS

    gains = list(1.0 + 0.04 * (-1.0) ** np.arange(N_BINS) * np.cos(np.arange(N_BINS) * 0.3))
    warp = [0.0, 0.0, 0.3, -0.2, 0.25, 0.0] + [0.0] * 11
    truth = ForwardParams(bin_offset=9.3, bin_gains=gains, time_warp=warp)
    spec = SyntheticSpec(z_range=(0.1, 0.3), theta_range=(0.0, 0.0), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=False, rays=4)
    frames = make_frames(8, params=truth, spec=spec, seed=3)
    got, report = fit_forward(frames, init=ForwardParams(bin_offset=9.3), progress=False, rays=4, iterations=15,
                              fitted={**DNL_TERMS, **INL_TERMS}, coarse_rays=0,
                              priors={"bin_gains": (1.0, 0.03), "time_warp": (0.0, 0.3)})
    covered = slice(20, 34)
    np.testing.assert_allclose(bin_widths(torch.tensor(got.bin_gains, dtype=torch.float64))[covered],
                               bin_widths(torch.tensor(gains, dtype=torch.float64))[covered], atol=0.01)
    where = torch.tensor([16.0, 20.0, 24.0, 28.0, 32.0], dtype=torch.float64)  # the warp (less its line) there
    np.testing.assert_allclose(warp_positions(where, got.time_warp)[0], warp_positions(where, warp)[0], atol=0.05)
    assert report["rms_scaled_residual_after"] < 0.1 * report["rms_scaled_residual_before"]


def test_the_ambient_option_fits_and_says_why_it_stopped():
    """``fit_forward(..., ambient=True)`` (the ambient through the pile-up, compared above the ambient of bins 0-7)
    fits synthetic frames as well as the floor-subtracted fit and reports whether and why it stopped."""
    spec = SyntheticSpec(z_range=(0.08, 0.3), theta_range=(0.0, 0.0), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=True, rays=4)
    frames = make_frames(6, params=ForwardParams(bin_offset=9.3, pileup=1e-6), spec=spec, seed=4)
    fitted = {"bin_offset": "lin", "pileup": "log"}
    init = ForwardParams(bin_offset=9.0, pileup=5e-7)
    _, plain = fit_forward(frames, init=init, progress=False, rays=4, iterations=15, fitted=fitted, coarse_rays=0)
    _, amb = fit_forward(frames, init=init, progress=False, rays=4, iterations=15, fitted=fitted, coarse_rays=0,
                         ambient=True)
    assert amb["converged"] and amb["why"]
    assert amb["rms_scaled_residual_after"] < 0.5 * amb["rms_scaled_residual_before"]
    assert amb["rms_scaled_residual_after"] < 1.2 * plain["rms_scaled_residual_after"]


def test_the_zones_time_scales_come_back_from_a_level_sweep():
    """Level frames rendered with each zone's own time scale (``zone_bin_scales``) and timing offset: fitted from ones
    (``ZONE_SCALE_TERMS``, the centre zone's the gauge), both come back, the scales to 0.2 %, and the report says
    they are determined."""
    from place_safe.calibration.forward_fit import ZONE_SCALE_TERMS

    scales = [1.012, 0.99, 1.0, 1.008, 1.0, 0.985, 0.984, 1.005, 1.011]
    offsets = [0.1, -0.2, 0.0, 0.15, 0.0, 0.2, 0.1, -0.1, -0.05]
    truth = ForwardParams(bin_offset=9.3, zone_bin_scales=scales, zone_offsets=offsets)
    spec = SyntheticSpec(z_range=(0.05, 0.4), theta_range=(0.0, 0.0), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=False, rays=4)
    frames = make_frames(8, params=truth, spec=spec, seed=3)
    got, report = fit_forward(frames, init=ForwardParams(bin_offset=9.3), progress=False, rays=4, iterations=15,
                              fitted={"zone_offsets": "lin", **ZONE_SCALE_TERMS}, coarse_rays=0)
    np.testing.assert_allclose(got.zone_bin_scales, scales, atol=0.002)
    np.testing.assert_allclose(got.zone_offsets, offsets, atol=0.03)
    assert report["converged"]
    assert "zone_bin_scales" not in report["posterior_std"]["not_determined"]


def test_tilted_frames_give_back_the_zones_time_scales_with_the_geometry():
    """Convention check (noisy frames rendered by the model it fits; the fit's accuracy on units that differ from the
    model is the scorecard's, docs/results.md "A few tilted frames: each zone's own time scale with the geometry"):
    frames tilted 10-30 deg, rendered with each zone's own time scale and a mount 1.2 deg off, fitted from the nominal
    geometry and ones with the scales, the mount and the fields of view free (the geometry and scales of
    :data:`SCALES_AND_GEOMETRY_FITTED`): all come back (the scales to 0.2 %, the mount to 0.1 deg, the fields of view to
    1 %) and the report calls each determined; level frames of the same unit leave the fields of view undetermined."""
    from place_safe.calibration.forward_fit import ZONE_SCALE_TERMS

    scales = [1.012, 0.99, 1.0, 1.008, 1.0, 0.985, 0.984, 1.005, 1.011]
    mount = [math.radians(0.9), math.radians(-0.8)]
    truth = ForwardParams(bin_offset=9.3, zone_bin_scales=scales, mount_tilt=mount)
    fitted = {"mount_tilt": "lin", "edge_fov_scale": "log", "corner_fov_scale": "log", **ZONE_SCALE_TERMS}
    for tilts in ((math.radians(10.0), math.radians(30.0)), (0.0, 0.0)):
        spec = SyntheticSpec(z_range=(0.05, 0.3), theta_range=tilts, specular_weight_range=(0.14681, 0.14681),
                             specular_exponent_range=(1.8378, 1.8378), noise=True, rays=4)
        frames = make_frames(10, params=truth, spec=spec, seed=4)
        got, report = fit_forward(frames, init=ForwardParams(bin_offset=9.3), progress=False, rays=4, iterations=20,
                                  fitted=fitted, coarse_rays=0)
        assert report["converged"]
        undetermined = set(report["posterior_std"]["not_determined"])
        if tilts[1] > 0.0:
            np.testing.assert_allclose(got.zone_bin_scales, scales, atol=0.002)
            assert math.degrees(np.abs(np.array(got.mount_tilt) - mount).max()) < 0.1
            assert abs(got.edge_fov_scale - 1.0) < 0.01 and abs(got.corner_fov_scale - 1.0) < 0.01
            assert not undetermined
        else:
            assert {"edge_fov_scale", "corner_fov_scale"} <= undetermined


@pytest.mark.slow
def test_the_staged_unit_model_holds_what_each_stage_trades_with(monkeypatch):
    """Convention check on a small synthetic level sweep (6 frames, a few iterations; not a measure of the fit):
    ``fit_forward_staged`` runs three fits, each from the one before and with the ambient through the pile-up;
    the second adds the zones' time scales with the fields of view and the beam held at the first's values, the
    third the time warp with the range law held as well. The report gives each stage's residuals, convergence and
    reason, and converges only when every stage did."""
    from place_safe.calibration import forward_fit as ff

    calls = []
    real = ff.fit_forward

    def spy(frames, init=None, **kw):
        params, report = real(frames, init=init, **kw)
        calls.append((init, kw["fitted"], kw["ambient"], params))
        return params, report

    monkeypatch.setattr(ff, "fit_forward", spy)
    frames = _level_frames(6)
    logged = []
    params, report = ff.fit_forward_staged(frames, progress=False, log=logged.append, rays=2, coarse_rays=0,
                                           iterations=2)
    assert len(calls) == 3 and all(amb for _, _, amb, _ in calls)
    (init1, fit1, _, p1), (init2, fit2, _, p2), (init3, fit3, _, p3) = calls
    assert init1 is None and init2 is p1 and init3 is p2 and params is p3
    assert {**ff.FITTED, **ff.UNIT_TERMS, **ff.LEARNED_RESPONSE}.items() <= fit1.items()
    assert "zone_bin_scales" in fit2 and not set(ff.GEOMETRY) & set(fit2)
    assert "time_warp" in fit3 and not (set(ff.GEOMETRY) | set(ff.RANGE_LAW)) & set(fit3)
    for name in ff.GEOMETRY:
        assert getattr(p3, name) == getattr(p1, name)
    for name in ff.RANGE_LAW:
        assert getattr(p3, name) == getattr(p2, name)
    stages = report["stages"]
    assert list(stages) == ["1_unit", "2_zone_scales", "3_time_warp"]
    for s in stages.values():
        assert {"rms_scaled_residual_before", "rms_scaled_residual_after", "converged", "why", "seconds"} <= set(s)
    assert report["unit_model"] == "staged"
    assert report["converged"] == all(s["converged"] for s in stages.values())
    assert all(k in report["why"] for k in stages)
    assert report["rms_scaled_residual_after"] == stages["3_time_warp"]["rms_scaled_residual_after"]
    assert len(logged) == 3 and "stage 3 of 3" in logged[-1]
    with pytest.raises(TypeError, match="ambient"):
        ff.fit_forward_staged(frames, ambient=False)


@pytest.mark.parametrize("ambient", [False, True])
def test_the_jacobian_is_the_derivative_of_the_residuals(monkeypatch, ambient):
    """The solver's Jacobian (forward-mode tangents taken in groups of parameters) against central differences of
    its residuals, with every term of the model fitted, at a point off the start (tilted frames, so the tilt and the
    beam act): each column within 1e-5 of its largest entry."""
    from place_safe.calibration import forward_fit as ff, gauss_newton

    every = {**ff.FITTED, **ff.UNIT_TERMS, **ff.LEARNED_RESPONSE, **ff.ZONE_SCALE_TERMS, **ff.DNL_TERMS,
             **ff.INL_TERMS}
    spec = SyntheticSpec(z_range=(0.06, 0.3), theta_range=(0.0, 0.3), specular_weight_range=(0.14681, 0.14681),
                         specular_exponent_range=(1.8378, 1.8378), noise=True, rays=4)
    frames = make_frames(4, params=ForwardParams(bin_offset=9.3), spec=spec, seed=5)
    seen = {}

    def capture(fun, jac, x0, lower, upper, **_):
        seen.update(fun=fun, jac=jac, x0=np.clip(x0, lower, upper), lower=lower, upper=upper)
        raise StopIteration

    monkeypatch.setattr(gauss_newton, "solve", capture)
    with pytest.raises(StopIteration):
        ff.fit_forward(frames, progress=False, rays=2, coarse_rays=0, fitted=every, ambient=ambient)
    rng = np.random.default_rng(1)
    lo, hi = seen["lower"], seen["upper"]
    x = seen["x0"] + 0.02 * rng.standard_normal(seen["x0"].size)
    x = np.clip(x, np.where(np.isfinite(lo), lo + 1e-3, -np.inf), np.where(np.isfinite(hi), hi - 1e-3, np.inf))
    J = seen["jac"](x)
    step = 1e-6
    for i in range(x.size):
        e = np.zeros(x.size)
        e[i] = step
        fd = (seen["fun"](x + e) - seen["fun"](x - e)) / (2 * step)
        scale = max(np.abs(fd).max(), np.abs(J[:, i]).max(), 1e-12)
        np.testing.assert_allclose(J[:, i], fd, rtol=0, atol=1e-5 * scale, err_msg=f"column {i}")


def test_the_coarse_stage_starts_from_each_tail_decay_and_floor_and_keeps_the_lower(monkeypatch):
    """From the default start the coarse stage runs from each of TAIL_DECAY_STARTS with each reference floor (each
    frame's albedo at its least-squares value there), then from the winner's decay and floor with the pulse's
    soft-binning blend at each of PULSE_SOFT_BIN_STARTS, and the fit continues from the run whose objective ended lower.
    Frames rendered by the forward model with long tails (a convention check of the bookkeeping, not of accuracy)."""
    from place_safe.calibration import forward_fit as ff

    truth = ForwardParams(bin_offset=9.3, zone_tail_weights=[0.08] * 9, zone_tail_decays=[7.0] * 9)
    spec = SyntheticSpec(z_range=(0.05, 0.35), theta_range=(0.0, 0.0), albedo_range=(1.0, 1.0),
                         specular_weight_range=(0.14681, 0.14681), specular_exponent_range=(1.8378, 1.8378),
                         noise=True, rays=3)
    frames = make_frames(8, params=truth, spec=spec, seed=5)
    _, report = fit_forward(frames, progress=False, rays=3, iterations=8)
    starts = report["solver"]["coarse"]["starts"]
    from_middle = [s for s in starts if s["pulse_soft_bin"] == 0.5]
    assert sorted((s["tail_decay_bins"], s["ref_floor"]) for s in from_middle) == sorted(
        (d, f) for d in ff.TAIL_DECAY_STARTS for f in ("measured", "published"))
    # then the pulse's soft-binning blend from each of PULSE_SOFT_BIN_STARTS, at the tail decay and floor that won
    won = min(from_middle, key=lambda s: s["objective_rms_with_priors"])
    assert [(s["tail_decay_bins"], s["ref_floor"], s["pulse_soft_bin"]) for s in starts[len(from_middle):]] == [
        (won["tail_decay_bins"], won["ref_floor"], b) for b in ff.PULSE_SOFT_BIN_STARTS]
    chosen = [s for s in starts if s["chosen"]]
    assert len(chosen) == 1 and chosen[0]["objective_rms_with_priors"] == min(
        s["objective_rms_with_priors"] for s in starts)
    assert report["solver"]["coarse"]["rms_scaled_residual"] <= chosen[0]["objective_rms"] + 1e-9
    assert report["ref_floor"]["chosen"] == chosen[0]["ref_floor"]
    # the residual reported before the fit is the chosen start's (here the blend's: its floor's entry says so)
    entry = report["ref_floor"][chosen[0]["ref_floor"]]
    assert entry.get("pulse_soft_bin", 0.5) == chosen[0]["pulse_soft_bin"]
    assert report["rms_scaled_residual_before"] == pytest.approx(entry["rms_scaled_residual_at_start"], rel=0.02)
    # the floors' bookkeeping, from the blend's middle alone
    monkeypatch.setattr(ff, "PULSE_SOFT_BIN_STARTS", ())
    _, report = fit_forward(frames, progress=False, rays=3, iterations=8)
    starts = report["solver"]["coarse"]["starts"]
    assert len(starts) == 2 * len(ff.TAIL_DECAY_STARTS)
    chosen = [s for s in starts if s["chosen"]]
    assert len(chosen) == 1 and chosen[0]["objective_rms"] == min(s["objective_rms"] for s in starts)
    assert report["ref_floor"]["chosen"] == chosen[0]["ref_floor"]  # the floor the fit went on with ...
    floor = report["ref_floor"][chosen[0]["ref_floor"]]["counts"]
    assert report["ref_floor"]["counts"] == floor and report["params"]["ref_floor"] == floor  # ... and kept
    # the residual reported before the fit is the chosen start's: what the fit started from
    assert report["rms_scaled_residual_before"] == pytest.approx(
        report["ref_floor"][chosen[0]["ref_floor"]]["rms_scaled_residual_at_start"], rel=0.02)
    # a start the caller gives is the only one
    _, given = fit_forward(frames, init=ForwardParams(bin_offset=9.3), progress=False, rays=3, iterations=2)
    assert [s["tail_decay_bins"] for s in given["solver"]["coarse"]["starts"]] == [None]


def test_the_ambient_slope_is_kept_only_when_it_is_one_number_over_distance():
    """A unit whose ambient falls by the same share in every frame: measured and kept (the fit then compares the
    frames above the sloping floor); the real sweep, whose first bins move with the return (the pile-up's
    shadowing): not one number, the floor stays flat; a flat unit, or one whose ambient rises: 0."""
    from place_safe.calibration.forward_fit import AMBIENT_SLOPE_AGREEMENT, measure_ambient_slope

    rng = np.random.default_rng(3)
    z = np.linspace(0.03, 0.40, 30)
    u = np.arange(128) / 127.0

    def frames(slope_at):
        return np.stack([rng.poisson(np.broadcast_to(100.0 * (1.0 + slope_at(zi) * (u - 0.5)), (9, 128)))
                         for zi in z]).astype(float)

    value, report = measure_ambient_slope(frames(lambda zi: -0.2), z)
    assert report["adopted"] and value == pytest.approx(-0.2, abs=0.02)
    value, report = measure_ambient_slope(frames(lambda zi: 0.0), z)
    assert value == 0.0 and not report["adopted"]
    value, report = measure_ambient_slope(frames(lambda zi: 0.2), z)  # rising: nothing physical makes it
    assert value == 0.0 and not report["adopted"] and "rises" in report["why"]
    value, report = measure_ambient_slope(frames(lambda zi: -0.02 / zi), z)  # changes with distance
    assert value == 0.0 and not report["adopted"]
    assert abs(report["near_half"] - report["far_half"]) > AMBIENT_SLOPE_AGREEMENT
    real = load_frames(SWEEP)
    value, report = measure_ambient_slope(np.array([f.hists for f in real], float), np.array([f.truth.z0 for f in real]))
    assert value == 0.0 and "not one number over distance" in report["why"]


def test_a_coarse_start_whose_residuals_are_not_finite_is_skipped(monkeypatch):
    """One start of the coarse stage that cannot run (its residuals not finite: gauss_newton raises) leaves the
    others to run; the report marks it with no objective. All of them failing fails the fit as one start did."""
    from place_safe.calibration import forward_fit as ff
    from place_safe.calibration import gauss_newton

    solve = gauss_newton.solve
    calls = {"n": 0}

    def first_fails(*a, **kw):
        calls["n"] += 1
        if calls["n"] == 1:
            raise ArithmeticError("the residuals at the start are not finite")
        return solve(*a, **kw)

    monkeypatch.setattr(gauss_newton, "solve", first_fails)
    _, report = fit_forward(_level_frames(6), progress=False, rays=3, iterations=3)
    starts = report["solver"]["coarse"]["starts"]
    assert starts[0]["objective_rms"] is None and not starts[0]["chosen"] and any(s["chosen"] for s in starts[1:])

    def all_fail(*a, **kw):
        raise ArithmeticError("the residuals at the start are not finite")

    monkeypatch.setattr(gauss_newton, "solve", all_fail)
    with pytest.raises(ArithmeticError):
        ff.fit_forward(_level_frames(6), progress=False, rays=3, iterations=3)


def test_each_frame_solves_its_crosstalk_only_where_a_level_sweep_left_it_undetermined():
    """``free_crosstalk_std``: CROSSTALK_LEFT_SHARE of the fitted crosstalk when the fit's report marks the crosstalk as
    traded by a level sweep, 0 (held) when its frames determined it or the report says nothing."""
    from place_safe.calibration.forward_fit import CROSSTALK_FREE_MIN, LEVEL_SWEEP_TRADED, crosstalk_traded, free_crosstalk_std
    from place_safe.recovery.diff_settings import CROSSTALK_LEFT_SHARE
    p = ForwardParams(crosstalk=0.018)
    level = {"posterior_std": {"crosstalk": {"std": 0.0007, "level_sweep": LEVEL_SWEEP_TRADED["crosstalk"]}}}
    tilted = {"posterior_std": {"crosstalk": {"std": 0.0007}}}
    assert crosstalk_traded(level) and not crosstalk_traded(tilted) and not crosstalk_traded(None)
    assert free_crosstalk_std(p, level) == pytest.approx(CROSSTALK_LEFT_SHARE * 0.018)
    assert free_crosstalk_std(p, tilted) == 0.0 and free_crosstalk_std(p, {}) == 0.0
    assert free_crosstalk_std(ForwardParams(crosstalk=0.0), level) == 0.0
    # a crosstalk the fit found next to none (the real unit, the mismatched simulated units) stays held
    assert free_crosstalk_std(ForwardParams(crosstalk=0.5 * CROSSTALK_FREE_MIN), level) == 0.0


def test_the_albedo_spread_counts_only_albedos_the_counts_determined():
    """``albedo_spread``: a frame whose log albedo sits at a bound (a saturated return: no count moved it) or that the
    fit left out is not in the CV, and the frames at a bound are counted; under two frames left, NaN."""
    import place_safe.calibration.forward_fit as ff

    la = np.log([12.0, 12.3, 11.8, 110.0])
    lower, upper = np.full(4, np.log(12.0) - 8.0), np.log([80.0, 80.0, 80.0, 110.0])
    cv, n = ff.albedo_spread(la, lower, upper)
    assert n == 1 and abs(cv - np.std([12.0, 12.3, 11.8]) / np.mean([12.0, 12.3, 11.8])) < 1e-12
    cv_all, n_all = ff.albedo_spread(la, lower, np.full(4, np.log(200.0)))  # no bound reached: every frame counts
    assert n_all == 0 and cv_all > 1.0
    cv, n = ff.albedo_spread(la, lower, upper, used=np.array([True, False, True, True]))
    assert n == 1 and math.isnan(cv)  # one of the three used at its bound: more than a quarter
    low = la.copy()
    low[0] = lower[0]
    assert ff.albedo_spread(low, lower, upper)[1] == 2
    assert math.isnan(ff.albedo_spread(la[2:], lower[2:], upper[2:])[0])
    # a frame the fit left out is not counted at its bound either
    assert ff.albedo_spread(la, lower, upper, used=np.array([True, True, True, False])) == (
        pytest.approx(np.std([12.0, 12.3, 11.8]) / np.mean([12.0, 12.3, 11.8])), 0)
    # more than a quarter of the frames at a bound: the fit, not a saturated frame, put them there; spread unknown
    many = np.log([12.0, 12.3, 11.8, 12.1, 12.2, 110.0, 110.0])
    cv, n = ff.albedo_spread(many, np.full(7, -10.0), np.log([80.0] * 5 + [110.0] * 2))
    assert n == 2 and math.isnan(cv)
    with pytest.raises(ValueError, match="frames used"):
        ff.albedo_spread(la, lower, upper, used=np.array([True]))




def test_the_anscombe_residuals_written_out_derivatives_are_the_formulas():
    """The forward fit's Anscombe residual (its derivatives written out) against autograd through its formula, with
    counts below zero (clamped: no slope) among them: forward mode, many tangents at once, and reverse mode."""
    import torch
    from torch.func import jvp, vmap
    from place_safe.calibration.forward_fit import _AnscombeResidual  # (its written-out derivatives, called directly)

    def formula(m, root, w):
        return (torch.sqrt(torch.clamp(m, min=0.0) + 0.375) - root) * w

    g = torch.Generator().manual_seed(2)
    m = 50.0 * torch.randn((3, 9, 20), dtype=torch.float64, generator=g) + 20.0
    assert (m < 0).any()
    root = torch.sqrt(torch.rand(m.shape, dtype=torch.float64, generator=g) * 100.0 + 0.375)
    w = torch.rand(m.shape, dtype=torch.float64, generator=g)
    torch.testing.assert_close(_AnscombeResidual.apply(m, root, w), formula(m, root, w), rtol=0.0, atol=0.0)
    dm = torch.randn((4,) + m.shape, dtype=torch.float64, generator=g)
    got = vmap(lambda t: jvp(lambda a: _AnscombeResidual.apply(a, root, w), (m,), (t,))[1])(dm)
    want = vmap(lambda t: jvp(lambda a: formula(a, root, w), (m,), (t,))[1])(dm)
    torch.testing.assert_close(got, want, rtol=1e-14, atol=1e-14)
    inputs = [x.clone().requires_grad_() for x in (m, root, w)]
    v = torch.randn(m.shape, dtype=torch.float64, generator=g)
    got = torch.autograd.grad((_AnscombeResidual.apply(*inputs) * v).sum(), inputs)
    want = torch.autograd.grad((formula(*inputs) * v).sum(), inputs)
    for a, b in zip(got, want):
        torch.testing.assert_close(a, b, rtol=1e-14, atol=1e-14)
