"""The TMF8820 in 3x3 mode: the zone layout (zone rectangles, kinds and centre directions).

Conventions
-----------
* Zones are numbered 1..9 in the sensor's reporting order; arrays index them 0..8.
* Each zone is a rectangle on the tangent plane ``z = 1`` of the sensor frame (origin at the
  sensor, +z the optical axis). Values from ``docs/tmf8820.md`` (SPAD pitch 16.8 x 38.8 um behind
  a 400 um lens; 5x2 pixels at the sides, 4x2 in the middle column).
* A histogram has 128 bins of counts; channel 0 of a measurement is the reference histogram (the
  laser pulse seen inside the package), channels 1..9 the zones.
* On-sensor distances are in millimetres in the files and metres in :class:`Frame`.
"""

from __future__ import annotations

import numpy as np


N_ZONES = 9
N_BINS = 128

#: Zone rectangles on z = 1: rows are zones 1..9, columns (x_min, x_max, y_min, y_max).
ZONE_RECTS = np.array(
    [
        [+0.0840, +0.2940, +0.0970, +0.2910],
        [+0.0840, +0.2940, -0.0970, +0.0970],
        [+0.0840, +0.2940, -0.2910, -0.0970],
        [-0.0840, +0.0840, +0.0970, +0.2910],
        [-0.0840, +0.0840, -0.0970, +0.0970],
        [-0.0840, +0.0840, -0.2910, -0.0970],
        [-0.2940, -0.0840, +0.0970, +0.2910],
        [-0.2940, -0.0840, -0.0970, +0.0970],
        [-0.2940, -0.0840, -0.2910, -0.0970],
    ]
)

#: Kind of each zone: 0 centre, 1 edge (2, 4, 6, 8), 2 corner (1, 3, 7, 9).
ZONE_KIND = np.array([2, 1, 2, 1, 0, 1, 2, 1, 2])
CENTRE, EDGE, CORNER = 0, 1, 2


def zone_numbers(zones: np.ndarray) -> str:
    """The zones of a (9,) mask, or of an array of indices 0..8, as the sensor numbers them: "1, 2, 3"."""
    z = np.asarray(zones)
    return ", ".join(str(int(i) + 1) for i in (np.flatnonzero(z) if z.dtype == bool else z))


def zone_centre_directions() -> np.ndarray:
    """Unit direction (9, 3) through the middle of each zone rectangle on z = 1."""
    cx = ZONE_RECTS[:, :2].mean(axis=1)
    cy = ZONE_RECTS[:, 2:].mean(axis=1)
    d = np.stack([cx, cy, np.ones(N_ZONES)], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


ZONE_DIRECTIONS = zone_centre_directions()

__all__ = ["N_ZONES", "N_BINS", "ZONE_RECTS", "ZONE_KIND", "CENTRE", "EDGE", "CORNER", "ZONE_DIRECTIONS", "zone_centre_directions"]
