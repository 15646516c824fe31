"""Descent speeds from sensor latency and braking distance (property: the arm can always stop), the slosh bound."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from place_safe.placement.machine import PlacementConfig
from place_safe.placement.speed import braking_speed, descent_speed, slosh_rise, stoppable_speed, stopping_distance


@given(st.floats(0.0, 2.0), st.floats(0.0, 0.5), st.floats(0.05, 5.0))
def test_from_the_stoppable_speed_the_arm_stops_within_the_distance(d, latency, accel):
    v = stoppable_speed(d, latency, accel)
    assert v >= 0.0
    assert v * latency + v * v / (2 * accel) <= d + 1e-9


def test_bad_inputs_give_no_speed():
    assert stoppable_speed(math.nan, 0.1, 0.5) == 0.0
    assert stoppable_speed(0.1, 0.1, 0.0) == 0.0
    assert stoppable_speed(-0.1, 0.1, 0.5) == 0.0


@given(st.floats(-0.1, 1.0), st.floats(0.0, 0.3), st.floats(0.1, 5.0), st.floats(0.0, 0.02),
       st.floats(0.005, 0.05))
def test_descent_speed_always_leaves_room_to_stop_above_the_margin(c, latency, accel, margin, v_band):
    # the invariant of the profile: above the band speed, reacting `latency` late and braking at `accel`
    # stops at least `margin` above the sensed surface, and the cup arrives at the slow band no faster than
    # braking at `accel` allows
    slow = 0.010
    v = descent_speed(c, slow, margin, latency, accel, 0.25, v_band)
    assert v_band <= v <= max(0.25, v_band)
    if v > v_band + 1e-12:
        assert stopping_distance(v, latency, accel) <= c - margin + 1e-9
        assert v * v <= v_band * v_band + 2 * accel * (c - slow) + 1e-9


@given(st.floats(0.0, 1.0), st.floats(0.0, 5.0), st.floats(0.0, 1.0))
def test_braking_speed_reaches_the_end_speed_within_the_distance(d, accel, v_end):
    v = braking_speed(d, accel, v_end)
    assert v >= v_end
    if accel > 0:
        assert v * v <= v_end * v_end + 2 * accel * d + 1e-12


def test_bad_inputs_to_the_profile_give_the_band_speed():
    assert descent_speed(math.nan, 0.01, 0.005, 0.15, 1.2, 0.25, 0.025) == 0.025
    assert descent_speed(0.3, 0.01, 0.005, math.nan, 1.2, 0.25, 0.025) == 0.025
    assert braking_speed(math.nan, 1.0, 0.02) == 0.02


def test_the_default_lateral_acceleration_keeps_a_full_cup_unspilled():
    cfg = PlacementConfig()
    # a full cup: liquid 10 mm below the rim; the bound doubles the quasi-static rise for sloshing
    assert slosh_rise(cfg.lateral_accel, cfg.cup_radius) < 0.010
    assert slosh_rise(2 * cfg.lateral_accel, cfg.cup_radius) > slosh_rise(cfg.lateral_accel, cfg.cup_radius)
