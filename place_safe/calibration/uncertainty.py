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

A level sweep cannot show what a tilt does to ``peak``: each zone's return spreads over its footprint and
the peak method reads the slope short (on mismatched units 0.06-0.08 rad per unit ``tan(tilt)``, 1.4 deg mean
at 0-30 deg, where its level-calibrated covariance said 0.03 deg). Its covariance gets the stated tilt term
``Uncertainty.tilt_rel =`` :data:`PEAK_TILT_REL` per tilt component.

For ``diff`` the fallback to peak is a safety net chosen on held-out frames (:func:`select_fallback`): a
frame falls back when its residual chi-square is above ``chi2_limit``, when the two estimates contradict each
other (:data:`CONSISTENCY_LIMIT`), or when diff's tilt variance is above ``prefer_ratio`` times peak's (peak
reads this slope better). The calibration frames are split in :data:`CV_FOLDS` folds interleaved in distance;
for each, diff's floor is fitted on the others and every candidate pair (chi2_limit, prefer_ratio) returns a
plane for each held-out frame. The pair whose returned planes score best over all held-out frames wins: the
worse of the mean angular and mean point error, each per frame in units of peak's median error and capped at
10 (so frames on which both methods fail do not decide). There is no "always fall back" candidate: where
diff's own covariance says it reads the slope better, a level sweep cannot tell otherwise, and the
per-frame comparison already returns peak where peak reads better. Ties go to the larger chi-square limit
and the ratio nearest 1. Units: rad, m.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import replace

import numpy as np

from place_safe.evaluation.metrics import angular_errors, nees, point_errors  # noqa: F401 (nees: re-exported)
from place_safe.recovery.estimator import PlaneEstimate, Uncertainty, tilt_offset
from place_safe.recovery.too_close import TOO_CLOSE_REASON
from place_safe.sensor.frame import Frame
from place_safe.calibration.near_range import held_out_tables, near_range_std
from place_safe.calibration.points import MIN_CALIBRATION_RANGE
from place_safe.recovery.differentiable import NEAR_FALLBACK_RANGE, DifferentiableEstimator
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
    """The floors of :class:`Uncertainty` for estimates whose covariances hold no floor yet (maximum likelihood;
    ``base``'s tilt term counts as known)."""
    base = base or Uncertainty()
    rows = [(tilt_offset(e.plane) - tilt_offset(t), np.asarray(e.covariance, dtype=float) + base.tilt_floor(e.plane.normal, e.plane.offset),
             e.plane.offset) for e, t in zip(estimates, truths) if e.ok and e.covariance is not None and t is not None]
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


#: Tilt term of peak's covariance (:attr:`~place_safe.recovery.estimator.Uncertainty.tilt_rel`): each tilt
#: component's std per unit tan(tilt). Measured per component (RMS over frames tilted 3-30 deg, 5-30 cm):
#: mismatched units A and B 0.047 and 0.048; the unit A's own calibrated forward model, rendered tilted, 0.046;
#: the independent generator 0.023. A level sweep shows none of it, so it is stated, not fitted.
PEAK_TILT_REL = 0.05

#: Folds of the cross-validation that chooses diff's fallback limits (:func:`select_fallback`).
CV_FOLDS = 3

#: Candidate ratios of diff's to peak's tilt variance under which diff keeps its plane.
PREFER_RATIOS = (0.25, 0.5, 1.0, 2.0, 4.0)


def chi2_candidates(chi2: np.ndarray) -> list[float]:
    """Candidate chi-square limits from the calibration frames' diff chi-squares (``inf``: diff failed): their
    median, 90th percentile, largest, and twice the largest (a frame the model explains twice as badly as any
    calibration frame is not one it was calibrated for). No finite chi-square: ``[inf]`` (nothing to go by)."""
    c = np.asarray(chi2, dtype=float)
    c = c[np.isfinite(c)]
    if c.size == 0:
        return [math.inf]
    return sorted({float(np.median(c)), float(np.percentile(c, 90)), float(c.max()), 2.0 * float(c.max())})


def select_fallback(chi2: np.ndarray, consistent: np.ndarray, var_ratio: np.ndarray, diff_errors: np.ndarray,
                    peak_errors: np.ndarray, chi2_limits: Sequence[float],
                    ratios: Sequence[float] = PREFER_RATIOS) -> tuple[float, float, list[dict]]:
    """The (chi2_limit, prefer_ratio) whose returned planes score best on held-out frames.

    Per frame (F,): ``chi2`` diff's chi-square per bin (``inf``: failed), ``consistent`` whether diff agrees
    with peak, ``var_ratio`` diff's tilt variance over peak's (NaN: no comparison, diff kept), all as seen on
    the frame held out; ``diff_errors``, ``peak_errors`` (F, M): errors on M metrics in comparable units.
    A frame returns diff's plane when ``chi2 <= chi2_limit``, it is consistent and ``var_ratio <=
    prefer_ratio``; the score is the worse metric's mean error of the planes returned. Ties: the larger limit,
    then the ratio nearest 1. Returns the pair and every candidate's score.
    """
    chi2 = np.asarray(chi2, dtype=float)
    vr = np.asarray(var_ratio, dtype=float)
    table = []
    for lim in chi2_limits:
        for r in ratios:
            use = (chi2 <= lim) & np.asarray(consistent, dtype=bool) & ~(vr > r)
            sel = np.where(use[:, None], diff_errors, peak_errors)
            score = float(np.max(np.mean(sel, axis=0))) if len(chi2) else 0.0
            table.append({"chi2_limit": float(lim), "prefer_ratio": float(r), "score": score,
                          "frames_using_diff": int(use.sum())})
    if not all(math.isfinite(t["score"]) for t in table):  # errors that cannot be compared: the stated defaults
        return float(max(chi2_limits)), 1.0, table
    best = min(t["score"] for t in table)
    tied = [t for t in table if t["score"] <= best * (1 + 1e-9) + 1e-12]
    pick = max(tied, key=lambda t: (t["chi2_limit"], -abs(math.log(t["prefer_ratio"]))))
    return pick["chi2_limit"], pick["prefer_ratio"], table


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
    cross-validated), ``too_close``, how many of them the peak method reads as too close
    (:mod:`place_safe.recovery.too_close`: no plane, no part in the mean), and ``nees_per_dof_closer_held_out``,
    the same mean with each frame read by a table fitted without it (:func:`_held_out_near`).

    A factor on the near-range errors chosen so that held-out mean is 1 was tried and is not applied: each
    held-out frame lies on a knot that lost its own data, so it reads worse than a new frame between knots
    with data on both sides. On level-sweep calibrations of two simulated mismatched units (5 mm-40 cm) the
    factor (1.1-1.5) took the 2-5 cm NEES per dof of held-out level frames from 0.55 / 0.86 to 0.38 / 0.51; on the
    real halves it took 5-9 cm below 0.5."""

    lo = MIN_CALIBRATION_RANGE if min_range is None else float(min_range)
    depths, stds, near = near_range_std(frames, peak_params)
    base = Uncertainty(near_depths=depths, near_range_std=stds, tilt_rel=PEAK_TILT_REL)
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
        report["near_range"]["nees_per_dof_closer"] = _mean_nees(ests, [f.truth for f in closer])
        report["near_range"]["too_close"] = sum(1 for e in ests if (e.reason or "").startswith(TOO_CLOSE_REASON))
        held = _held_out_near(frames, closer, peak_params)
        ests = [PeakEstimator(p, unc).estimate(f) for f, p in held]
        report["near_range"]["nees_per_dof_closer_held_out"] = _mean_nees(ests, [f.truth for f in closer])
    return unc, report


def _mean_nees(estimates: Sequence[PlaneEstimate], truths: Sequence) -> float | None:
    """Mean NEES per dof of the estimates with a plane and covariance (None: none)."""
    v = nees(estimates, truths)
    v = v[np.isfinite(v)]
    return float(np.mean(v)) if v.size else None


def _held_out_near(frames: Sequence[Frame], closer: Sequence[Frame], peak_params) -> list:
    """(frame, peak parameters) for each frame of ``closer``: with the near-range table's zone errors fitted
    again without that frame (:func:`~place_safe.calibration.near_range.held_out_tables`: same knots, so the frame
    sits between knots as a new frame does), so the frame's plane is held out from the table that reads it.
    Without a table (or where the refit is unusable) ``peak_params`` as they are."""

    tables = held_out_tables(frames, peak_params) if peak_params.near_depths else {}
    return [(f, tables.get(id(f), peak_params)) for f in closer]


def fit_diff_uncertainty(frames: Sequence[Frame], forward, peak_params, correction=None,
                         peak_uncertainty: Uncertainty | None = None, options=None) -> tuple[Uncertainty, dict]:
    """The diff method's floor and fallback limits (chi-square, consistency, preference) from frames with ground
    truth, for the solver ``options`` (:class:`~place_safe.recovery.differentiable.SolverOptions`; default: the
    solver's defaults): they depend on the bins the solver fits. The limits are chosen on held-out frames
    (module doc); the report gives the held-out figures (``angular_deg``, ``point_mm``: diff's own plane, peak's
    and the one returned; ``frames_using_diff``) and every candidate's score."""

    # closer frames always get peak's plane (NEAR_FALLBACK_RANGE): they take no part in choosing the limits
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= NEAR_FALLBACK_RANGE]
    truths = [f.truth for f in use]
    peak_unc = peak_uncertainty if peak_uncertainty is not None else Uncertainty()
    est = DifferentiableEstimator(forward, peak_params, correction=correction, peak_uncertainty=peak_unc,
                                  options=options)  # no floor, no fallback: diff's own plane and fit covariance
    diff = est.estimate_many(use)
    peak = [est.init.estimate(f) for f in use]
    own = [e.ok and e.method_used == est.name and e.residual is not None for e in diff]

    def errs(e: PlaneEstimate, t) -> tuple[float, float]:
        if not e.ok:
            return math.inf, math.inf
        return (float(angular_errors(e.plane.normal, t.normal)[0]),
                float(point_errors(e.plane.normal, e.plane.offset, t.normal, t.offset)[0]))

    e_diff = np.array([errs(e, t) if ok else (math.inf, math.inf) for e, t, ok in zip(diff, truths, own)]).reshape(-1, 2)
    e_peak = np.array([errs(e, t) for e, t in zip(peak, truths)]).reshape(-1, 2)
    # each error in units of peak's median error, capped at 10, so a few hopeless frames (both methods
    # far off) do not decide; the score is the worse of the two metrics' means
    finite = np.where(np.isfinite(e_peak), e_peak, np.nan)  # peak's median over the frames it read (all NaN: 1)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a column without a finite error
        unit = np.maximum(np.nan_to_num(np.nanmedian(finite, axis=0), nan=1.0), 1e-12)
    n_diff, n_peak = np.minimum(e_diff / unit, 10.0), np.minimum(e_peak / unit, 10.0)
    chi2 = np.array([e.residual ** 2 if ok else math.inf for e, ok in zip(diff, own)])
    test = Uncertainty(consistency_limit=CONSISTENCY_LIMIT)

    def held_out(floor: Uncertainty, i: int) -> tuple[bool, float]:
        """Whether frame i's diff estimate (with ``floor``) agrees with peak's, and its tilt variance over peak's."""
        if not own[i] or diff[i].covariance is None:
            return True, math.nan
        e = replace(diff[i], covariance=floor.apply(diff[i].covariance, diff[i].plane.offset, diff[i].plane.normal))
        mine, theirs = e.tilt_std(), peak[i].tilt_std()
        ratio = (mine / theirs) ** 2 if mine is not None and theirs else math.nan
        return test.consistent(e, peak[i]), ratio

    def floor_from(rows: np.ndarray) -> Uncertainty:
        return fit_floor([diff[i] for i in rows if own[i]], [truths[i] for i in rows if own[i]])[0]

    n = len(use)
    folds = min(CV_FOLDS, n // 2)
    consistent, ratio = np.ones(n, dtype=bool), np.full(n, math.nan)
    fold = np.empty(n, dtype=int)
    fold[np.argsort([t.z0 for t in truths], kind="stable")] = np.arange(n) % max(folds, 1)
    for k in range(folds):  # each fold's limits tested with the floor fitted on the other folds
        floor = floor_from(np.flatnonzero(fold != k))
        for i in np.flatnonzero(fold == k):
            consistent[i], ratio[i] = held_out(floor, int(i))
    candidates = chi2_candidates(chi2)
    if folds >= 2:
        limit, prefer, table = select_fallback(chi2, consistent, ratio, n_diff, n_peak, candidates)
    else:  # too few frames to hold any out: the most permissive finite limit, equal variances
        limit, prefer, table = max(candidates), 1.0, []
    under = [i for i in range(n) if own[i] and chi2[i] <= limit]
    unc, rep = fit_floor([diff[i] for i in under], [truths[i] for i in under],
                         Uncertainty(chi2_limit=limit, consistency_limit=CONSISTENCY_LIMIT, prefer_ratio=prefer))
    use_diff = (chi2 <= limit) & consistent & ~(ratio > prefer)
    sel = np.where(use_diff[:, None], e_diff, e_peak)

    def mean_finite(a: np.ndarray, scale: float) -> float:
        return float(np.mean(a[np.isfinite(a)])) * scale if np.any(np.isfinite(a)) else math.nan

    rep.update({"chi2_limit": None if math.isinf(limit) else limit, "prefer_ratio": prefer, "folds": folds,
                "held_out": "frames_using_diff, angular_deg and point_mm: each frame with the floor of the other folds",
                "frames_using_diff": int(np.sum(use_diff)), "frames_using_peak": int(np.sum(~use_diff)),
                "frames_inconsistent_with_peak": int(np.sum(~consistent)),
                "frames_peak_reads_better": int(np.sum(ratio > prefer)),
                "angular_deg": {k: mean_finite(v[:, 0], 180 / math.pi) for k, v in
                                (("diff", e_diff), ("peak", e_peak), ("selected", sel))},
                "point_mm": {k: mean_finite(v[:, 1], 1e3) for k, v in (("diff", e_diff), ("peak", e_peak), ("selected", sel))},
                "candidates": table})
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


__all__ = ["update_calibration", "nees", "fit_floor", "fit_peak_uncertainty", "fit_diff_uncertainty", "select_fallback",
           "chi2_candidates", "CONSISTENCY_LIMIT", "PEAK_TILT_REL", "CV_FOLDS", "PREFER_RATIOS"]
