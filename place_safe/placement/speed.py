"""Approach speed from what the robot can still stop in: sensor latency and braking distance.

Concept: while the surface is far the cup may move fast, but only as fast as lets the arm stop
before the slow band above the surface even if it learns about a change ``latency`` seconds late
(a frame is measured, transferred and estimated before the machine sees it) and then brakes at
``accel``. The distance covered is ``v * latency + v**2 / (2 * accel)``; :func:`stoppable_speed`
is the largest ``v`` for which that fits in the distance left. SI units (m, s, m/s, m/s^2).
"""

from __future__ import annotations

import math


def stoppable_speed(distance: float, latency: float, accel: float) -> float:
    """Largest speed (m/s) from which reacting ``latency`` s late and braking at ``accel`` stops within
    ``distance`` m (0 for no distance; NaN inputs give 0)."""
    if not (distance > 0 and accel > 0 and latency >= 0):
        return 0.0
    v = accel * (-latency + math.sqrt(latency * latency + 2.0 * distance / accel))
    return v if math.isfinite(v) else 0.0


def approach_speed(clearance: float, slow_clearance: float, latency: float, accel: float, v_max: float,
                   v_min: float) -> float:
    """Speed (m/s) at cup ``clearance`` above the surface: at most ``v_max``, stoppable before the slow band
    at ``slow_clearance``, never below ``v_min`` (the slow band's speed)."""
    return max(v_min, min(v_max, stoppable_speed(clearance - slow_clearance, latency, accel)))


__all__ = ["stoppable_speed", "approach_speed"]
