"""The contact detector on a CB3-like force estimate: free-air noise is not contact, a touch is, the threshold
comes from the noise measured at rest; invariants as hypothesis properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.robot.contact_detector import (ContactDetector, DetectorSettings, detection_delay,
                                               false_alarm_rate, touch_latency)

DOWN = np.array([0.0, 0.0, -1.0])  # the tool moves down: a table pushes up (+z)


def _rest(det: ContactDetector, rng, sigma=3.6, offset=(2.0, -1.0, 6.0), n=50):
    det.zero(rng.normal(0.0, sigma, (n, 3)) + offset)


def test_free_air_cb3_noise_is_never_contact_and_a_table_touch_is():
    rng = np.random.default_rng(3)
    det = ContactDetector(DetectorSettings.for_controller("cb3"))
    offset = np.array([2.0, -1.0, 6.0])
    _rest(det, rng, offset=offset)
    for _ in range(20_000):  # 160 s of free-air descent at 125 Hz
        assert not det.update(rng.normal(0.0, 3.6, 3) + offset, DOWN)
        assert det.contact_force() == 0.0
    for k in range(40):  # a 15 N touch: seen within a few cycles
        if det.update(rng.normal(0.0, 3.6, 3) + offset + [0.0, 0.0, 15.0], DOWN):
            break
    assert det.contact and k < 10 and det.contact_force() > det.threshold


def test_threshold_follows_the_noise_measured_at_rest_never_below_the_setting():
    rng = np.random.default_rng(0)
    det = ContactDetector(DetectorSettings.for_controller("cb3"))
    _rest(det, rng, sigma=1.0)  # quieter than the setting: the setting's floor holds
    assert det.noise_std == pytest.approx(3.6)
    t_cb3 = det.threshold
    _rest(det, rng, sigma=8.0)  # a noisier arm: the threshold rises with it
    assert det.noise_std > 7.0 and det.threshold > 2 * t_cb3
    assert np.all(det.rest_std > 7.0)


def test_e_series_defaults_are_more_sensitive():
    cb3, es = DetectorSettings.for_controller("cb3"), DetectorSettings.for_controller("e-series")
    assert es.threshold() < cb3.threshold() and es.period < cb3.period


def test_a_force_along_the_motion_is_not_a_touch_and_a_nan_reading_is():
    det = ContactDetector(DetectorSettings(noise_std=1.0))
    det.zero(np.zeros((5, 3)) + np.random.default_rng(1).normal(0, 0.1, (5, 3)))
    for _ in range(20):  # pulled along the motion (not pushed back): no touch of a surface
        det.update([0.0, 0.0, -2.0], DOWN)
    assert not det.contact
    assert det.update([math.nan, 0.0, 0.0], DOWN) and det.contact_force() == math.inf


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), sigma=st.floats(0.2, 6.0), cycles=st.integers(1, 400))
def test_contact_force_is_zero_or_at_least_half_the_threshold(seed, sigma, cycles):
    """Invariant: the reported force is 0 without a confirmed contact, and a confirmed one reports the averaged
    force (never a single raw sample's norm)."""
    rng = np.random.default_rng(seed)
    det = ContactDetector(DetectorSettings(noise_std=sigma))
    det.zero(rng.normal(0.0, sigma, (50, 3)))
    for _ in range(cycles):
        det.update(rng.normal(0.0, sigma, 3) + [0, 0, rng.uniform(0, 4 * sigma)], DOWN)
        f = det.contact_force()
        assert f == 0.0 if not det.contact else f >= 0.5 * det.threshold


def test_rate_and_delay_functions_report_numbers():
    s = DetectorSettings.for_controller("cb3")
    fa = false_alarm_rate(s, 3.6, cycles=100_000)
    assert fa["cycles"] == 100_000 and fa["per_cycle"] < 1e-3
    d = detection_delay(s, 3.6, step=15.0, trials=200)
    assert d["missed"] == 0.0 and 0 < d["delay_median"] <= 0.05
    assert detection_delay(s, 3.6, step=0.0, ramp=0.0, trials=20, max_seconds=0.1)["missed"] > 0.5


def _cb3_after_rest(rng, offset):
    """A CB3 detector zeroed on a quiet rest reading, so its threshold is exactly the setting's (7.35 N): the
    strictest case for false alarms. (Zeroed on 50 samples of 3.6 N noise, the largest of the three measured
    spreads is ~3.9 N and the threshold ~7.9 N: fewer false alarms, slower touches -- see issue 29b's report.)"""
    det = ContactDetector(DetectorSettings.for_controller("cb3"))
    det.zero(rng.normal(0.0, 1.0, (50, 3)) + offset)
    assert det.threshold == pytest.approx(5.0 * 3.6 / math.sqrt(6))
    return det


@settings(max_examples=8, deadline=None)
@given(offset=st.tuples(*[st.floats(-30.0, 30.0)] * 3))
def test_cb3_noise_never_alarms_whatever_the_rest_offset(offset):
    """Invariant: 8000 cycles (64 s) of a fixed seed's CB3 noise (3.6 N per axis) never read as contact, whatever
    the payload offset the rest reading takes away."""
    rng = np.random.default_rng(29)
    det = _cb3_after_rest(rng, np.asarray(offset))
    noise = rng.normal(0.0, 3.6, (8000, 3)) + np.asarray(offset)
    assert not any(det.update(f, DOWN) for f in noise)
    assert det.contact_force() == 0.0


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 100_000), before=st.integers(0, 50))
def test_a_10n_step_on_cb3_noise_is_always_seen_within_30_cycles(seed, before):
    """Invariant: a touch that steps to 10 N against the approach direction is confirmed within 30 cycles
    (240 ms) on CB3 noise, and then reports an averaged force well above the noise."""
    rng = np.random.default_rng(seed)
    offset = np.array([1.0, 2.0, -5.0])
    det = _cb3_after_rest(rng, offset)
    for _ in range(before):
        det.update(rng.normal(0.0, 3.6, 3) + offset, DOWN)
    seen = [det.update(rng.normal(0.0, 3.6, 3) + offset + [0.0, 0.0, 10.0], DOWN) for _ in range(30)]
    assert any(seen)
    assert det.contact_force() > 0.5 * det.threshold


def test_a_10n_step_on_cb3_noise_is_seen_within_6_cycles_in_95_percent_of_touches():
    """The issue's figure in cycles (6 cycles of 8 ms = 48 ms <= 50 ms), over 400 seeded touches through the
    streaming detector (not the vectorised measurement), at the setting's threshold."""
    within = 0
    for seed in range(400):
        rng = np.random.default_rng(seed)
        det = _cb3_after_rest(rng, np.zeros(3))
        for _ in range(10):
            det.update(rng.normal(0.0, 3.6, 3), DOWN)
        within += any(det.update(rng.normal(0.0, 3.6, 3) + [0.0, 0.0, 10.0], DOWN) for _ in range(6))
    assert within >= 0.95 * 400


@settings(max_examples=40, deadline=None)
@given(axis=st.integers(0, 2), bad=st.sampled_from([math.nan, math.inf, -math.inf]), where=st.booleans(),
       cycles=st.integers(0, 20))
def test_a_non_finite_reading_or_direction_is_contact(axis, bad, where, cycles):
    """Invariant: fail closed -- a non-finite force component or approach direction is a confirmed contact of
    infinite force, whatever came before."""
    rng = np.random.default_rng(cycles)
    det = _cb3_after_rest(rng, np.zeros(3))
    for _ in range(cycles):
        det.update(rng.normal(0.0, 3.6, 3), DOWN)
    f, a = rng.normal(0.0, 3.6, 3), DOWN.copy()
    (f if where else a)[axis] = bad
    assert det.update(f, a) and det.contact and det.contact_force() == math.inf


def test_cb3_default_meets_the_10n_50ms_figure_on_synthetic_noise():
    s = DetectorSettings.for_controller("cb3")
    d = detection_delay(s, 3.6, step=10.0, trials=1000)
    assert d["missed"] == 0.0 and d["delay_p95"] <= 0.05 and d["delay_median"] <= 0.04


@pytest.mark.parametrize("bad", [{"window": 0}, {"noise_std": -1.0}, {"sigmas": math.nan}, {"persistence": True}])
def test_bad_settings_are_refused(bad):
    with pytest.raises(ValueError):
        DetectorSettings(**bad)


def test_rest_spread_within_sampling_error_keeps_the_setting() -> None:
    """Zeroing on 50 samples of the CB3's own 3.6 N noise does not raise the threshold by sampling chance
    (the largest of three per-axis estimates is ~10 % high), but a clearly noisier arm (6 N) does."""
    settings = DetectorSettings.for_controller("cb3")
    rng = np.random.default_rng(7)
    kept = 0
    for _ in range(200):
        det = ContactDetector(settings)
        det.zero(rng.normal(0.0, 3.6, size=(50, 3)) + [1.0, -2.0, 3.0])
        kept += det.threshold == settings.threshold()
    assert kept >= 190
    noisy = ContactDetector(settings)
    noisy.zero(rng.normal(0.0, 6.0, size=(50, 3)))
    assert noisy.noise_std > 5.0
    assert noisy.threshold > settings.threshold()


def test_the_touch_latency_follows_the_noise_measured_at_rest():
    """As zeroed on the CB3's own noise the detector reports a 10 N touch as late as its settings say (48 ms); zeroed on
    a noisier arm (6 N per axis) it raised its threshold and reports it later, as touch_latency at that noise does."""
    settings = DetectorSettings.for_controller("cb3")
    rng = np.random.default_rng(3)
    det = ContactDetector(settings)
    det.zero(rng.normal(0.0, 3.6, size=(50, 3)))
    assert det.noise_std == settings.noise_std and det.touch_latency() == touch_latency(settings) == 0.048
    det.zero(rng.normal(0.0, 6.0, size=(50, 3)))
    assert det.noise_std > 5.0
    assert det.touch_latency() > 0.2  # (inf: a detector that misses more than 1 in 20 such touches)
