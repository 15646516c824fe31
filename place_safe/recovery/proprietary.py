"""Plane recovery from the TMF8820's own per-zone distances ("proprietary distances").

The sensor reports a first-object distance per zone (:attr:`Frame.distances`, m; 0 = no object) and
a confidence. The reading of a zone is that distance in millimetres, mapped to a range by the same
:class:`place_safe.calibration.points.PeakParams` as the peak method (``r = (mm - b - off_z) / (m g_z)``
plus the optional smooth correction); ``proprietary-naive`` uses m = 1000 mm/m, b = 0 and nominal
directions, i.e. the distances as reported along the zone centres. Points at those ranges along the
zone directions are fitted by SVD. Zones with distance 0 (or confidence 0) are dropped; 3 or more
are needed. A frame whose histograms are corrupt (NaN, infinite or negative counts, counts beyond the 24-bit
counters: what ``peak`` and ``diff`` refuse) gives no plane either, though the method does not read them
(:func:`histogram_problem`). A frame whose zones' median range (mapped) lies within the laser pulse's half width, or closer than 3 cm
with no object in the centre zone, gives no plane,
reason ``"too close: the return overlaps the internal return (...)"`` (:mod:`place_safe.recovery.too_close`).
``residual``: RMS perpendicular distance (m) of the points from the plane.

``covariance`` (of ``(n_x, n_y, d)``, see :mod:`place_safe.recovery.estimator`): the SVD fit's
(:func:`~place_safe.recovery.points.plane_covariance`) with each zone's range error at least the reading's
resolution, a 1 mm step: :data:`READING_STEP_STD` mm over the zone's calibrated slope ``m g_z`` (mm per m). A
calibrated mapping states what it leaves of the zones' range errors on its calibration frames
(``PeakParams.zone_residual``, ``common_residual``; :func:`~place_safe.calibration.points.fit_proprietary`): each
zone then errs by the larger of the resolution and the own part, in place of the fit's residual, and the zones
share the common part besides (one error along every ray at once: it moves the offset more than the tilt).
Without them (``proprietary-naive``, older calibration files) each zone errs by the larger of the resolution and
the fit's residual. Held out on the real sweep (calibrated on one half, 5-40 cm of the other): mean NEES per dof
1.02 (even -> odd) and 1.56 (odd -> even) with the stated residuals; 2.2 / 1.8 with one per-zone residual and no
shared part, 7.1 / 5.9 with the resolution and the fit's residual alone (the offset's z-scores up to 7: the
zones' errors are largely shared).
"""

from __future__ import annotations

import math

import numpy as np

from place_safe.recovery.points import MM_PER_M, PeakParams, plane_covariance, plane_through
from place_safe.exceptions import FrameError, NoPlaneError
from place_safe.sensor.frame import (MAX_CONFIDENCE, MAX_SENSOR_DISTANCE, MIN_SENSOR_DISTANCE, N_ZONES, SENSOR_RANGE,
                                     Frame, real_array)
from place_safe.recovery.estimator import Estimator, PlaneEstimate, check_arguments
from place_safe.sensor.histogram import beyond_count_max
from place_safe.recovery.too_close import may_be_close, overlap_reason, plane_overlap_reason

#: Reading units (mm): standard deviation of rounding to the sensor's whole millimetres (a uniform step of 1 mm).
READING_STEP_STD = 1.0 / math.sqrt(12.0)
#: Smallest ratio of a stated covariance's least to its largest eigenvalue: below it the linearisation is degenerate
#: (a plane within about 0.01 deg of the optical axis, 3 zones 1 mm and 1-2 m away, gives 1e-14 and a negative
#: eigenvalue after rounding) and the frame gives no plane. The real sweep at 3-40 cm: 2e-5 to 4e-3.
MIN_EIGEN_RATIO = 1e-12


def on_sensor_readings(frame: Frame) -> tuple[np.ndarray, np.ndarray]:
    """(distances (9,) in m, zones that report an object (9,)) of ``frame``'s on-sensor result: a zone reports one
    where its distance is not 0, not beyond the sensor's range (:data:`~place_safe.sensor.frame.SENSOR_RANGE`, 5 m: a
    distance the 16-bit field holds beyond it, up to 65535 mm, is no target the sensor measured; at full confidence it
    read as a plane 64 m away) and its confidence (if given) not 0. FrameError for a frame without them, or with
    values the sensor cannot report (NaN, negative, beyond 16-bit millimetres, a confidence beyond a byte): the
    method refuses such a frame, and its calibration leaves it out."""
    if frame.distances is None:
        raise FrameError(frame.distances_error
                         or "frame has no on-sensor distances; the proprietary method needs 'distances'")
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
        if conf.shape != (N_ZONES,):
            raise FrameError(f"confs_1 has shape {conf.shape}, expected ({N_ZONES},)")
        if not np.all((conf >= 0) & (conf <= MAX_CONFIDENCE)):  # NaN fails too
            raise FrameError(f"confs_1 outside what the sensor reports (0-{MAX_CONFIDENCE}, 0 = no object)")
        valid &= conf > 0
    return dist, valid & (dist <= SENSOR_RANGE)


def beyond_range(frame: Frame) -> int:
    """How many zones of ``frame`` report a distance beyond the sensor's range (:data:`SENSOR_RANGE`) at a confidence
    above 0 (left out by :func:`on_sensor_readings`), for the reason of a frame left with too few zones."""
    dist = np.asarray(frame.distances, dtype=float)
    conf = np.ones(N_ZONES) if frame.confidences is None else np.asarray(frame.confidences, dtype=float)
    return int(np.sum((dist > SENSOR_RANGE) & (conf > 0)))


def histogram_problem(frame: Frame) -> str | None:
    """Why ``frame``'s histograms make it a corrupt frame (None: they do not): what ``peak`` and ``diff`` refuse a frame
    for before reading it (:meth:`Frame.validate`: not real numbers, the wrong shape, NaN, infinite or negative counts;
    a count above the 24-bit counters', :func:`~place_safe.sensor.histogram.beyond_count_max`), a missing reference
    histogram excepted (this method reads none; a clipped return is a measurement, not corruption). The on-sensor
    distances come in the same measurement: a frame whose histograms hold NaN counts gave its plane from them (session
    83), one that ``peak`` and ``diff`` refuse."""
    try:
        frame.validate(need_reference=False)
    except FrameError as exc:
        return f"{exc}: a frame whose histograms are corrupt is not used, its on-sensor distances neither"
    if (beyond := beyond_count_max(frame.hists)) is not None:  # (a reference's: Frame.validate)
        return f"{beyond}: a frame whose histograms are corrupt is not used, its on-sensor distances neither"
    return None


class ProprietaryEstimator(Estimator):
    """On-sensor distances, calibrated (``proprietary``) or as reported (:meth:`naive`)."""

    name = "proprietary"
    needs_histograms = False

    def __init__(self, params: PeakParams | None = None) -> None:
        check_arguments(type(self).__name__, params=(params, PeakParams))
        self.params = params if params is not None else PeakParams.default_proprietary()

    @classmethod
    def naive(cls) -> "ProprietaryEstimator":
        est = cls(PeakParams.default_proprietary())
        est.name = "proprietary-naive"
        return est

    def _estimate(self, frame: Frame) -> PlaneEstimate:
        if (corrupt := histogram_problem(frame)) is not None:
            raise FrameError(corrupt)
        dist, valid = on_sensor_readings(frame)
        if valid.sum() < 3:
            far = beyond_range(frame)
            raise NoPlaneError(f"only {int(valid.sum())} zone(s) report an object" + (
                f" ({far} more report one beyond the sensor's {SENSOR_RANGE:g} m range: no target it measures)"
                if far else "") + "; a plane needs 3 or more")
        # a zone without an object counts as dark (the on-sensor result holds no return heights)
        if may_be_close(dist * MM_PER_M, valid, self.params):
            too_close = overlap_reason(self.params.ranges(np.where(valid, dist * MM_PER_M, np.nan)), valid,
                                       valid.astype(float))
            if too_close:
                raise NoPlaneError(too_close)
        points = self.params.points(dist * MM_PER_M)
        plane, rms = plane_through(points, valid)
        cov = self.covariance(points, valid, plane)  # (first: a plane along the optical axis says so)
        if (too_close := plane_overlap_reason(points, valid, plane.offset)) is not None:
            raise NoPlaneError(too_close)
        return PlaneEstimate(plane, residual=rms, covariance=cov)

    def covariance(self, points: np.ndarray, valid: np.ndarray, plane) -> np.ndarray:
        """The stated covariance (3, 3, symmetric) of ``(n_x, n_y, d)`` of ``plane`` fitted through the zone
        ``points`` (9, 3; m) in ``valid`` (9,) (module doc)."""
        p = self.params
        step = READING_STEP_STD / (p.m * np.asarray(p.zone_gains))  # m: the resolution along each zone's ray
        if p.zone_residual > 0.0 or p.common_residual > 0.0:
            cov = plane_covariance(points, valid, plane, np.maximum(step, p.zone_residual), replace_fit=True,
                                   common_std=p.common_residual)
        else:
            cov = plane_covariance(points, valid, plane, step)
        cov = 0.5 * (cov + cov.T)
        eig = np.linalg.eigvalsh(cov) if np.all(np.isfinite(cov)) else np.full(3, np.nan)
        if not eig[0] > MIN_EIGEN_RATIO * eig[-1]:
            raise NoPlaneError("the zone points do not determine the plane's uncertainty (its covariance is not "
                               "positive definite: the plane nearly contains the optical axis, or the points a line)")
        return cov


__all__ = ["ProprietaryEstimator", "on_sensor_readings", "histogram_problem"]
