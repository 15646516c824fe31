"""Too close to measure: a frame whose return overlaps the internal return is reported without a plane.

Concept
-------
The TMF8820's laser pulse is about 2.1 bins wide at half its height (the real sweep's returns at 5-8 cm:
about 29 mm of range). The light that never leaves the package (the internal / cover-glass return) and the
crosstalk between zones arrive at range 0. A surface closer than the pulse's half width at half maximum
therefore returns light whose peak lies within the internal return's width: the zones' peaks stop following
depth (on the real sweep the zones of the 0.5 cm frame read ranges from -0.3 to 9.7 mm; those of the
1.25 cm frame 2 mm farther, where the truth is 7.5 mm farther). Close to that range the emitter beside the
receiver no longer lights the centre zone's footprint (its return falls below 1 % of the brightest zone's at
1.25 and 2.0 cm, 10 % at 2.75 cm). The peak method's plane there is wrong by 10-85 deg while its covariance
claims a few degrees (normalised estimation error squared per degree of freedom 12-9000).

Such a frame is reported as what it is: no plane, with :data:`TOO_CLOSE_REASON`. The test
(:func:`overlap_reason`) looks at the frame alone, with the calibrated far-range mapping's first-pass
ranges (without the near-range table, which extrapolates there):

1. the median range of the zones with a return is below :data:`OVERLAP_RANGE` (the pulse's half width at
   half maximum: the return's peak lies within the internal return's width); or
2. the centre zone is dark (its return below :data:`DARK_CENTRE_FRACTION` of the frame's brightest, or none)
   while the median range is below :data:`DARK_CENTRE_RANGE` (a dark centre farther away is the scene: a
   hole, an edge, a black patch; the estimators deal with it as before).

On the real sweep (tests/data, both halves' calibrations) it flags the 0.5, 1.25 and 2.0 cm frames and none
from 2.75 cm on. The peak estimator (and so ``diff``, which starts from it and falls back to it) and the
on-sensor-distance estimator (a zone without an object counts as dark there: the sensor's result holds no
return heights) apply it. Units: metres.
"""

from __future__ import annotations

import math

import numpy as np

from place_safe.sensor.zones import N_ZONES

#: The reason of a frame without a plane because it is too close (``recover --jsonl`` ``reason`` starts so).
TOO_CLOSE_REASON = "too close: the return overlaps the internal return"
#: m: the pulse's half width at half maximum in range (1.05 bins of 14.1 mm): a median zone range below it
#: puts the return's peak within the internal return's width.
OVERLAP_RANGE = 0.0148
#: Fraction of the frame's brightest return below which the centre zone counts as dark.
DARK_CENTRE_FRACTION = 0.01
#: m: median zone range below which a dark centre zone means the emitter no longer lights it (the real
#: sweep's centre zone: 0.5 % of the brightest at 2.0 cm, 10 % at 2.75 cm, 33 % at 3.5 cm; the on-sensor
#: distances, mapped, read that 2.0 cm frame at 27 mm, its centre zone without an object).
DARK_CENTRE_RANGE = 0.03
#: Index of the centre zone (zone 5).
CENTRE = N_ZONES // 2


#: m: a frame whose nearest zone reads farther than this on the linear part of the mapping cannot be too close
#: (the mapping's corrections move a range by millimetres; each zone's own terms in the inverse range, by up to
#: 5 cm, are allowed for: ``PeakParams.inverse_screen_shift``): :func:`may_be_close` skips the test (a peak frame's
#: budget is half a millisecond).
SCREEN_RANGE = 0.1


def may_be_close(readings: np.ndarray, valid: np.ndarray, params) -> bool:
    """Whether the nearest zone with a return reads closer than :data:`SCREEN_RANGE` on the linear part of
    ``params``' mapping (:class:`~place_safe.recovery.points.PeakParams`; readings (9,) in its units). A few
    microseconds: only frames for which it is True need :func:`overlap_reason`."""
    x = np.where(np.asarray(valid, dtype=bool), np.asarray(readings, dtype=float), np.inf)
    k = int(x.argmin())
    nearest = float(x[k])
    if not math.isfinite(nearest):
        return False
    r = (nearest - params.b - params.zone_offsets[k]) / (params.m * params.zone_gains[k])
    if params.zone_inverse:  # each zone's own terms in the inverse range may take centimetres off a range
        r -= params.inverse_screen_shift()[k]
    return not r > SCREEN_RANGE


def overlap_reason(ranges: np.ndarray, valid: np.ndarray, heights: np.ndarray | None = None) -> str | None:
    """:data:`TOO_CLOSE_REASON` with what was seen, or None: for one frame's first-pass zone ranges (9,) (m,
    the far-range mapping's), their return mask (9,) and, where known, the zones' return heights (9,) (counts
    above the floor; None: the centre-zone test is skipped). See the module doc."""
    r = np.asarray(ranges, dtype=float)
    v = np.asarray(valid, dtype=bool) & np.isfinite(r)
    if not np.count_nonzero(v):
        return None
    used = np.sort(r[v])
    n = used.size
    median = float(used[n // 2] if n % 2 else 0.5 * (used[n // 2 - 1] + used[n // 2]))
    if median < OVERLAP_RANGE:
        return (f"{TOO_CLOSE_REASON} (median zone range {median * 1e3:.1f} mm, within the pulse's "
                f"{OVERLAP_RANGE * 1e3:.1f} mm of it)")
    if heights is not None and median < DARK_CENTRE_RANGE:
        h = np.where(np.asarray(valid, dtype=bool), np.nan_to_num(np.asarray(heights, dtype=float)), 0.0)
        top = float(h.max())
        if top > 0 and h[CENTRE] < DARK_CENTRE_FRACTION * top:
            return (f"{TOO_CLOSE_REASON} (the centre zone is dark: {h[CENTRE] / top:.1%} of the brightest zone "
                    f"at a median zone range of {median * 1e3:.1f} mm)")
    return None


def plane_overlap_reason(points: np.ndarray, valid: np.ndarray, offset: float) -> str | None:
    """:data:`TOO_CLOSE_REASON` when the plane read through a frame's zone ``points`` (9, 3; m) in ``valid`` (9,)
    lies closer to the sensor than :data:`OVERLAP_RANGE` (``offset``, m) while a zone used reads within
    :data:`SCREEN_RANGE`; else None. The first-pass test (:func:`overlap_reason`) sees the far-range mapping's
    ranges; the calibrated mapping (each zone's offset and gain, the near-range table) can still put the plane
    inside the overlap, where no reading is one: zones that all show the internal return at one bin map to ranges
    of 8-30 mm and a plane 6-7 mm away tilted 68-70 deg (an adversarial round, session 74, with the real sweep's
    and both simulated sensors' calibrations; one of them stated it to 1.6 deg). Either the plane is right and the
    surface lies in the overlap, or it is wrong: no plane either way."""
    if not (offset < OVERLAP_RANGE):  # (the usual plane: nothing more to ask)
        return None
    pts = np.asarray(points, dtype=float)
    v = np.asarray(valid, dtype=bool) & np.all(np.isfinite(pts), axis=1)  # the zones the plane was fitted through
    if not np.count_nonzero(v):
        return None
    nearest = float(np.min(np.linalg.norm(pts[v], axis=1)))
    if not nearest <= SCREEN_RANGE:
        return None
    return (f"{TOO_CLOSE_REASON} (the plane read lies {offset * 1e3:.1f} mm from the sensor, within the pulse's "
            f"{OVERLAP_RANGE * 1e3:.1f} mm of it)")


__all__ = ["TOO_CLOSE_REASON", "OVERLAP_RANGE", "DARK_CENTRE_FRACTION", "DARK_CENTRE_RANGE", "SCREEN_RANGE",
           "may_be_close", "overlap_reason", "plane_overlap_reason"]
