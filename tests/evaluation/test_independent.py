"""Physical sanity of the independent test generator (place_safe.evaluation.independent).

These check the generator against physics (time of flight, inverse square law, geometry, Poisson
statistics), not against the project's forward model, which it does not import.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from place_safe.evaluation.independent import (FINE, PULSE_MODES, IndependentGenerator, SceneSpec, SensorSpec,
                                               zone_pulse)
from place_safe.geometry import Plane
from place_safe.sensor.histogram import find_peaks


def _gen(**kw) -> IndependentGenerator:
    return IndependentGenerator(SensorSpec.draw(0, **kw))


def _net(h: np.ndarray) -> np.ndarray:
    return h - np.median(h[:, 100:], axis=1, keepdims=True)


def test_frames_are_valid_and_reproducible():
    a = _gen().frames(4, seed=3)
    b = _gen().frames(4, seed=3)
    for fa, fb in zip(a, b):
        fa.validate()
        assert np.array_equal(fa.hists, fb.hists) and np.array_equal(fa.reference, fb.reference)
        assert np.all(fa.hists >= 0) and np.all(fa.hists == np.round(fa.hists))
        assert fa.truth is not None and 0.02 <= fa.truth.z0 <= 0.30 and fa.truth.theta <= math.radians(30) + 1e-9
    assert not np.array_equal(a[0].hists, _gen().frames(1, seed=4)[0].hists)


@pytest.mark.parametrize("noise", [True, False])
def test_generators_report_no_distance_where_their_histograms_show_no_return(noise):
    """``synth --min-distance 4.9 --max-distance 5`` wrote on-sensor distances of about 5 m at confidence 255 over
    histograms with nothing in them (both generators); there is no object to report now. Near planes keep theirs."""
    from place_safe.evaluation.synthetic import SyntheticSpec
    from place_safe.evaluation.synthetic import make_frames as model_frames

    far = ((4.9, 5.0), (0.0, math.radians(30)))
    for f in _gen().frames(3, seed=1, scene=SceneSpec(*far, noise=noise)) + \
            model_frames(3, seed=1, spec=SyntheticSpec(z_range=far[0], theta_range=far[1], noise=noise)):
        assert not find_peaks(f.hists)[1].any()  # the histograms show no return
        assert np.all(f.distances == 0.0) and np.all(f.confidences == 0.0)
    for f in _gen().frames(3, seed=1, scene=SceneSpec((0.05, 0.3), far[1], noise=noise)):
        assert np.all(f.distances > 0.0) and np.all(f.confidences == 255.0)


def test_peak_moves_one_bin_per_bin_size_of_range():
    g = _gen(pileup=0.0)
    s = g.sensor
    pos = []
    for z in (0.10, 0.25):
        h = g.expected(Plane(np.array([0, 0, 1.0]), z), 1.0, 0.0, 1.0)
        pos.append(find_peaks(h)[0][4])
    assert pos[1] - pos[0] == pytest.approx(0.15 / s.bin_size, abs=0.3)


def test_far_returns_fall_with_the_inverse_square():
    g = _gen(pileup=0.0, crosstalk=0.0)
    tot = [_net(g.expected(Plane(np.array([0, 0, 1.0]), z), 1.0, 0.0, 1.0))[4].sum() for z in (0.4, 0.8)]
    assert tot[0] / tot[1] == pytest.approx(4.0, rel=0.05)


def test_close_returns_saturate():
    g = _gen(pileup=0.0, crosstalk=0.0)
    tot = [_net(g.expected(Plane(np.array([0, 0, 1.0]), z), 1.0, 0.0, 1.0))[4].sum() for z in (0.02, 0.04)]
    assert 0.8 < tot[0] / tot[1] < 2.0  # far less than the inverse square's 4


def test_tilted_plane_is_nearer_on_the_side_its_normal_points_to():
    g = _gen(pileup=0.0)
    t = math.radians(25)
    h = g.expected(Plane(np.array([math.sin(t), 0.0, math.cos(t)]), 0.12), 1.0, 0.0, 1.0)
    pos = find_peaks(h)[0]
    # n . x = d with n_x > 0: along rays with x > 0 (zones 1-3) the plane is nearer than at x < 0 (zones 7-9)
    assert pos[:3].mean() < pos[3:6].mean() < pos[6:].mean()
    assert pos[6:].mean() - pos[:3].mean() > 1.0


def test_without_baseline_or_pixel_spread_the_sensor_is_mirror_symmetric():
    g = _gen(baseline=(0.0, 0.0), pixel_gain_spread=0.0, zone_offsets=[0.0] * 9,
             zone_tail_weight=[0.0] * 9)
    h = g.expected(Plane(np.array([0, 0, 1.0]), 0.03), 1.0, 0.1, 2.0)
    assert np.allclose(h[1], h[7], rtol=1e-9)  # zones 2 and 8 mirror each other in x
    assert np.allclose(h[3], h[5], rtol=1e-9)  # zones 4 and 6 in y


def test_emitter_baseline_brightens_the_zones_on_its_side_at_close_range():
    g = _gen(baseline=(0.004, 0.0), pixel_gain_spread=0.0, zone_offsets=[0.0] * 9, zone_tail_weight=[0.0] * 9,
             pileup=0.0, crosstalk=0.0)
    h = _net(g.expected(Plane(np.array([0, 0, 1.0]), 0.01), 1.0, 0.0, 1.0))
    assert h[1].sum() > 1.02 * h[7].sum()


def test_poisson_noise_has_unit_scaled_spread():
    g = _gen()
    noisy = g.frames(1, seed=5)[0]
    clean = g.frames(1, seed=5, scene=SceneSpec(noise=False))[0]
    assert noisy.truth.offset == clean.truth.offset
    z = (noisy.hists - clean.hists) / np.sqrt(clean.hists + 1e-9)
    assert np.sqrt(np.mean(z ** 2)) == pytest.approx(1.0, abs=0.1)


def test_crosstalk_modes_differ_by_the_zone_itself():
    plane = Plane(np.array([0.1, 0.0, 1.0]), 0.1)
    h_all = _gen(pileup=0.0, crosstalk_mode="all").expected(plane, 1.0, 0.0, 1.0)
    h_oth = _gen(pileup=0.0, crosstalk_mode="others").expected(plane, 1.0, 0.0, 1.0)
    c = SensorSpec.draw(0).crosstalk
    total = h_oth.sum(0) / (1.0 + 8.0 * c)  # h_oth = d + c (sum d - d): sum over zones = (1 + 8c) sum d
    direct = (h_oth - c * total) / (1.0 - c)
    assert np.allclose(h_all - h_oth, c * direct, rtol=1e-6, atol=1e-6)


def test_brighter_surfaces_give_more_counts_and_saturation_is_sublinear():
    plane = Plane(np.array([0, 0, 1.0]), 0.03)
    for mode in ("shaded", "unshaded"):
        g = _gen(pileup=0.0, saturation_mode=mode)
        a = _net(g.expected(plane, 0.5, 0.0, 1.0)).sum()
        b = _net(g.expected(plane, 1.0, 0.0, 1.0)).sum()
        assert a < b
        if mode == "shaded":
            assert b < 2.0 * a * 0.98
        else:  # saturation acts on the unshaded term only: reflectance scales the counts linearly
            assert b == pytest.approx(2.0 * a, rel=1e-6)


def test_pulse_modes_agree_on_the_pulse_position():
    s = SensorSpec.draw(0)
    peaks = []
    for mode in PULSE_MODES:
        k = zone_pulse(SensorSpec.draw(0, pulse_mode=mode))
        assert k.max() == pytest.approx(1.0) and np.all(k >= 0)
        peaks.append(np.argmax(k) / FINE)
    assert max(peaks) - min(peaks) < 0.5
    assert np.mean(peaks) == pytest.approx(14.0 * s.ref_time_scale, abs=0.6)


def test_bad_structural_choice_is_rejected():
    with pytest.raises(ValueError, match="pulse_mode"):
        SensorSpec(pulse_mode="cubic")
