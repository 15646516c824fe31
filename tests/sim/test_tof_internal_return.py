"""The simulated sensors render the internal (cover-glass) return and crosstalk: measured from the real sweep,
the same whatever the scene, each mismatched unit its own; their near frames read "too close" or a plane within
its bound, never a confident wrong one; the estimators keep the user's calibration."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytest.importorskip("mujoco")

from place_safe.evaluation.metrics import angular_error  # noqa: E402
from place_safe.exceptions import NoPlaneError  # noqa: E402
from place_safe.recovery import make_estimator  # noqa: E402
from place_safe.recovery.too_close import TOO_CLOSE_REASON  # noqa: E402
from place_safe.sensor.frame import N_BINS, N_ZONES  # noqa: E402
from place_safe.sim.scene import SceneConfig, TableConfig, build_scene  # noqa: E402
from place_safe.sim.tof import RayReturns, SimToF, ToFConfig, simulated_calibration, true_params  # noqa: E402
from place_safe.sim.tof_mismatch import MismatchConfig, MismatchedToF  # noqa: E402

H = 0.75  # table top (m)
#: Bins the internal return fills and a surface at >= 15 cm leaves alone (its return starts after bin 17).
EARLY = slice(0, 17)
SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"


def _scene(tilt_deg: float = 0.0, gap: float = 0.2):
    table = TableConfig(height=H, center=(0.0, 0.0), size=(1.0, 1.0, 0.04), tilt=math.radians(tilt_deg),
                        tilt_direction=0.7)
    return build_scene(SceneConfig(table=table, rig_pos=(0.0, 0.0, H + gap), rig_euler=(math.pi, 0.0, 0.0)))


@pytest.fixture(scope="module")
def sensors():
    scene = _scene()
    cfg = ToFConfig(noise=False, rays=4)
    return (SimToF(scene, config=cfg),
            *(MismatchedToF(scene, config=cfg, mismatch=MismatchConfig(seed=s)) for s in (11, 12)))


def _returns(r: float, cos: float, albedo: float, hit_fraction: float, rays: int) -> RayReturns:
    n = rays * rays
    hit = np.zeros((N_ZONES, n), bool)
    hit[:, : int(round(hit_fraction * n))] = True
    full = np.ones((N_ZONES, n))
    nan3 = np.full((N_ZONES, n, 3), np.nan)
    return RayReturns(np.where(hit, r, 1.0), np.where(hit, cos, 0.0), full * albedo, full * 0.15, full * 1.8,
                      hit, np.where(hit, 0, -1), nan3, nan3)


def _glass_only(tof: SimToF) -> np.ndarray:
    """The noise-free frame of a sensor whose rays all miss (the mismatched sensor's sloping ambient included)."""
    return tof.render(_returns(1.0, 1.0, 1.0, 0.0, tof.config.rays), tof._kernel_ref)


def _detrended(h: np.ndarray) -> np.ndarray:
    """``h`` less a straight line through bins 40-127 per zone (the mismatched sensor's ambient slope)."""
    x = np.arange(N_BINS, dtype=float)
    out = np.empty_like(h)
    for z in range(h.shape[0]):
        a, b = np.polyfit(x[40:], h[z, 40:], 1)
        out[z] = h[z] - (a * x + b)
    return out


def test_the_true_sensor_carries_the_real_internal_return_and_no_more_crosstalk_than_it_fits():
    """The simulator's true parameters hold the internal return measured on the real sweep's far frames
    (30-55 counts at its peak, bins 12-15: zero range plus the pulse's delay), and no neighbour crosstalk: the
    real near frames bound it below the scalar crosstalk already rendered."""
    import json

    p = true_params()
    assert all(40.0 < g < 120.0 for g in p.glass_gains)
    rep = json.loads((Path(__file__).resolve().parents[2] / "sim" / "sensors" /
                      "tmf8820_real_report.json").read_text())["internal_return"]
    assert all(25.0 < v < 55.0 for v in rep["measured_peak_counts"])
    assert rep["crosstalk_bound"]["scalar"] < p.crosstalk
    assert not any(p.crosstalk_grid)


def test_the_internal_return_sits_at_zero_range_in_a_frame_that_sees_nothing(sensors):
    for tof in sensors:
        g = _detrended(_glass_only(tof))
        peak = np.argmax(g, axis=1)
        assert np.all((peak >= 12) & (peak <= 15)), peak
        assert np.all(g.max(axis=1) > 15.0) and np.all(g.max(axis=1) < 150.0)
        assert np.all(np.abs(g[:, 40:]) < 1.0)  # nothing far out


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(r=st.floats(0.15, 4.0), cos=st.floats(0.05, 1.0), albedo=st.floats(0.01, 50.0),
       hit_fraction=st.floats(0.0, 1.0), which=st.integers(0, 2))
def test_rendering_is_finite_non_negative_and_the_internal_return_does_not_depend_on_the_scene(
        sensors, r, cos, albedo, hit_fraction, which):
    tof = sensors[which]
    ret = _returns(r, cos, albedo, hit_fraction, tof.config.rays)
    h = tof.render(ret, tof._kernel_ref)
    assert h.shape == (N_ZONES, N_BINS)
    # measure() adds the mean ambient (the mismatched sensor's render holds only its slope about the mean)
    assert np.all(np.isfinite(h)) and np.all(h + tof.ambient[:, None] >= 0.0)
    # the surface is at >= 15 cm: the first bins hold the internal return alone, whatever the surface
    np.testing.assert_allclose(h[:, EARLY], _glass_only(tof)[:, EARLY], rtol=1e-6, atol=1e-6)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(r=st.floats(0.0, 0.15), cos=st.floats(0.05, 1.0), albedo=st.floats(0.01, 50.0), which=st.integers(0, 2))
def test_a_near_surface_overlaps_the_internal_return_and_the_rendering_stays_finite(sensors, r, cos, albedo, which):
    tof = sensors[which]
    h = tof.render(_returns(r, cos, albedo, 1.0, tof.config.rays), tof._kernel_ref)
    assert np.all(np.isfinite(h)) and np.all(h + tof.ambient[:, None] >= 0.0)
    g = _glass_only(tof)
    # the glass is in the frame, its bins shared with the surface's return when the surface is close: a surface
    # adds counts to them, never removes the internal return
    assert np.all(h[:, EARLY] >= g[:, EARLY] - 1e-6 * (1.0 + np.abs(g[:, EARLY])))


def test_each_mismatched_unit_has_its_own_internal_return_and_crosstalk(sensors):
    nominal, a, b = sensors
    true = np.asarray(nominal.params.glass_gains)
    for unit in (a, b):
        assert not np.allclose(unit.params.glass_gains, true, rtol=0.02)
        assert any(unit.params.crosstalk_grid)
    assert not np.allclose(a.params.glass_gains, b.params.glass_gains)
    again = MismatchedToF(nominal.scene, config=nominal.config, mismatch=MismatchConfig(seed=11))
    assert again.params == a.params
    assert not np.allclose(_glass_only(a), _glass_only(nominal))


def test_the_estimators_keep_the_users_calibration_not_the_simulators_parameters():
    """The packaged simulated calibrations are what a user's capture + calibrate give: they know nothing of the
    simulator's internal return (the simulator's true parameters are handed over only by --oracle)."""
    from place_safe.sim.scenario import Scenario

    true = true_params()
    for sensor in ("nominal", "mismatch"):
        cal = simulated_calibration(sensor)
        fwd = cal.sections.get("forward")
        assert fwd is not None
        assert list(fwd.get("glass_gains", [0.0] * N_ZONES)) != list(true.glass_gains)
    cal, note = Scenario().resolve_calibration()
    assert "ORACLE" not in note


def _near_frames(sensor: str, gaps, tilt_deg: float, seed: int):
    scene = _scene(tilt_deg)
    cfg = ToFConfig(noise=True, seed=seed)
    tof = (SimToF(scene, config=cfg) if sensor == "nominal"
           else MismatchedToF(scene, config=cfg, mismatch=MismatchConfig(seed=seed)))
    out = []
    for gap in gaps:
        scene.set_sensor_pose(tof.data, np.array([0.0, 0.0, H + gap]), np.diag([1.0, -1.0, -1.0]))
        f = tof.measure()
        if f.truth is not None:
            out.append(f)
    return out


@pytest.mark.parametrize("sensor,tilt,seed", [("nominal", 0.0, 1), ("nominal", 8.0, 2), ("mismatch", 0.0, 11),
                                              ("mismatch", 6.0, 12)])
def test_simulated_near_frames_read_too_close_or_a_plane_within_its_bound(sensor, tilt, seed):
    """Below 2 cm, with the packaged user calibration: each frame is "too close" (no plane) or a plane within 5 deg
    or within 3 sigma of its reported tilt; never a confident wrong plane."""
    cal = simulated_calibration(sensor)
    frames = _near_frames(sensor, (0.005, 0.0075, 0.01, 0.0125, 0.015, 0.0175, 0.02), tilt, seed)
    assert len(frames) >= 5
    for method in ("peak", "diff"):
        est = make_estimator(method, cal)
        for f in frames:
            try:
                e = est.estimate(f)
            except NoPlaneError as exc:
                assert str(exc).startswith(TOO_CLOSE_REASON) or "zones" in str(exc), str(exc)
                continue
            if e.plane is None:
                assert e.reason, method
                continue
            err = math.degrees(angular_error(e.plane, f.truth))
            std = e.tilt_std()
            bound = 3.0 * math.degrees(std) if std is not None else 0.0
            assert err <= max(5.0, bound), (method, sensor, f.truth.z0, err, bound)


def test_the_packaged_internal_return_is_reproduced_from_the_real_sweep():
    """``sim/make_real_sensor.py``'s measurement gives the packaged glass gains and delay again (reproducible)."""
    import importlib.util

    from place_safe.io.frame_file import load_frames

    path = Path(__file__).resolve().parents[2] / "sim" / "make_real_sensor.py"
    spec = importlib.util.spec_from_file_location("make_real_sensor", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    frames = load_frames(SWEEP)
    p = true_params()
    glass, report = mod.fit_internal_return(frames, p)
    np.testing.assert_allclose(glass["glass_gains"], p.glass_gains, rtol=1e-6)
    assert glass["glass_delay"] == p.glass_delay
    assert report["frames"] >= 30
    bound = mod.crosstalk_bound(frames)
    assert bound["frames"] == 3 and bound["scalar"] < 1e-5


@pytest.mark.slow
@pytest.mark.parametrize("name", ["jaw_sensor_level", "jaw_sensor_mismatch_level", "jaw_sensor_tilt_10",
                                  "jaw_sensor_mismatch_tilt_7"])
def test_the_jaw_mounted_sensor_with_the_internal_return_releases_level_refuses_tilted(name):
    """With the internal return rendered: the sensor 5 mm above the cup bottom releases on level tables (from the
    fused plane of the farther frames) and refuses tilted ones; no frame flagged too close carries a plane, so
    none can decide a release."""
    from place_safe.sim.placement_run import run_placement
    from place_safe.sim.scenario import load_scenario

    path = Path(__file__).resolve().parents[2] / "scenarios" / "set" / f"{name}.toml"
    expected = load_scenario(path).expect.outcome
    res = run_placement(path, seconds=20, log_frames=True)
    assert res.outcome == expected, res.summary()
    close = [f for f in res.frame_log if TOO_CLOSE_REASON in (f.get("reason") or "")]
    assert all(not f["plane"] for f in close)
    if expected == "released":
        assert close and "farther frames" in res.reason


# -- the real sensor's dark zones close up (opt-in: ToFConfig.blinding) -------------------------------------------

def _zone_brightness(frame) -> np.ndarray:
    """log10 of each zone's return (bins 8-29 less the early floor) over the frame's median zone (9,)."""
    h = frame.hists - np.median(frame.hists[:, :8], axis=1, keepdims=True)
    a = np.maximum(h[:, 8:30].sum(axis=1), 1.0)
    return np.log10(a / np.median(a))


def test_blinding_is_off_by_default_and_leaves_the_frame_alone(sensors):
    assert ToFConfig().blinding is False
    for tof in sensors:
        assert tof.blinding is None
        np.testing.assert_array_equal(tof.blinding_factors(tof.cast()), np.ones(N_ZONES))


def test_blinding_gives_the_real_sweeps_dark_zones_close_up():
    """With ``blinding`` a level table darkens the zones the real sweep's do: zone 4 at 5 mm, zone 5 (centre) at
    12.5 and 20 mm, fading with range (real, log10 of the median zone: -3.3, -5.4, -2.1, -0.8 at 27.5 mm, within
    0.1 from 5 cm on)."""
    scene = _scene()
    tof = SimToF(scene, config=ToFConfig(noise=False, blinding=True))
    got, share = {}, {}
    for gap in (0.005, 0.0125, 0.02, 0.0275, 0.05, 0.1):
        scene.set_sensor_pose(tof.data, np.array([0.0, 0.0, H + gap]), np.diag([1.0, -1.0, -1.0]))
        got[gap] = _zone_brightness(tof.measure())
        share[gap] = tof.blinding_factors(tof.cast())
    assert np.argmin(got[0.005]) == 3 and got[0.005][3] < -3.0
    assert np.argmin(got[0.0125]) == 4 and got[0.0125][4] < -4.0
    assert np.argmin(got[0.02]) == 4 and -3.0 < got[0.02][4] < -1.0
    assert -1.0 < got[0.0275][4] < -0.2
    assert np.all(share[0.05] > 0.7) and np.all(share[0.1] > 0.99)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(gap=st.floats(0.003, 0.5), tilt=st.floats(0.0, 30.0), albedo=st.floats(0.05, 5.0))
def test_blinding_factors_are_finite_shares(gap, tilt, albedo):
    from place_safe.recovery.forward import ForwardModel, ZoneRays
    from place_safe.sim.tof import Blinding, glint_measure

    t = math.radians(tilt)
    n = np.array([0.0, math.sin(t), -math.cos(t)])  # the surface faces the sensor
    d, w = (x.numpy() for x in ForwardModel(true_params(), ZoneRays.stratified(4)).ray_geometry())
    pts = gap / np.abs(d @ n)[..., None] * d
    b = Blinding.load()
    g = glint_measure(pts, np.broadcast_to(n, pts.shape), albedo * w, np.ones(w.shape, bool), b.emitter,
                      b.glint_width)
    assert np.all(np.isfinite(g)) and np.all(g >= 0.0)
    share = np.exp(-np.power(g / b.g0, b.power))
    assert np.all((share >= 0.0) & (share <= 1.0))


@pytest.mark.parametrize("sensor,seed", [("nominal", 1), ("mismatch", 11)])
def test_with_blinding_level_near_frames_read_too_close_or_a_plane_within_its_bound(sensor, seed):
    """The dark zones on: below 2.5 cm over a level table each frame is too close or a plane within 5 deg or 3 sigma.
    (Tilted tables are not asserted: there the glint darkens an edge zone, no rule flags it and the packaged
    calibrations read 15-25 mm planes 10-36 deg off, beyond 3 sigma; see docs/results.md.)"""
    scene = _scene(0.0)
    cfg = ToFConfig(noise=True, seed=seed, blinding=True)
    tof = (SimToF(scene, config=cfg) if sensor == "nominal"
           else MismatchedToF(scene, config=cfg, mismatch=MismatchConfig(seed=seed)))
    est = make_estimator("peak", simulated_calibration(sensor))
    for gap in (0.005, 0.01, 0.015, 0.02, 0.025):
        scene.set_sensor_pose(tof.data, np.array([0.0, 0.0, H + gap]), np.diag([1.0, -1.0, -1.0]))
        f = tof.measure()
        e = est.estimate(f)
        if e.plane is None:
            assert e.reason
            continue
        err = math.degrees(angular_error(e.plane, f.truth))
        std = e.tilt_std()
        assert err <= max(5.0, 3.0 * math.degrees(std) if std is not None else 0.0), (gap, err)


@pytest.mark.parametrize("sensor,ambient,seed", [("nominal", 60.0, 1), ("nominal", 120.0, 2), ("nominal", 0.0, 3),
                                                 ("mismatch", 60.0, 11), ("mismatch", 60.0, 12)])
def test_a_frame_that_sees_nothing_has_no_return_at_the_internal_return(sensor, ambient, seed):
    """The sensor looks up at nothing: its frames hold the floor and the internal return only. No zone reads a
    return at the internal return's bins (a surface at zero range); the nominal sensor's none anywhere. (Before the
    peak finder told the internal return apart: 5.8 of 9 zones per frame at ambient 60, 2.0 at 120.)"""
    from place_safe.sensor.histogram import INTERNAL_BINS, find_peaks

    table = TableConfig(height=H, center=(0.0, 0.0), size=(1.0, 1.0, 0.04))
    scene = build_scene(SceneConfig(table=table, rig_pos=(0.0, 0.0, H + 0.2), rig_euler=(0.0, 0.0, 0.0)))  # facing up
    cfg = ToFConfig(rays=4, ambient_range=[ambient, ambient], seed=seed)
    tof = (SimToF(scene, config=cfg) if sensor == "nominal"
           else MismatchedToF(scene, config=cfg, mismatch=MismatchConfig(seed=seed)))
    frames = [tof.measure() for _ in range(20)]
    assert all(f.extra["sim"]["hit_fraction"] == 0.0 for f in frames)
    h = np.array([f.hists for f in frames])
    for subbin in ("spline", "centroid"):
        pos, valid, _ = find_peaks(h, 0.0, subbin)
        assert not (valid & (pos < INTERNAL_BINS[1])).any()
        if sensor == "nominal":
            assert not valid.any()
