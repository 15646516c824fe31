"""ClockMap and PoseHistory (place_safe.placement.time_alignment): a frame's stamp on the robot's clock and the
pose it was measured from."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.placement.time_alignment import ClockMap, PoseHistory


def test_clock_map_and_pose_history():
    c = ClockMap("monotonic")
    assert math.isnan(c.to_robot(5.0))
    c.observe(10.0, 4.0)
    c.observe(10.1, 4.09)  # a fresher robot packet: larger offset
    assert c.offset == pytest.approx(6.01)
    assert math.isnan(c.to_robot("x")) and ClockMap("robot").to_robot(3.0) == 3.0
    h = PoseHistory(tolerance=0.004)
    A, B = np.eye(4), np.eye(4)
    B[:3, 3] = (0.0, 0.0, 1.0)
    h.add(0.0, A)
    h.add(1.0, B)
    h.add(1.0, B)  # same time: replaces
    h.add(float("nan"), A)  # ignored
    assert h.at(0.5)[2, 3] == pytest.approx(0.5)
    assert h.at(2.0) is None and h.at(float("nan")) is None


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.one_of(st.floats(-1e3, 1e3), st.just(math.nan)), st.floats(-1.0, 1.0)), min_size=1, max_size=30),
       st.one_of(st.floats(-2e3, 2e3), st.just(math.nan)))
def test_pose_history_never_extrapolates(samples, t):
    """Whatever is recorded, a pose is only given inside the recorded span (plus the tolerance), and it lies
    between the recorded positions: a frame is never placed at a pose the robot was not at."""
    h = PoseHistory(tolerance=0.004)
    kept: list[tuple[float, float]] = []
    for when, z in samples:
        T = np.eye(4)
        T[2, 3] = z
        h.add(when, T)
        if math.isfinite(when):
            kept = [(a, b) for a, b in kept if a < when] + [(when, z)]
    pose = h.at(t)
    if not kept or not math.isfinite(t) or t < kept[0][0] - 0.004 or t > kept[-1][0] + 0.004:
        assert pose is None
    else:
        assert pose is not None
        zs = [z for _, z in kept]
        assert min(zs) - 1e-9 <= pose[2, 3] <= max(zs) + 1e-9
