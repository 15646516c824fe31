"""Approach speeds derived from sensor latency and braking distance (property: the arm can always stop)."""

from __future__ import annotations

import math

from hypothesis import given
from hypothesis import strategies as st

from place_safe.placement.speed import approach_speed, stoppable_speed


@given(st.floats(0.0, 2.0), st.floats(0.0, 0.5), st.floats(0.05, 5.0))
def test_from_the_stoppable_speed_the_arm_stops_within_the_distance(d, latency, accel):
    v = stoppable_speed(d, latency, accel)
    assert v >= 0.0
    assert v * latency + v * v / (2 * accel) <= d + 1e-9


@given(st.floats(-1.0, 1.0), st.floats(0.0, 0.5))
def test_approach_speed_stays_between_the_slow_speed_and_the_cap(c, latency):
    v = approach_speed(c, 0.015, latency, 0.5, 0.25, 0.015)
    assert 0.015 <= v <= 0.25


def test_bad_inputs_give_no_speed():
    assert stoppable_speed(math.nan, 0.1, 0.5) == 0.0
    assert stoppable_speed(0.1, 0.1, 0.0) == 0.0
    assert stoppable_speed(-0.1, 0.1, 0.5) == 0.0
