"""Plane recovery from the TMF8820's own per-zone distances ("proprietary distances").

The sensor reports a first-object distance per zone (:attr:`Frame.distances`, m; 0 = no object) and
a confidence. The reading of a zone is that distance in millimetres, mapped to a range by the same
:class:`place_safe.calibration.points.PeakParams` as the peak method (``r = (mm - b - off_z) / (m g_z)``
plus the optional smooth correction); ``proprietary-naive`` uses m = 1000 mm/m, b = 0 and nominal
directions, i.e. the distances as reported along the zone centres. Points at those ranges along the
zone directions are fitted by SVD. Zones with distance 0 (or confidence 0) are dropped; 3 or more
are needed. A frame whose zones' median range (mapped) lies within the laser pulse's half width, or closer than 3 cm
with no object in the centre zone, gives no plane,
reason ``"too close: the return overlaps the internal return (...)"`` (:mod:`place_safe.recovery.too_close`).
``residual``: RMS perpendicular distance (m) of the points from the plane.
"""

from __future__ import annotations

import numpy as np

from place_safe.recovery.points import MM_PER_M, PeakParams, plane_from_points
from place_safe.exceptions import FrameError, NoPlaneError
from place_safe.sensor.frame import MAX_SENSOR_DISTANCE, MIN_SENSOR_DISTANCE, N_ZONES, Frame, real_array
from place_safe.recovery.estimator import Estimator, PlaneEstimate
from place_safe.recovery.too_close import may_be_close, overlap_reason


class ProprietaryEstimator(Estimator):
    """On-sensor distances, calibrated (``proprietary``) or as reported (:meth:`naive`)."""

    name = "proprietary"
    needs_histograms = False

    def __init__(self, params: PeakParams | None = None) -> None:
        self.params = params if params is not None else PeakParams.default_proprietary()

    @classmethod
    def naive(cls) -> "ProprietaryEstimator":
        est = cls(PeakParams.default_proprietary())
        est.name = "proprietary-naive"
        return est

    def _estimate(self, frame: Frame) -> PlaneEstimate:
        if frame.distances is None:
            raise FrameError("frame has no on-sensor distances; the proprietary method needs 'distances'")
        dist = real_array(frame.distances, "distances").astype(float)
        if dist.shape != (N_ZONES,):
            raise FrameError(f"distances has shape {dist.shape}, expected ({N_ZONES},)")
        if np.any(np.isnan(dist)) or np.any(np.isinf(dist)):
            raise FrameError("distances contains NaN or infinite values")
        if np.any(dist < 0):
            raise FrameError("distances contains negative values; expected metres >= 0 (0 = no object)")
        valid = dist > 0
        if np.any(valid & ((dist < MIN_SENSOR_DISTANCE) | (dist > MAX_SENSOR_DISTANCE))):
            raise FrameError(f"distances outside what the sensor reports (0 for no object, else "
                             f"{MIN_SENSOR_DISTANCE * 1e3:g}-{MAX_SENSOR_DISTANCE * 1e3:g} mm)")
        if frame.confidences is not None:
            conf = real_array(frame.confidences, "confs_1").astype(float)
            if conf.shape == (N_ZONES,):
                valid &= np.nan_to_num(conf, nan=0.0) > 0
        if valid.sum() < 3:
            raise NoPlaneError(f"only {int(valid.sum())} zone(s) report an object; a plane needs 3 or more")
        # a zone without an object counts as dark (the on-sensor result holds no return heights)
        if may_be_close(dist * MM_PER_M, valid, self.params):
            too_close = overlap_reason(self.params.ranges(np.where(valid, dist * MM_PER_M, np.nan)), valid,
                                       valid.astype(float))
            if too_close:
                raise NoPlaneError(too_close)
        plane, rms = plane_from_points(self.params, dist * MM_PER_M, valid)
        return PlaneEstimate(plane, residual=rms)


__all__ = ["ProprietaryEstimator"]
