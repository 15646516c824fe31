"""Descent speed from what the robot can still stop in: sensor latency, braking, and a planned slow-down.

Concept: while the surface is far the cup may move fast, but two limits hold at every cup clearance ``c``
above the sensed surface:

* **planned braking** (:func:`braking_speed`): the cup arrives at the slow band (``slow_clearance``) at the
  band's speed ``v_band``, decelerating at ``accel``: ``v = sqrt(v_band**2 + 2 * accel * (c - slow_clearance))``.
  For a surface that stays where it was sensed this is all the arm needs (the clearance is computed from
  the current TCP pose each control tick, so it is not late).
* **room for a late surprise** (:func:`stoppable_speed`): if a frame shows the surface (or something on it)
  higher than believed, the machine learns it ``latency`` s late (a frame is measured, transferred and
  estimated before the machine sees it) and then brakes at ``accel``; the distance covered,
  ``v * latency + v**2 / (2 * accel)``, must fit in the measured clearance minus ``margin``.

:func:`descent_speed` is the smallest of these and the cap ``v_max``, never below ``v_band``.
SI units (m, s, m/s, m/s^2).
"""

from __future__ import annotations

import math


MIN_DISTANCE = 1e-12
"""m: a stopping distance below this (a picometre) is none: subnormal arithmetic would give nonsense speeds."""


def stoppable_speed(distance: float, latency: float, accel: float) -> float:
    """Largest speed (m/s) from which reacting ``latency`` s late and braking at ``accel`` stops within
    ``distance`` m (0 for no distance; NaN inputs give 0)."""
    if not (distance > MIN_DISTANCE and accel > 0 and latency >= 0):
        return 0.0
    # the root of v latency + v^2 / (2 accel) = distance, written without the cancellation of
    # accel (-latency + sqrt(...)), which went negative (-2e-323) for subnormal distances
    v = 2.0 * distance / (latency + math.sqrt(latency * latency + 2.0 * distance / accel))
    return max(v, 0.0) if math.isfinite(v) else 0.0


def braking_speed(distance: float, accel: float, v_end: float) -> float:
    """Speed (m/s) from which braking at ``accel`` reaches ``v_end`` after ``distance`` m (``v_end`` for no
    distance; NaN inputs give ``v_end``, or 0 if it is not a number)."""
    v_end = v_end if v_end >= 0 else 0.0
    if not (distance > 0 and accel > 0):
        return v_end if math.isfinite(v_end) else 0.0
    v = math.sqrt(v_end * v_end + 2.0 * accel * distance)
    return max(v, v_end) if math.isfinite(v) else v_end  # (max: squares of tiny speeds underflow)


def descent_speed(clearance: float, slow_clearance: float, margin: float, latency: float, accel: float,
                  v_max: float, v_band: float) -> float:
    """Speed (m/s) at cup ``clearance`` (m) above the sensed surface (see the module docstring): at most
    ``v_max``; braking at ``accel`` arrives at ``slow_clearance`` at ``v_band``; reacting ``latency`` s late
    and braking at ``accel`` still stops ``margin`` m above the surface; never below ``v_band``."""
    return max(v_band, min(v_max, braking_speed(clearance - slow_clearance, accel, v_band),
                           stoppable_speed(clearance - margin, latency, accel)))


def slosh_rise(accel: float, radius: float, amplification: float = 2.0) -> float:
    """m the liquid's surface rises at the wall of a cup of inner ``radius`` (m) accelerated sideways at
    ``accel`` (m/s^2): the quasi-static free surface tilts by atan(accel / g), so it rises
    ``radius * accel / g`` at the wall; ``amplification`` allows for sloshing (a step in acceleration
    overshoots the static tilt by up to 2x). A full cup (10 mm below its rim, 35 mm radius) stays
    unspilled below about 1.4 m/s^2 by this bound; the placement's ``lateral_accel`` (1.2 m/s^2) gives
    8.6 mm."""
    return amplification * radius * abs(accel) / 9.81


def stopping_distance(speed: float, latency: float, accel: float) -> float:
    """m covered from ``speed`` when the machine reacts ``latency`` s late and then brakes at ``accel``."""
    return speed * latency + speed * speed / (2.0 * accel)


__all__ = ["stoppable_speed", "braking_speed", "descent_speed", "stopping_distance", "slosh_rise"]
