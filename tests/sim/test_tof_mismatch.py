"""The mismatched simulated sensor differs structurally from the forward model (and from SimToF)."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip("mujoco")

from place_safe.config import parse_config  # noqa: E402
from place_safe.exceptions import ConfigError  # noqa: E402
from place_safe.sim.scene import SceneConfig, build_scene  # noqa: E402
from place_safe.sim.tof import SimToF, ToFConfig  # noqa: E402
from place_safe.sim.tof_mismatch import MismatchConfig, MismatchedToF, make_sensor  # noqa: E402


def _pair(height=0.2):
    scene = build_scene(SceneConfig())
    data = scene.make_data()
    R = np.diag([1.0, -1.0, -1.0])  # looking straight down
    scene.set_sensor_pose(data, np.array([-0.5, -0.1, 0.75 + height]), R)
    cfg = ToFConfig(noise=False)
    return scene, data, make_sensor("nominal", scene, data, cfg), make_sensor("mismatch", scene, data, cfg)


def test_mismatch_differs_from_the_model_beyond_its_parameters():
    scene, data, nom, mis = _pair()
    a, b = nom.measure(), mis.measure()
    assert isinstance(mis, MismatchedToF)
    assert a.truth is not None and b.truth is not None
    assert np.allclose(a.truth.normal, b.truth.normal)  # same world, same truth
    rel = np.abs(a.hists - b.hists).sum(axis=1) / a.hists.sum(axis=1)
    assert np.all(rel > 0.01)  # every zone differs by more than a percent of its counts
    # warming shifts the timing: the same pose later gives shifted peaks (ambient kept constant here)
    warm = MismatchedToF(scene, data, ToFConfig(noise=False), MismatchConfig(ambient_drift=0.0, ambient_slope=0.0))
    data.time = 0.0
    cold_h = warm.measure().hists
    data.time = 40.0
    c = warm.measure()
    assert c.extra["sim"]["temperature"] == 45.0
    pk = lambda h: ((h - h.min(1, keepdims=True)) * np.arange(h.shape[1])).sum(1) / (h - h.min(1, keepdims=True)).sum(1)  # noqa: E731
    assert np.mean(np.abs(pk(c.hists) - pk(cold_h))) > 0.05  # common drift plus per-zone skew


def test_baseline_changes_ranges_and_is_deterministic():
    scene, data, nom, mis = _pair(0.08)
    r0, r1 = nom.cast(), mis.cast()
    d = r1.ranges[r1.hit] - r0.ranges[r0.hit]
    b = MismatchConfig().baseline
    assert np.abs(d).max() > 0.05 * b and np.all(np.abs(d) <= b / 2 + 1e-9)  # triangle inequality
    _, _, _, mis2 = _pair(0.08)
    assert np.allclose(mis2.measure().hists, _pair(0.08)[3].measure().hists)


def test_unknown_sensor_and_bad_mismatch_settings_are_rejected():
    scene = build_scene(SceneConfig())
    with pytest.raises(ValueError, match="unknown simulated sensor"):
        make_sensor("ideal", scene)
    with pytest.raises(ConfigError, match="baseline"):
        parse_config(MismatchConfig, {"baseline": 1.0}, "mismatch")
    with pytest.raises(ConfigError):
        parse_config(MismatchConfig, {"skew_bins": math.nan}, "mismatch")


def test_latency_spikes_delay_frames_in_order():
    from place_safe.sim.scene import SceneError
    from place_safe.sim.tof import SimToF

    with pytest.raises(SceneError, match="spike_prob"):
        ToFConfig(spike_prob=2.0)
    scene = build_scene(SceneConfig())
    tof = SimToF(scene, None, ToFConfig(spike_prob=1.0, spike_seconds=0.2, noise=False))
    f = tof.read(2.0)
    assert f.extra["sim"]["latency_spike"] == 0.2
    assert tof.data.time - f.timestamp >= tof.config.latency + 0.2 - 1e-9


def test_extra_tails_end_as_exponentials_do():
    # each zone's extra tail is one exponential to its last lag, long enough to have died out (no step where it
    # stops: before 2026-11-28 the tails stopped at 23 bins, a step of up to 10 % of their start)
    scene = build_scene(SceneConfig())
    mc = MismatchConfig(tail_decay=(8.0, 8.0), tail_weight=(0.15, 0.15))
    mis = MismatchedToF(scene, None, ToFConfig(noise=False), mc)
    taps = mis.tail_taps(0, warm=20.0)
    assert taps.size == mc.tail_lags and np.isclose(taps.sum(), 0.15)
    ratio = taps[1:] / taps[:-1]
    assert np.allclose(ratio, ratio[0])
    assert taps[-1] < 1e-4 * taps[0]
    old = MismatchedToF(scene, None, ToFConfig(noise=False), mc.model_copy(update={"tail_lags": 23}))
    assert old.tail_taps(0, warm=20.0).size == 23 and old.tail_taps(0, warm=20.0)[-1] > 0.09 * old.tail_taps(0, 20.0)[0]


def test_a_zones_own_time_scale_moves_its_return_in_proportion_to_range():
    # off by default (a seed's frames are what they were); on, each zone's return moves with its own sign, by more
    # the farther the table
    def centroids(height, mc):
        scene, data, _, _ = _pair(height)
        mis = MismatchedToF(scene, data, ToFConfig(noise=False), mc)
        h = mis.measure().hists
        h = np.clip(h - np.median(h, axis=1, keepdims=True), 0.0, None)
        b = np.arange(h.shape[1])
        h = np.where(np.abs(b - h.argmax(axis=1, keepdims=True)) <= 4, h, 0.0)  # the return: not the internal one
        return (h * b).sum(1) / h.sum(1), mis

    still = MismatchConfig(ambient_drift=0.0, ambient_slope=0.0)
    scaled = still.model_copy(update={"zone_time_scale": 0.05})
    (near0, _), (near1, mis) = centroids(0.1, still), centroids(0.1, scaled)
    (far0, _), (far1, _) = centroids(0.35, still), centroids(0.35, scaled)
    u = mis._time_scale - 1.0
    assert np.all(np.abs(u) <= 0.05) and np.ptp(u) > 0.02
    moved = np.abs(u) > 0.005
    assert np.all(np.sign(far1 - far0)[moved] == np.sign(u)[moved])
    assert np.all(np.abs(far1 - far0)[moved] > np.abs(near1 - near0)[moved])
    _, _, _, default = _pair(0.1)
    assert np.all(default._time_scale == 1.0)


def test_a_zones_own_time_scale_moves_its_return_before_the_bins():
    """The scale moves each ray's return before it is binned (``MismatchedToF.timed``: the ranges times the zone's
    scale, the albedo times its square so the counts stay), so a zone's return is rendered as the sensor renders any
    return, at ``1 + u`` times its range. (It used to resample the binned histogram about range 0, which also averaged
    neighbouring bins by where the return fell: a blur no sensor's bins have.)"""
    still = MismatchConfig(ambient_drift=0.0, ambient_slope=0.0, skew_bins=0.0, drift_bins_per_degc=0.0,
                           tail_weight=(0.0, 0.0), zone_time_scale=0.05, seed=3)
    scene, data, _, _ = _pair(0.2)
    mis = MismatchedToF(scene, data, ToFConfig(noise=False), still)
    returns = mis.cast()
    s = mis._time_scale
    assert np.ptp(s) > 0.02
    t = mis.timed(returns)
    np.testing.assert_allclose(t.ranges[returns.hit], (returns.ranges * s[:, None])[returns.hit])
    np.testing.assert_allclose(t.albedo, returns.albedo * s[:, None] ** 2)
    # what the unit reports is the sensor's render of the timed returns (the tails here are none and the delays 0)
    ref = mis._kernel_ref
    h = mis.render(returns, ref)
    np.testing.assert_allclose(h, SimToF._render(mis, t, ref), rtol=1e-12, atol=1e-9)
    flat = MismatchedToF(scene, data, ToFConfig(noise=False), still.model_copy(update={"zone_time_scale": 0.0}))
    assert flat.timed(returns) is returns
    # the counts stay: each zone's histogram sums to what the unit without scales renders
    np.testing.assert_allclose(h.sum(axis=1), flat.render(returns, ref).sum(axis=1), rtol=1e-3)
    # and it is what a forward model whose own zone time scales are the unit's renders of the rays as they are
    # (ForwardParams.zone_bin_scales: a return at range r at r / bin_size * scale past the zone's range-0 bin)
    from place_safe.recovery.forward import ForwardModel, ZoneRays
    oracle = MismatchedToF(scene, data, ToFConfig(noise=False), still)
    oracle.forward = ForwardModel(oracle.params.model_copy(update={"zone_bin_scales": [float(v) for v in s]}),
                                  ZoneRays.stratified(oracle.config.rays))
    oracle._kernel = None
    np.testing.assert_allclose(SimToF._render(oracle, returns, ref), h, rtol=1e-9, atol=1e-9 * h.max())
    # the near-range blinding (the glint off the table) sees the rays as they are, not their albedo times the scale
    blind = MismatchedToF(scene, data, ToFConfig(noise=False, blinding=True), still)
    plain = MismatchedToF(scene, data, ToFConfig(noise=False), still)
    r = blind.cast()
    np.testing.assert_allclose(blind.render(r, ref), plain.render(r, ref) * blind.blinding_factors(r)[:, None],
                               rtol=1e-9, atol=1e-9 * h.max())


def test_a_unit_mounted_off_its_nominal_orientation_turns_its_rays_and_keeps_its_other_differences():
    """``MismatchConfig.mount_tilt`` turns every ray by the mount rotation (the forward model's convention, so a
    forward fit can find it) and draws nothing: the seed's other differences stay what they were."""
    from place_safe.recovery.forward import mount_rotation

    scene = build_scene(SceneConfig())
    tilt = (0.012, -0.02)
    plain = MismatchedToF(scene, None, ToFConfig(noise=False), MismatchConfig())
    mounted = MismatchedToF(scene, None, ToFConfig(noise=False), MismatchConfig(mount_tilt=tilt))
    turned = plain.directions @ mount_rotation(list(tilt)).numpy().T
    assert np.allclose(mounted.directions, turned)
    assert np.allclose(mounted.params.mount_tilt, tilt)
    for name in ("_tail_w", "_tail_k", "_skew", "_amb_phase", "_time_scale", "ambient"):
        assert np.array_equal(getattr(mounted, name), getattr(plain, name)), name
    for name in ("glass_gains", "glass_delay", "crosstalk_grid"):
        assert getattr(mounted.params, name) == getattr(plain.params, name), name
    with pytest.raises(ValueError):
        MismatchConfig(mount_tilt=(0.2, 0.0))  # beyond 3 deg: not a mount error
