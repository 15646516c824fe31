"""The time budget of a placement: where the seconds from start to release go, and what limit sets each part.

Concept: :class:`~place_safe.placement.machine.PlacementMachine` adds the robot time of every control tick
to one *bucket* (:attr:`PlacementMachine.budget`, seconds); :data:`BUCKETS` lists them in the order a
placement passes through them. :func:`budget_limits` says, for a
:class:`~place_safe.placement.config.PlacementConfig` and a sensor's frame period and latency, which
setting or physical limit sets the length of each bucket and what that length is at best.

Buckets (robot clock, s):

* ``wait for surface``: before the first fused plane (the sensor's first frames must arrive);
* ``accelerate``: the arm is still below a descent speed it was given (``accel``);
* ``cruise``: descending at ``approach_speed``;
* ``brake``: the descent profile (:mod:`place_safe.placement.speed`) holds the speed below the cruise;
* ``survey``: what moving sideways to see the landing footprint (and back) takes from the descent -- a tick
  in which the cup descends at a fraction ``f`` of the speed it would have without the sideways move counts
  ``1 - f`` of its time here and the rest for the descent's part -- and waiting for the footprint's frames;
* ``confirm contact``: stopped on a contact far above the surface, deciding whether it is real;
* ``slow band``: the last ``slow_clearance - stop_clearance`` at ``descend_speed``;
* ``stop``: from the stop command until frames count for the check (``check_settle``);
* ``check frames``: waiting for the post-stop measurements the release rule needs;
* ``release``: gripper open, ``release_settle``; ``retreat``: moving up (after the decision).
"""

from __future__ import annotations

import math
from typing import Any

from place_safe.placement.rules import most_check_frames
from place_safe.placement.speed import slosh_rise

#: Budget buckets in the order a placement passes through them (see the module docstring).
BUCKETS = ("wait for surface", "accelerate", "cruise", "brake", "survey", "confirm contact", "slow band", "stop",
           "check frames", "release", "retreat")
#: Buckets that come before the release decision (the time from the start to the release).
BEFORE_RELEASE = BUCKETS[:9]


def budget_limits(cfg: Any, frame_period: float, frame_latency: float) -> dict[str, str]:
    """What sets each bucket (one line each, SI numbers) for placement settings ``cfg``, a sensor taking a
    frame every ``frame_period`` s that arrives ``frame_latency`` s after it was measured."""
    a, v = cfg.accel, cfg.approach_speed
    band = max(cfg.slow_clearance - cfg.stop_clearance, 0.0)
    stop_dist = cfg.descend_speed ** 2 / (2 * a)
    brake = (v - cfg.descend_speed) / a
    lo = cfg.check_frames
    hi = most_check_frames(cfg)
    first = frame_latency + 2 * frame_period
    return {
        "wait for surface": f"first fused plane: frames every {frame_period * 1e3:.0f} ms arrive "
                            f"{frame_latency * 1e3:.0f} ms after they are measured (>= {first:.2f} s for 3)",
        "accelerate": f"accel {a:.2f} m/s^2 (robot max_linear_accel): {v / a:.2f} s to {v:.2f} m/s",
        "cruise": f"approach_speed {v:.2f} m/s (robot max_linear_speed): {1 / v:.2f} s per metre",
        "brake": f"braking at {a:.2f} m/s^2 to {cfg.descend_speed * 1e3:.0f} mm/s at the slow band "
                 f"({brake:.2f} s from cruise), and reacting {cfg.sensor_latency * 1e3:.0f} ms late still stops "
                 f"{cfg.brake_margin * 1e3:.0f} mm above the sensed surface",
        "survey": f"sideways moves share the arm's {v:.2f} m/s with the descent (at most survey_speed "
                  f"{cfg.survey_speed:.2f} m/s, lateral_accel {cfg.lateral_accel:.2f} m/s^2: the liquid rises <= "
                  f"{slosh_rise(cfg.lateral_accel, cfg.cup_radius) * 1e3:.1f} mm at the wall); "
                  f"{cfg.footprint_frames} frames seeing the footprint from <= the close height",
        "confirm contact": f"obstacle_confirm {cfg.obstacle_confirm:.2f} s at rest after a hard stop",
        "slow band": f"{band * 1e3:.0f} mm at descend_speed {cfg.descend_speed * 1e3:.0f} mm/s = "
                     f"{band / cfg.descend_speed:.2f} s (the speed at which a surface sensed a centimetre off, or a box "
                     "the map missed, is met; the CB3 detector sees a touch ~40 ms late)",
        "stop": f"check_settle {cfg.check_settle * 1e3:.0f} ms (braking from {cfg.descend_speed * 1e3:.0f} mm/s "
                f"takes {cfg.descend_speed / a * 1e3:.0f} ms, {stop_dist * 1e3:.2f} mm)",
        "check frames": f"{lo} post-stop measurements ({hi} near a limit, sized from the fused uncertainty): "
                        f">= {frame_latency + (lo - 1) * frame_period:.2f} s "
                        f"({frame_latency * 1e3:.0f} ms transfer + {lo - 1} frame periods)",
        "release": f"release_settle {cfg.release_settle:.2f} s with the gripper open (after the decision)",
        "retreat": f"{cfg.retreat_distance * 1e3:.0f} mm up at {cfg.retreat_speed * 1e3:.0f} mm/s (after the decision)",
    }


def median_budget(budgets: list[dict], buckets: tuple[str, ...] = BUCKETS) -> dict[str, float]:
    """Median seconds per bucket over placements (a bucket a placement never entered counts as 0 s)."""
    import numpy as np

    if not budgets:
        return {}
    return {b: float(np.median([float((d or {}).get(b, 0.0)) for d in budgets])) for b in buckets}


def format_budget(median: dict[str, float], limits: dict[str, str], runs: int) -> str:
    """A console table: bucket, median seconds, what sets it; with the median total up to the release."""
    if not median:
        return "time budget: no releases"
    lines = [f"time budget (median s over {runs} releases; the total of medians is not the median total):",
             f"  {'part':<17} {'s':>5}  limit"]
    for b in BUCKETS:
        lines.append(f"  {b:<17} {median.get(b, 0.0):5.2f}  {limits.get(b, '')}")
    total = sum(median.get(b, 0.0) for b in BEFORE_RELEASE)
    lines.append(f"  {'to release':<17} {total:5.2f}" + ("" if math.isfinite(total) else " (incomplete)"))
    return "\n".join(lines)


__all__ = ["BUCKETS", "BEFORE_RELEASE", "budget_limits", "median_budget", "format_budget"]
