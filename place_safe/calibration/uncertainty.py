"""Calibrating how far to trust a method: its model-error floor and, for ``diff``, when to fall back to peak.

Concept
-------
A method's own covariance (its fit linearised at the solution, scaled by the residual; see
:mod:`place_safe.recovery.estimator`) describes noise. What the method's model gets wrong is not noise:
it is measured here on frames with ground truth and added as a floor
(:class:`~place_safe.recovery.estimator.Uncertainty`: a constant and a distance-dependent variance for
the tilt components and for the offset), chosen by maximum likelihood of the frames' errors under the
Gaussian with the estimate's covariance plus the floor; then one ``scale`` of the covariance makes the
mean normalised estimation error squared (NEES, per degree of freedom; about 1 when the covariances are
honest) 1 on these frames. NEES is reported before and after.

For ``peak`` closer than the near-range table's end (9 cm) the zones' range errors grow by orders of
magnitude (the real sweep: 0.1 mm at 8 cm, 2 mm at 2 cm, 4-6 mm at 1 cm) and the zones' lever arm
shrinks with the distance: no floor of the far-range form describes both. There each zone's error in the
plane fit's covariance is at least the zones' cross-validated range error at that distance
(:meth:`~place_safe.recovery.estimator.Uncertainty.near_std`,
:func:`~place_safe.calibration.near_range.near_range_std`,
:func:`~place_safe.recovery.points.plane_covariance`), and the floor and scale are fitted on the frames
beyond it. Held out on the real sweep's halves the 1-5 cm mean NEES per dof went from 42 / 8.7 to 16 / 4.4
and the 5-40 cm one from 1.28 / 1.07 to 1.34 / 0.98. The 1.25 cm frame stays 7 sigma off: its zones' errors
are correlated (a distortion that looks like a tilt), which independent zone errors do not describe.

For ``diff``, a frame whose diff and peak estimates contradict each other (:data:`CONSISTENCY_LIMIT`)
falls back to the peak estimate; so does a frame whose residual is above the chi-square limit
(:func:`select_chi2_limit`): among 0 (always fall back), infinity and the frames' own residuals that
admit at least :data:`MIN_DIFF_FRAMES` frames, the one whose selection has the lowest worse-of-two
score: the means of the angular and of the point error, each per frame in units of peak's median error
and capped at 10 (so frames on which both methods fail do not decide). Ties go to the larger limit (use
diff as often as it does not hurt). Units: rad, m.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from place_safe.evaluation.metrics import angular_errors, nees, point_errors  # noqa: F401 (nees: re-exported)
from place_safe.recovery.estimator import PlaneEstimate, Uncertainty, tilt_offset
from place_safe.sensor.frame import Frame
from place_safe.calibration.near_range import near_range_std
from place_safe.calibration.points import MIN_CALIBRATION_RANGE
from place_safe.recovery.differentiable import DifferentiableEstimator
from place_safe.recovery.peak import PeakEstimator


def _nll(errors: np.ndarray, covs: np.ndarray, extra: np.ndarray) -> float:
    """Mean negative log-likelihood of errors (F, k) under covariances covs (F, k, k) + extra (F, k, k)."""
    c = covs + extra
    sign, logdet = np.linalg.slogdet(c)
    if np.any(sign <= 0):
        return math.inf
    quad = np.einsum("fi,fi->f", errors, np.linalg.solve(c, errors[..., None])[..., 0])
    return float(np.mean(0.5 * (quad + logdet)))


def _fit_two(errors: np.ndarray, covs: np.ndarray, basis: tuple[np.ndarray, np.ndarray]) -> tuple[float, float]:
    """Maximum-likelihood variances (v0, v1) >= 0 of ``v0 * basis[0] + v1 * basis[1]`` (each (F,) scaling I)."""
    from scipy.optimize import minimize

    k = errors.shape[1]
    eye = np.eye(k)
    scale = np.array([max(float(np.mean(errors ** 2) / np.mean(b)), 1e-20) for b in basis])

    def f(logv: np.ndarray) -> float:
        v = np.exp(logv) * scale
        extra = (v[0] * basis[0] + v[1] * basis[1])[:, None, None] * eye
        return _nll(errors, covs, extra)

    best = None
    for start in ((0.0, -6.0), (-6.0, 0.0), (-1.0, -1.0)):
        res = minimize(f, np.array(start), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-6, "maxiter": 400})
        if best is None or res.fun < best.fun:
            best = res
    v = np.exp(best.x) * scale
    v[v < 1e-6 * scale] = 0.0  # a term the data do not want
    return float(v[0]), float(v[1])


def fit_floor(estimates: Sequence[PlaneEstimate], truths: Sequence, base: Uncertainty | None = None) -> tuple[Uncertainty, dict]:
    """The floors of :class:`Uncertainty` for estimates whose covariances hold no floor yet (maximum likelihood)."""
    base = base or Uncertainty()
    rows = [(tilt_offset(e.plane) - tilt_offset(t), e.covariance, e.plane.offset) for e, t in zip(estimates, truths)
            if e.ok and e.covariance is not None and t is not None]
    if len(rows) < 3:
        return base, {"frames": len(rows), "why": "fewer than 3 estimates with a covariance"}
    err = np.array([r[0] for r in rows])
    cov = np.array([r[1] for r in rows])
    d = np.maximum(np.array([r[2] for r in rows]), 1e-3)
    one = np.ones(len(d))
    t0, t1 = _fit_two(err[:, :2], cov[:, :2, :2], (one, 1.0 / d ** 2))
    o0, o1 = _fit_two(err[:, 2:], cov[:, 2:, 2:], (one, d ** 2))
    unc = replace(base, tilt_std=math.sqrt(t0), tilt_range_std=math.sqrt(t1), offset_std=math.sqrt(o0),
                  offset_rel=math.sqrt(o1))
    before = float(np.mean([e @ np.linalg.solve(c, e) for e, c in zip(err, cov)]) / 3.0)
    ml = float(np.mean([e @ np.linalg.solve(c + unc.floor(dd), e) for e, c, dd in zip(err, cov, d)]) / 3.0)
    unc = replace(unc, scale=float(np.clip(ml, 0.1, 10.0)))  # mean NEES per dof 1 on these frames
    after = float(np.mean([e @ np.linalg.solve(unc.apply(c, dd), e) for e, c, dd in zip(err, cov, d)]) / 3.0)
    return unc, {"frames": len(rows), "tilt_std_deg": math.degrees(unc.tilt_std), "scale": unc.scale,
                 "nees_per_dof_maximum_likelihood": ml,
                 "tilt_range_std_mm": unc.tilt_range_std * 1e3, "offset_std_mm": unc.offset_std * 1e3,
                 "offset_rel": unc.offset_rel, "nees_per_dof_before": before, "nees_per_dof_after": after}


#: Squared Mahalanobis distance between the diff and peak estimates of (n_x, n_y, d) above which diff falls
#: back to peak: the 99.9 % point of chi-square with 3 degrees of freedom (honest covariances: 1 frame in 1000).
CONSISTENCY_LIMIT = 16.27


#: Diff is used only under a chi-square limit that at least this many calibration frames pass; when no such
#: limit beats peak alone, the limit is 0 and diff always falls back to peak. A limit chosen because one frame in 27 was
#: better by chance (the real sweep's halves: score 0.03 % better) admits held-out frames near it just as
#: much by chance (there: one frame at 0.69 deg against peak's 0.27).
MIN_DIFF_FRAMES = 3


def select_chi2_limit(chi2: np.ndarray, diff_errors: np.ndarray, peak_errors: np.ndarray) -> float:
    """The chi-square limit above which diff falls back to peak, from calibration frames.

    chi2: (F,) each frame's diff residual chi-square per bin (``inf``: diff failed). diff_errors,
    peak_errors: (F, M) each method's errors on M metrics, in comparable units. Each candidate limit is
    scored by the worse metric's mean error when frames under it use diff and the rest peak; the largest
    limit with the best score wins. Candidates: 0 (diff always falls back), infinity, and the frames'
    chi-squares under which at least :data:`MIN_DIFF_FRAMES` frames lie (fewer cannot tell a better model
    from luck). No frames: 0.
    """
    chi2 = np.asarray(chi2, dtype=float)
    if chi2.size == 0:
        return 0.0
    admitted = [float(c) for c in np.unique(chi2[np.isfinite(chi2) & (chi2 > 0)])
                if np.sum(chi2 <= c) >= MIN_DIFF_FRAMES]
    candidates = [0.0] + admitted + ([math.inf] if chi2.size >= MIN_DIFF_FRAMES else [])
    scores = []
    for lim in candidates:
        use_diff = (chi2 <= lim)[:, None]
        scores.append(float(np.max(np.mean(np.where(use_diff, diff_errors, peak_errors), axis=0))))
    if not all(math.isfinite(sc) for sc in scores):  # errors that cannot be compared: diff always falls back
        return 0.0
    best = min(scores)
    return max(c for c, sc in zip(candidates, scores) if sc <= best * (1 + 1e-9))


def fit_peak_uncertainty(frames: Sequence[Frame], peak_params, min_range: float | None = None) -> tuple[Uncertainty, dict]:
    """The peak method's floor from frames with ground truth at ``min_range`` (m, axis distance) or farther:
    the range its mapping was calibrated on (default
    :data:`~place_safe.calibration.points.MIN_CALIBRATION_RANGE`).

    Why not closer frames: the mapping is not fitted there and its errors are of another kind (the real
    sweep at 0.5-2 cm: 10-60 deg). With them in, the floor's two terms and the scale could describe neither
    regime: held out at 5-40 cm the NEES per dof was 0.3-0.4 (covariances 3x too large), at 1-5 cm 5-8.
    Those frames get the zones' near-range errors instead (module doc); where there are some, the floor and
    scale are fitted on the frames beyond their last depth. The report's ``near_range`` holds the errors per
    depth and the mean NEES per dof of the closer frames with them (in sample for the floor; the errors are
    cross-validated)."""
    lo = MIN_CALIBRATION_RANGE if min_range is None else float(min_range)
    depths, stds, near = near_range_std(frames, peak_params)
    base = Uncertainty(near_depths=depths, near_range_std=stds)
    far = max(lo, depths[-1]) if depths else lo  # the floor and scale from the frames the near term leaves alone
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= far]
    ests = [PeakEstimator(peak_params).estimate(f) for f in use]
    unc, report = fit_floor(ests, [f.truth for f in use], base)
    report["min_range_m"] = far
    closer = [f for f in frames if f.truth is not None and f.truth.z0 < far]
    report["frames_closer"] = len(closer)
    report["near_range"] = near
    if closer and depths:
        ests = [PeakEstimator(peak_params, unc).estimate(f) for f in closer]
        report["near_range"]["nees_per_dof_closer"] = float(np.nanmean(nees(ests, [f.truth for f in closer])))
    return unc, report


def fit_diff_uncertainty(frames: Sequence[Frame], forward, peak_params, correction=None,
                         peak_uncertainty: Uncertainty | None = None, options=None) -> tuple[Uncertainty, dict]:
    """The diff method's chi-square limit (fallback to peak) and floor from frames with ground truth, for
    the solver ``options`` (:class:`~place_safe.recovery.differentiable.SolverOptions`; default: the
    solver's defaults): both depend on the bins the solver fits."""
    use = [f for f in frames if f.truth is not None]
    truths = [f.truth for f in use]
    est = DifferentiableEstimator(forward, peak_params, correction=correction, peak_uncertainty=peak_uncertainty,
                                  options=options)
    diff = est.estimate_many(use)
    peak = [est.init.estimate(f) for f in use]

    def errs(e: PlaneEstimate, t) -> tuple[float, float]:
        if not e.ok:
            return math.inf, math.inf
        return (float(angular_errors(e.plane.normal, t.normal)[0]),
                float(point_errors(e.plane.normal, e.plane.offset, t.normal, t.offset)[0]))

    e_diff = np.array([errs(e, t) for e, t in zip(diff, truths)])  # (F, 2): angular, point
    e_peak = np.array([errs(e, t) for e, t in zip(peak, truths)])
    # each error in units of peak's median error, capped at 10, so a few hopeless frames (both methods
    # far off) do not decide; the score is the worse of the two metrics' means
    finite = np.where(np.isfinite(e_peak), e_peak, np.nan)  # peak's median over the frames it read (all NaN: 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column without a finite error
        unit = np.maximum(np.nan_to_num(np.nanmedian(finite, axis=0), nan=1.0), 1e-12)
    n_diff, n_peak = np.minimum(e_diff / unit, 10.0), np.minimum(e_peak / unit, 10.0)
    chi2 = np.array([e.residual ** 2 if e.ok and e.residual is not None else math.inf for e in diff])
    limit = select_chi2_limit(chi2, n_diff, n_peak)
    by_diff = [e for e, c in zip(diff, chi2) if c <= limit]
    unc, rep = fit_floor(by_diff, [t for t, c in zip(truths, chi2) if c <= limit],
                         Uncertainty(chi2_limit=limit, consistency_limit=CONSISTENCY_LIMIT))
    # with the fitted floors: the frames whose diff estimate the peak estimate contradicts (they fall back too)
    final = [replace(e, covariance=unc.apply(e.covariance, e.plane.offset)) if e.ok and e.covariance is not None
             else e for e in diff]
    inconsistent = np.array([not unc.consistent(e, p) for e, p in zip(final, peak)])
    sel = np.where(((chi2 <= limit) & ~inconsistent)[:, None], e_diff, e_peak)

    def mean_finite(a: np.ndarray, scale: float) -> float:
        return float(np.mean(a[np.isfinite(a)])) * scale

    use_diff = (chi2 <= limit) & ~inconsistent
    rep.update({"chi2_limit": None if math.isinf(limit) else limit, "frames_using_diff": int(np.sum(use_diff)),
                "frames_using_peak": int(np.sum(~use_diff)), "frames_inconsistent_with_peak": int(inconsistent.sum()),
                "angular_deg": {k: mean_finite(v[:, 0], 180 / math.pi) for k, v in
                                (("diff", e_diff), ("peak", e_peak), ("selected", sel))},
                "point_mm": {k: mean_finite(v[:, 1], 1e3) for k, v in (("diff", e_diff), ("peak", e_peak), ("selected", sel))}})
    return unc, rep


def update_calibration(cal, frames: Sequence[Frame], method: str) -> dict:
    """Fit the ``uncertainty`` entries a method needs (``peak``; ``diff``: peak's too) into ``cal``; returns the report."""
    section = dict(cal.sections.get("uncertainty", {}))
    report = {}
    if method in ("peak", "diff"):
        unc, report["peak"] = fit_peak_uncertainty(frames, cal.peak())
        section["peak"] = unc.to_dict()
    if method == "diff":
        unc, report["diff"] = fit_diff_uncertainty(frames, cal.forward(), cal.peak(), cal.diff(),
                                                   Uncertainty.from_dict(section["peak"]), cal.diff_options())
        section["diff"] = unc.to_dict()
    cal.sections["uncertainty"] = section
    return report


__all__ = ["update_calibration", "nees", "fit_floor", "fit_peak_uncertainty", "fit_diff_uncertainty", "select_chi2_limit",
           "MIN_DIFF_FRAMES", "CONSISTENCY_LIMIT"]
