"""The point error of a reading-to-point mapping over frames with ground truth: the score every calibration of
:class:`~place_safe.recovery.points.PeakParams` minimises (:mod:`place_safe.calibration.points`,
:mod:`place_safe.calibration.near_range`). Metres."""
from __future__ import annotations

import numpy as np

from place_safe.evaluation.metrics import point_errors
from place_safe.recovery.points import PeakParams, fit_planes

#: m: the point error charged for a frame whose plane cannot be fitted.
FAILED_FIT_ERROR = 1.0



def true_ranges(tn: np.ndarray, td: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """m: the range (F, Z) along each zone direction ``dirs`` (Z, 3; unit) to each frame's true plane ``n . x = d``
    (normals ``tn`` (F, 3), offsets ``td`` (F,)); inf / NaN where a direction misses the plane (callers mask them,
    and silence the division's warnings where they expect it)."""
    return td[:, None] / (tn @ dirs.T)

def frame_point_errors(p: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray,
                       td: np.ndarray) -> np.ndarray:
    """Each frame's point error (m, (F,)) with mapping ``p``, readings and mask (F, 9) and true normals (F, 3)
    and offsets (F,); :data:`FAILED_FIT_ERROR` where the readings give no plane."""
    return plane_point_errors(p.points(readings), valid, tn, td)


def plane_point_errors(points: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray) -> np.ndarray:
    """The point error (m, (F,)) of the plane through each frame's zone points (F, 9, 3) with mask (F, 9) against
    its true plane (normals ``tn`` (F, 3), offsets ``td`` (F,)); :data:`FAILED_FIT_ERROR` where they give no plane."""
    n, d, _, ok = fit_planes(points, valid)
    e = np.full(len(td), FAILED_FIT_ERROR)
    if ok.any():
        e[ok] = point_errors(n[ok], d[ok], tn[ok], td[ok])
    return e


__all__ = ["FAILED_FIT_ERROR", "frame_point_errors", "plane_point_errors", "true_ranges"]
