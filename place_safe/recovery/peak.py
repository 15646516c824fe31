"""Histogram-peak plane recovery: the sub-bin peak of each zone gives a range, the ranges give points,
an SVD fit gives the plane (the paper's "calibrated peak finding" baseline, with per-zone offsets).

Per zone, vectorised over zones (and over frames in :func:`place_safe.sensor.histogram.find_peaks`):

1. floor = the smaller of the medians of the first :data:`EARLY_BINS` bins (before any return can
   arrive: the laser pulse leaves after bin ~11) and of the last :data:`LATE_BINS` bins (after the
   return of anything within about 1.3 m); subtracted.
2. the highest bin from :data:`SEARCH_START` on; a zone has a return when that bin is more than
   :data:`NOISE_SIGMAS` Poisson standard deviations of the floor (and :data:`MIN_NET_COUNTS`) above it.
   Within the internal return's bins it must also stand well above the internal return
   (:data:`~place_safe.sensor.histogram.INTERNAL_MAX_COUNTS`); otherwise the highest bin beyond them is
   looked at instead (a zone that sees nothing does not read a surface at zero range).
3. sub-bin position, by :attr:`PeakParams.subbin <place_safe.recovery.points.PeakParams>`:
   ``"spline"``, the maximum of a not-a-knot cubic spline (:class:`scipy.interpolate.CubicSpline`)
   through the :data:`HALF_WINDOW` bins on either side, on a grid of :data:`SUBBIN_STEPS` points per
   bin within one bin of the highest bin (one precomputed matrix: the spline is linear in the counts;
   PCHIP flattens the peak and was 3x worse on the real sweep); or ``"centroid"`` (what calibration
   writes), the centre of the return under a cos^2 window that sits on it (half-width
   ``PeakParams.subbin_half_width``, 3 bins by default; :func:`~place_safe.sensor.histogram.windowed_centroid`),
   which does not depend on where the return falls between bins as the spline's maximum does. A zone
   whose return holds two surfaces reads its maximum instead (see :func:`~place_safe.sensor.histogram.find_peaks`).
4. range, direction and point from :class:`place_safe.recovery.points.PeakParams`; the plane is
   the SVD least-squares fit of the zones with a return (3 or more needed).

A frame whose return overlaps the internal return (:func:`~place_safe.recovery.too_close.overlap_reason`: the
zones' median range within the pulse's half width, or a dark centre zone closer than 3 cm; or the calibrated plane
itself within that half width: :func:`~place_safe.recovery.too_close.plane_overlap_reason`) gives no plane
and the reason ``"too close: the return overlaps the internal return (...)"``.

``residual`` of the estimate: RMS perpendicular distance (m) of the zone points from the plane;
``covariance``: the SVD fit's (:func:`~place_safe.recovery.points.plane_covariance`); closer than the near-range
errors' end each zone's error is the calibrated near-range one instead of the fit's residual: there the zones'
errors are systematic (a pattern over the zones that mostly does not tilt the plane), which the residual of
independent zones overstates as tilt (real halves held out, 2-5 cm: NEES per dof 0.15 with the residual alone).
Those errors are sized on a level sweep's frames; on a tilted plane each zone also reads its footprint's spread of
ranges its own way (:data:`ZONE_TILT_SCATTER`, which the residual would have held), added to each zone's near-range
error (14 simulated units calibrated on a level sweep, frames tilted 0-20 deg at 2-5 cm: NEES per dof 1.2-3.0
without it, 1.0-1.2 with it). A sweep with tilted near frames widens the law by their scatter, so there it counts
twice on tilted near planes: cautious.
The calibrated errors are fitted by maximum likelihood on held-out planes
(:func:`~place_safe.calibration.uncertainty.fit_peak_uncertainty`). Then the calibrated floor and the
tilt term (:class:`~place_safe.recovery.estimator.Uncertainty`: on a tilted plane each zone's return spreads
over its footprint and the peak reads the slope short, an error a level sweep cannot show; a calibration on mostly
tilted frames has none, its floor holds that error). A fit through fewer zones than the grid states the larger of
its residual variance and the zones' scatter (:func:`partial_zone_variance`: the calibrated ``Uncertainty.zone_std``
and, on a tilted plane, :data:`ZONE_TILT_SCATTER`; three zones have no residual of their own), and carries the floor
through its own lever arms (:func:`partial_grid_floor`).
Histograms clipped (:func:`~place_safe.sensor.histogram.clipped_zones`: the 24-bit maximum, a flat top, a narrower
store's limit), or frames flagged ``saturated`` in ``extra`` /
``extra["meta"]``, give no plane: a clipped peak has no usable position. Counts above the 24-bit maximum give no
plane either, with a reason that says so (:func:`~place_safe.sensor.histogram.beyond_count_max`): the sensor cannot
report them.
"""

from __future__ import annotations

import math

import numpy as np

from place_safe.exceptions import FrameError, NoPlaneError
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame
from place_safe.recovery.estimator import COS_MAX_TILT, Estimator, PlaneEstimate, Uncertainty, check_arguments
from place_safe.recovery.points import (PeakParams, PlaneFitGeometry, known_error_covariance, plane_covariance,
                                       plane_fit_geometry, plane_through)
from place_safe.recovery.too_close import may_be_close, overlap_reason, plane_overlap_reason
from place_safe.sensor.histogram import COUNT_MAX, beyond_count_max, find_peaks
from place_safe.sensor.zones import zone_numbers

def _flagged_saturated(frame: Frame) -> bool:
    """Whether the frame's ``extra`` (or its ``meta``) says ``"saturated": true`` (a boolean true only: "no" is not)."""
    extra = frame.extra if isinstance(frame.extra, dict) else {}
    meta = extra.get("meta") if isinstance(extra.get("meta"), dict) else {}
    return extra.get("saturated") is True or meta.get("saturated") is True


class PeakEstimator(Estimator):
    """Calibrated peak finding (``peak``) or, with :meth:`naive`, physical constants (``peak-naive``)."""

    name = "peak"
    needs_histograms = True

    def __init__(self, params: PeakParams | None = None, uncertainty: Uncertainty | None = None) -> None:
        check_arguments(type(self).__name__, params=(params, PeakParams), uncertainty=(uncertainty, Uncertainty))
        self.params = params if params is not None else PeakParams.default_peak()
        self.uncertainty = uncertainty if uncertainty is not None else Uncertainty()

    @classmethod
    def naive(cls) -> "PeakEstimator":
        """Uncalibrated: published bin size, ``b`` from the forward model's offset and a bin-14
        reference peak (:meth:`PeakParams.naive_peak`), nominal zone directions, no zone offsets."""
        est = cls(PeakParams.naive_peak())
        est.name = "peak-naive"
        return est

    def _far_ranges(self, readings: np.ndarray) -> np.ndarray:
        """First-pass ranges (m, (9,)) of readings: the far-range mapping, without the near-range table (which
        extrapolates where a frame is too close; :mod:`place_safe.recovery.too_close`)."""
        p = self.params
        if not p.near_depths:
            return p.ranges(readings)
        key = (p.m, p.b, p.edge_scale, p.corner_scale, tuple(p.zone_offsets), tuple(p.zone_gains),
               tuple(p.residual_coeffs), tuple(p.residual_domain), tuple(p.phase_coeffs), tuple(p.zone_inverse))
        if getattr(self, "_far_key", None) != key:
            self._far = p.without_near_table()
            self._far_key = key
        return self._far.ranges(readings)

    def zone_points(self, frame: Frame) -> tuple[np.ndarray, np.ndarray]:
        """The zone points (9, 3; m, sensor frame) and which of them the plane fit uses (9,) of a frame whose
        histograms are valid; raises :class:`~place_safe.exceptions.NoPlaneError` (saturated, too close, fewer
        than 3 returns) or :class:`~place_safe.exceptions.FrameError` (shape) where there is no plane."""
        if _flagged_saturated(frame):
            raise NoPlaneError("frame is flagged saturated; the peaks are clipped")
        h = np.asarray(frame.hists, dtype=float)
        if h.shape != (N_ZONES, N_BINS):
            raise FrameError(f"hists has shape {h.shape}, expected ({N_ZONES}, {N_BINS})")
        if (beyond := beyond_count_max(h)) is not None:  # not clipped: counts the sensor cannot have reported
            raise NoPlaneError(beyond)
        p = self.params
        pos, valid, saturated, heights = find_peaks(h, p.pileup, p.subbin, p.subbin_half_width, heights=True)
        if np.count_nonzero(saturated):
            zones = zone_numbers(saturated)
            raise NoPlaneError(f"histogram clipped (saturated counts: a flat top or counters at their maximum) in "
                               f"zone(s) {zones}")
        if may_be_close(pos, valid, p):
            too_close = overlap_reason(self._far_ranges(pos), valid, heights)
            if too_close:
                raise NoPlaneError(too_close)
        if p.drops_weak:  # as PeakParams.peaks: the near-range rule's weak zones out
            valid = p.drop_weak(pos, valid, heights)
            pos = np.where(valid, pos, np.nan)
        if (used := np.count_nonzero(valid)) < 3:
            raise NoPlaneError(f"only {used} zone(s) show a return above the noise floor; "
                               "a plane needs 3 or more")
        return self.params.points(pos), valid

    def _estimate(self, frame: Frame) -> PlaneEstimate:
        points, valid = self.zone_points(frame)
        plane, rms = plane_through(points, valid)
        if (too_close := plane_overlap_reason(points, valid, plane.offset)) is not None:
            raise NoPlaneError(too_close)
        return PlaneEstimate(plane, residual=rms, covariance=self.covariance(points, valid, plane),
                             method_used=self.name)

    def covariance(self, points: np.ndarray, valid: np.ndarray, plane) -> np.ndarray:
        """The reported covariance (3, 3) of ``(n_x, n_y, d)`` of ``plane`` fitted through the zone ``points``
        (9, 3) in ``valid`` (9,): the fit's, where any zone used is closer than the near-range errors' end with
        each zone's error the calibrated near-range one in place of the fit's residual, and on a tilted plane the
        zones' tilt scatter (:func:`zone_tilt_variance`) added to it (module doc); through fewer
        zones than the grid, at least the zones' scatter (:func:`partial_zone_variance`) and the floor through their
        lever arms (:func:`partial_grid_floor`); plus the floor and the tilt term."""
        unc = self.uncertainty
        calibrated = unc.tilt_range_std > 0.0 or unc.zone_std > 0.0
        if near_applies(unc, points, valid):
            fit = plane_fit_geometry(points, valid, plane)
            if calibrated and not valid.all():  # zones beyond the law's end at least the zones' scatter
                fit = fit._replace(sigma2=np.float64(partial_zone_variance(unc, fit, plane)))
            # zones within the law's end: its error (sized on the sweep's frames) and a tilted plane's zone scatter
            cov = near_covariances(unc, fit, points[:, 2], zone_tilt_variance(plane))
        elif calibrated and not valid.all():  # fewer zones than the grid: at least the zones' scatter, the floor
            fit = plane_fit_geometry(points, valid, plane)  # (carried through the zones' own lever arms)
            cov = partial_zone_variance(unc, fit, plane) * fit.inverse
            if unc.tilt_range_std > 0.0:
                cov = cov + partial_grid_floor(unc.tilt_range_std, fit, plane, self.params.directions())
        else:
            cov = plane_covariance(points, valid, plane)
        out = unc.apply(cov, plane.offset, plane.normal)
        if (unc.far_common_rel > 0.0 or unc.far_zone_rel > 0.0) and (
                np.fmax.reduce(points[:, 2], initial=-np.inf) > self.params.far_screen()):
            out = out + far_covariance(unc, points, valid, plane, self.params.residual_domain[1])
        return out


def far_covariance(unc: Uncertainty, points: np.ndarray, valid: np.ndarray, plane, end: float) -> np.ndarray:
    """The covariance (3, 3) of ``(n_x, n_y, d)`` that ranges past the mapping's calibrated domain add to a plane
    through the zone ``points`` (9, 3; m) in ``valid`` (9,): each zone beyond ``end`` (m, the domain's far end) errs by
    ``unc.far_zone_rel`` times its distance past it, and by ``unc.far_common_rel`` times that along every such zone's
    ray at once (:mod:`place_safe.calibration.far_range`); zeros where no zone used lies past ``end``.
    :meth:`PeakEstimator.covariance` calls it only for frames with a zone deeper than
    :meth:`~place_safe.recovery.points.PeakParams.far_screen` (a comparison, not nine norms, on the usual frame)."""
    past = np.where(valid, np.sqrt(np.einsum("ij,ij->i", points, points)) - end, 0.0)
    past = np.where(np.isfinite(past) & (past > 0.0), past, 0.0)
    if not past.any():
        return np.zeros((3, 3))
    fit = plane_fit_geometry(points, valid, plane)._replace(sigma2=np.float64(0.0))  # the known errors alone
    own = max(unc.far_zone_rel, 1e-9) * past  # (a known error above 0 where past: the shared part needs one)
    return known_error_covariance(fit, own, replace_fit=True, common_std=unc.far_common_rel * past)


def _range_error_gain(geometry: PlaneFitGeometry) -> np.ndarray:
    """(3, 3): the covariance of ``(n_x, n_y, d)`` that a unit range error of each point a fit used, independent, gives
    its plane (:func:`~place_safe.recovery.points.known_error_covariance` of a unit error in place of the fit's)."""
    return known_error_covariance(geometry, 1.0, replace_fit=True)


#: m of each zone's range scatter about a tilted plane per m of ``z0 tan(tilt)`` (the plane's crossing of the optical
#: axis, its tilt from it): a zone's footprint on a tilted plane spans a spread of ranges, and the zones read it each
#: their own way. Measured as the RMS residual of peak's nine-zone fits on tilted frames (0-30 deg, 5-30 cm) against
#: ``sqrt(zone_std^2 + (k z0 tan)^2)``: mismatched units 11 and 21 k = 0.0044 (both; the value here), the
#: independent generator 0.0050 (its check). A fit through all nine zones has this in its own residual; one through
#: fewer states it (:func:`partial_zone_variance`), and so does one within the near law's end, where the law's errors
#: replace the residual (:func:`near_covariances`).
ZONE_TILT_SCATTER = 0.0044


def zone_tilt_variance(plane) -> float:
    """``(ZONE_TILT_SCATTER z0 tan(tilt))^2`` (m^2) of ``plane`` (tilt from the optical axis, capped at 80 deg as the
    tilt term's is, and taken as 80 deg where the normal is not finite; 0 where the offset is not)."""
    nz, d = float(plane.normal[2]), float(plane.offset)
    if not math.isfinite(d):
        return 0.0
    nz = min(max(nz, COS_MAX_TILT), 1.0) if math.isfinite(nz) else COS_MAX_TILT  # (the tilt term's cap and fallback)
    return (ZONE_TILT_SCATTER * d / nz * math.sqrt(max(1.0 - nz * nz, 0.0)) / nz) ** 2


def partial_zone_variance(unc: Uncertainty, fit: PlaneFitGeometry, plane) -> float:
    """The zones' residual variance (m^2) a fit through fewer zones than the grid states for ``plane``: the larger of
    its own (``fit.sigma2``; none with three zones) and the zones' scatter, ``unc.zone_std^2`` and
    :func:`zone_tilt_variance`. Peak's NEES per dof (session 90, docs/results.md "Fewer zones than the grid"): the
    real halves' 5-40 cm frames, three zones 2.8-6.4 -> 0.73-1.42 (four 1.9-3.7 -> 0.90-1.31); 40 planes of the
    independent generator tilted 15-30 deg (the test's), three and four zones 7-660 -> 0.25-1.2."""
    return max(float(fit.sigma2), unc.zone_std ** 2 + zone_tilt_variance(plane))


def partial_grid_floor(tilt_range_std: float, fit: PlaneFitGeometry, plane, directions: np.ndarray) -> np.ndarray:
    """What a fit through fewer zones than the 3x3 grid adds to its covariance (3, 3) before ``Uncertainty.apply``.

    The floor's tilt term ``(tilt_range_std / d)^2`` is a range error between zones read through the whole grid's
    lever arms. Read as a range error ``s`` of each zone that the whole grid, on this plane, turns into that tilt
    variance, the zones used turn it into ``s^2 G_used``; this adds the part of ``s^2 (G_used - G_grid)`` that is
    positive (its negative eigenvalues cut to 0). ``fit``: :func:`~place_safe.recovery.points.plane_fit_geometry` of
    the fit through the zones used; ``directions`` (9, 3): the zones' rays; zones whose ray does not meet
    the plane in front of the sensor (a plane steeper than the view) are left out of the grid, and with fewer than 3
    left, or numbers that are not finite, nothing is added. On the real sweep's
    frames with three zones kept (an L, or three corners) peak's NEES per dof was 12-29, the fit's own part being zero
    with three points; with this 2.7-6.3, and 1.9-3.0 with four (was 4-8); six or more zones barely move (session
    89)."""
    d = float(plane.offset)
    facing = directions @ plane.normal
    meets = facing > 1e-6
    if np.count_nonzero(meets) < 3:
        return np.zeros((3, 3))
    grid = (d / np.where(meets, facing, 1.0))[:, None] * directions  # every zone's point on the plane
    g_grid = _range_error_gain(plane_fit_geometry(grid, meets, plane))
    g_used = _range_error_gain(fit)
    s2 = (tilt_range_std / max(d, 1e-3)) ** 2 / max(0.5 * (g_grid[0, 0] + g_grid[1, 1]), 1e-30)
    diff = g_used - g_grid
    if not np.all(np.isfinite(diff)) or not math.isfinite(s2):
        return np.zeros((3, 3))
    w, v = np.linalg.eigh(diff)
    return (v * np.clip(w, 0.0, None)) @ v.T * s2


def near_applies(unc: Uncertainty, points: np.ndarray, valid: np.ndarray) -> bool:
    """Whether :meth:`PeakEstimator.covariance` of a fit through zone ``points`` (9, 3) in ``valid`` (9,) takes the
    zones' errors from ``unc``'s near-range law: a zone used is closer than the law's end."""
    return bool(unc.near_depths) and bool(points[valid, 2].min() < unc.near_depths[-1])


def near_covariances(unc: Uncertainty, geometry: PlaneFitGeometry, depths: np.ndarray,
                     extra: float = 0.0) -> np.ndarray:
    """The fit's part of :meth:`PeakEstimator.covariance` (before ``unc.apply``) where :func:`near_applies`: each
    zone's error ``unc.near_std`` at its depth in place of the fit's residual, and ``unc.near_common`` shared by the
    zones. ``geometry``: :func:`~place_safe.recovery.points.plane_fit_geometry` of one fit or of many stacked (leading
    axes), ``depths`` (..., 9) m their zones' depths; ``extra`` (m^2): a variance off the plane added to each such
    zone's own (a tilted plane's zone scatter, :func:`zone_tilt_variance`, a residual's variance as the fit's is;
    carried to the zone's ray, along which ``near_std`` is, by its cosine with the normal); returns (..., 3, 3)."""
    std, common = unc.near_stds(depths)
    if extra > 0.0:
        along = extra / np.maximum(geometry.off_plane, 1e-3) ** 2  # (a zone not used has off_plane 0: unread)
        std = np.where(std > 0.0, np.sqrt(std * std + along), std)
    return known_error_covariance(geometry, std, replace_fit=True, common_std=common)


__all__ = ["PeakEstimator", "find_peaks", "COUNT_MAX", "far_covariance", "near_applies",
           "near_covariances", "partial_grid_floor",
           "partial_zone_variance", "zone_tilt_variance", "ZONE_TILT_SCATTER"]
