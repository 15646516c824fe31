"""Beyond the calibrated range: how fast the far mapping's error grows past its farthest frame, read on the sweep.

Concept
-------
The peak mapping (:class:`~place_safe.recovery.points.PeakParams`) is fitted on the calibration frames' ranges: its
residual series and each zone's inverse-range terms hold over ``residual_domain``, which ends at the farthest zone
range the sweep read (``hi``). A plane farther than that is read by the mapping's straight continuation
(:meth:`~place_safe.recovery.points.PeakParams.far_extension`), whose slope is the sweep's best word but not the
truth: a calibration of the real sweep cut at 20 cm reads 21-40 cm 0.7 mm off on average (3.7 mm when the corrections
were held at their end), where nothing stated more than 0.1-0.5 mm (NEES per dof 6-84). So the error of a range
beyond ``hi`` is stated as growing with the distance past it: a standard deviation of ``far_common_rel (r - hi)`` that
the zones of a frame share (the mapping's slope, one error along every ray: mostly the plane's offset) and
``far_zone_rel (r - hi)`` of each zone's own (their gains: the tilt)
(:class:`~place_safe.recovery.estimator.Uncertainty`, :func:`~place_safe.recovery.peak.far_covariance`).

How fast, the sweep says itself: the far mapping is fitted again on the frames up to :data:`FAR_INNER` of the sweep's
farthest depth (:func:`~place_safe.calibration.points.refit_mapping`) and reads the frames beyond, as a new sweep's
mapping would read planes past its end. The two rates are those at which these planes' errors read as their stated
covariance says (the in-range one the calibration states, plus the growth): each zone's own rate from the tilt errors
(what it moves), at least :data:`FAR_ZONE_SHARE` of the shared one; the shared rate from the offset errors. What the
inner fit reads against what the planes beyond a cut sweep needed (the shared rate): the real sweep cut at 20 / 25 /
30 cm 0.66 / 0.50 / 0.53 % against 0.67 / 0.16 / 1.2 %; two simulated units and the generator 0.01-0.11 % against
0.00-0.08 %. Where the sweep is too short for that (fewer than :data:`FAR_MIN_INNER` frames within the cut or
:data:`FAR_MIN_OUTER` beyond), the stated :data:`FAR_PRIOR_REL`. Units: metres; the rates are dimensionless.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
from scipy.optimize import brentq

from place_safe.calibration.point_errors import true_ranges
from place_safe.calibration.points import refit_mapping
from place_safe.recovery.estimator import Uncertainty, tilt_offset
from place_safe.exceptions import NoPlaneError
from place_safe.recovery.peak import PeakEstimator, far_covariance
from place_safe.recovery.points import plane_through
from place_safe.sensor.frame import Frame

#: Share of the sweep's farthest depth up to which the inner fit takes frames (the rest are read past its end).
FAR_INNER = 0.65
#: Fewest frames with ground truth within the inner share / beyond it for the growth to be read on the sweep.
FAR_MIN_INNER = 8
FAR_MIN_OUTER = 3
#: Growth stated where the sweep cannot show its own (each part): the real sweep's cut calibrations read 0.5-1.2 % and
#: needed up to 1.7 % (cut at 15 cm).
FAR_PRIOR_REL = 0.02
#: The most a zone's distance past the inner fit's end may be short of it and still count, as a share of that end:
#: zones just past it divide an error by almost nothing.
FAR_MIN_PAST = 0.05
#: The zones' own rate is stated at least this share of the shared one. What the inner fit's tilts say of it is the
#: least steady reading: on the real sweep cut at 15 / 20 / 25 / 30 cm it read 1.6 / 0 / 0 / 0 % where the planes
#: beyond needed 0 / 0.27 / 0.52 / 0 % (the shared rate read 0.85 / 0.66 / 0.50 / 0.53 %, needed 1.7 / 0.67 / 0.16 /
#: 1.2 %).
FAR_ZONE_SHARE = 0.75
#: m: a sweep that ends closer than this gets a note that farther planes are read past its range (the placement's
#: survey reads from about 40 cm).
FAR_NOTE_DEPTH = 0.35
#: The rates' accepted ceiling (a rate above it is a sweep that did not fit, reported and capped).
FAR_MAX_REL = 0.2


def far_growth(frames: Sequence[Frame], params, min_range: float,
               base: Uncertainty | None = None) -> tuple[float, float, dict]:
    """(``far_common_rel``, ``far_zone_rel``, report) of the far mapping ``params``
    (:class:`~place_safe.recovery.points.PeakParams`) calibrated on ``frames`` from ``min_range`` (m) on, with the
    peak method's in-range uncertainty ``base`` (what a plane states without the growth; None: its fit's own): read on
    the sweep itself (module doc), or :data:`FAR_PRIOR_REL` for both where it cannot be."""
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= min_range]
    report: dict = {"inner_share": FAR_INNER}
    if not use:
        return FAR_PRIOR_REL, FAR_PRIOR_REL, {**report, "from": "stated (FAR_PRIOR_REL): no frame with ground truth"}
    farthest = max(f.truth.z0 for f in use)
    cut = FAR_INNER * farthest
    inner = [f for f in use if f.truth.z0 <= cut]
    outer = [f for f in use if f.truth.z0 > cut]
    report.update(cut_m=cut, frames_inner=len(inner), frames_outer=len(outer))
    if len(inner) < FAR_MIN_INNER or len(outer) < FAR_MIN_OUTER:
        return FAR_PRIOR_REL, FAR_PRIOR_REL, {**report, "from": (
            f"stated (FAR_PRIOR_REL): the sweep has {len(inner)} frames within {FAR_INNER:g} of its farthest depth "
            f"and {len(outer)} beyond ({FAR_MIN_INNER} and {FAR_MIN_OUTER} needed to read the growth on it)")}
    fit = refit_mapping(inner, params.without_near_table(), min_range)
    end = float(fit.residual_domain[1])
    report["inner_domain_end_m"] = end
    errors, stated, zone_unit, common_unit = _read_past(outer, fit, end, base or Uncertainty())
    if len(errors) < FAR_MIN_OUTER:
        return FAR_PRIOR_REL, FAR_PRIOR_REL, {**report, "from": (
            f"stated (FAR_PRIOR_REL): {len(errors)} frames past the inner fit's end read ({FAR_MIN_OUTER} needed)")}
    t = slice(0, 2)  # the zones' own part from the tilt (what it moves: a pattern the plane cannot take up, the
    zone = _rate(errors[:, t], stated[:, t, t], zone_unit[:, t, t])  # corners long and the centre short, is no tilt)
    d = slice(2, 3)  # the shared part from the offset, with the zones' own beside it
    common = _rate(errors[:, d], stated[:, d, d] + min(zone, FAR_MAX_REL) ** 2 * zone_unit[:, d, d],
                   common_unit[:, d, d])
    zone = max(zone, FAR_ZONE_SHARE * common)
    capped = common > FAR_MAX_REL or zone > FAR_MAX_REL
    common, zone = min(common, FAR_MAX_REL), min(zone, FAR_MAX_REL)
    report.update(frames_read=len(errors), common_rel=common, zone_rel=zone, capped=capped)
    report["from"] = "read on the sweep: the inner fit's planes beyond it"
    if farthest < FAR_NOTE_DEPTH:
        report["note"] = (f"the sweep ends at {farthest * 100:.1f} cm: farther planes are read past the calibrated "
                          f"range (the mapping goes on with its far slope; their stated error grows "
                          f"{common * 100:.2f} % of the distance past it, read on the sweep); sweep to 40 cm or beyond "
                          f"where the arm reads (the survey starts there) to calibrate them")
    return common, zone, report


def _rate(errors: np.ndarray, stated: np.ndarray, unit: np.ndarray) -> float:
    """The rate ``k`` (>= 0) at which the errors (F, n) read a mean squared Mahalanobis distance per component of 1
    under ``stated + k^2 unit`` (each (F, n, n)); 0 where the stated covariances already cover them, inf where not
    even :data:`FAR_MAX_REL` does."""
    def excess(k2: float) -> float:
        c = stated + k2 * unit
        return float(np.mean([e @ np.linalg.solve(m, e) for e, m in zip(errors, c)])) / errors.shape[1] - 1.0

    if not excess(0.0) > 0.0:
        return 0.0
    hi = FAR_MAX_REL ** 2
    if excess(hi) > 0.0:
        return math.inf
    return math.sqrt(brentq(excess, 0.0, hi, xtol=1e-12))


def _read_past(frames: Sequence[Frame], fit, end: float, base: Uncertainty) -> tuple[np.ndarray, ...]:
    """``frames`` read by the mapping ``fit`` (whose domain ends at ``end``, m) with ``base``: for each with three or
    more zones at least :data:`FAR_MIN_PAST` of ``end`` past it, the error of ``(n_x, n_y, d)`` (F, 3), the covariance
    ``base`` states (F, 3, 3) and the covariances a unit rate of the zones' own and of the shared growth add (each
    (F, 3, 3), :func:`~place_safe.recovery.peak.far_covariance`)."""
    est = PeakEstimator(fit, base)
    hists = np.array([np.asarray(f.hists, dtype=float) for f in frames])
    readings, valid, _ = fit.peaks(hists)
    zone_points = fit.points(np.where(valid, readings, np.nan))  # (F, 9, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        true = true_ranges(np.array([f.truth.normal for f in frames]), np.array([f.truth.offset for f in frames]),
                           fit.directions())
    far = valid & (true - end >= FAR_MIN_PAST * end)
    own, shared = Uncertainty(far_zone_rel=1.0), Uncertainty(far_common_rel=1.0)
    out = [], [], [], []
    for i in np.flatnonzero(far.sum(axis=1) >= 3):  # (far zones are valid ones)
        points = zone_points[i]
        try:
            plane, _ = plane_through(points, valid[i])
        except NoPlaneError:
            continue
        for acc, v in zip(out, (tilt_offset(plane) - tilt_offset(frames[i].truth),
                                est.covariance(points, valid[i], plane),
                                far_covariance(own, points, valid[i], plane, end),
                                far_covariance(shared, points, valid[i], plane, end))):
            acc.append(v)
    return tuple(np.array(a).reshape((-1, 3) if k == 0 else (-1, 3, 3)) for k, a in enumerate(out))


__all__ = ["far_growth", "FAR_INNER", "FAR_ZONE_SHARE", "FAR_MIN_INNER", "FAR_MIN_OUTER", "FAR_PRIOR_REL",
           "FAR_MIN_PAST", "FAR_MAX_REL", "FAR_NOTE_DEPTH"]
