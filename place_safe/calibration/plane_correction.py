"""Diff's plane correction: what its solver leaves over, as series in the estimated distance.

After the forward fit, diff reads the calibration frames and what its planes miss is fitted as Chebyshev series in
the estimated ``z0`` (or ``1 / z0``): the offset error, the two slope errors (with a gain where tilted frames
identify one) and the frames' log albedo in ``ln z0`` (a range law, where the frames are one surface). Each series'
degree is chosen by leave-one-out cross-validation and kept only for a clear out-of-sample gain
(:func:`fit_range_correction`); the result is the ``diff`` section's
:class:`~place_safe.recovery.differentiable.RangeCorrection`. Units: metres and slopes (dimensionless).
"""
from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np
from tqdm import tqdm

from place_safe.calibration.forward_fit import usable_frames
from place_safe.calibration.points import MIN_TILT_SPREAD
from place_safe.exceptions import CalibrationError
from place_safe.geometry import Plane
from place_safe.recovery.differentiable import DifferentiableEstimator, RangeCorrection, SolverOptions
from place_safe.recovery.diff_settings import range_argument
from place_safe.recovery.forward import ForwardParams, mount_rotation
from place_safe.sensor.frame import Frame


def corrected_offset_error(z_est: np.ndarray, z_true: np.ndarray) -> float:
    """Mean absolute ``z0`` error (m) left after the best series in the estimated ``z0`` that
    :func:`fit_range_correction` would choose (:func:`_best_series`), leave-one-out; fewer than 8 frames: the mean
    absolute error as is."""
    ok = np.isfinite(z_est) & np.isfinite(z_true)
    z_est, err = z_est[ok], z_true[ok] - z_est[ok]
    if len(err) < 8:
        return float(np.mean(np.abs(err))) if len(err) else math.inf
    domain = [float(z_est.min()), max(float(z_est.max()), float(z_est.min()) + 1e-9)]
    return min(float(np.mean(np.abs(err))), _best_series(z_est, err, domain, _series_degree(len(err)))[0])


def _leave_one_out(design: np.ndarray, y: np.ndarray) -> float:
    """Mean absolute leave-one-out error of the least-squares fit ``design @ c = y`` (rows are frames)."""
    n = len(y)
    errs = []
    for k in range(n):
        keep = np.arange(n) != k
        c = np.linalg.lstsq(design[keep], y[keep], rcond=None)[0]
        errs.append(abs(y[k] - design[k] @ c))
    return float(np.mean(errs))


#: the highest degree of a correction series, and frames per coefficient it needs at least
MAX_SERIES_DEGREE = 4
FRAMES_PER_DEGREE = 5


def _series_degree(n_frames: int, degree: int = MAX_SERIES_DEGREE) -> int:
    """The highest degree tried for a correction series over ``n_frames`` frames (e.g. 4 over 24 real frames)."""
    return int(min(degree, max(0, n_frames // FRAMES_PER_DEGREE)))


def _series_design(z: np.ndarray, domain, degree: int, inverse: bool, log: bool = False) -> np.ndarray:
    """Chebyshev design matrix (frames, degree + 1) in z0, its inverse or its logarithm
    (:func:`~place_safe.recovery.diff_settings.range_argument`)."""
    from numpy.polynomial import chebyshev

    return chebyshev.chebvander(range_argument(z, domain, inverse, log), degree)


def _best_series(z: np.ndarray, err: np.ndarray, domain, max_degree: int,
                 extra: np.ndarray | None = None) -> tuple[float, bool, int]:
    """The series (in ``z0`` or ``1 / z0``, degree 0..``max_degree``) with the lowest leave-one-out mean absolute
    error for ``err``; ``extra`` (a column per frame, e.g. the estimated slope) multiplies a second series of the
    same kind (a gain). Returns (error, inverse, degree)."""
    best = (math.inf, False, 0)
    for inverse in (False, True):
        for deg in range(max_degree + 1):
            design = _series_design(z, domain, deg, inverse)
            if extra is not None:
                design = np.hstack([design, design * extra[:, None]])
            if design.shape[1] >= len(err):
                continue
            loo = _leave_one_out(design, err)
            if loo < best[0]:
                best = (loo, inverse, deg)
    return best


def _albedo_series(z: np.ndarray, log_albedo: np.ndarray, domain, max_degree: int,
                   report: dict) -> list[float] | None:
    """The log-albedo series of :class:`RangeCorrection` (Chebyshev coefficients in ``ln z0``) from the frames'
    estimated ``z0`` and log albedos (NaN: none reported), or None. The frames are taken as one surface (a level
    table): the series brings each frame's log albedo to their mean. Its degree (0..``max_degree``, at most one per
    :data:`FRAMES_PER_DEGREE` frames) is chosen by leave-one-out, and it is kept only for a clear (10 %) gain out of
    sample over no correction, so a sweep whose albedos scatter without a trend over distance (several surfaces)
    gets none. In ``ln z0`` because a range law is a power of the range: on the real halves the held-out albedo CV
    came out 1.9 / 1.4 % in ``ln z0`` (degree 3-4) against 2.4-3.8 / 1.3-3.1 % in ``1 / z0`` (degree 2-4) and
    3.0-7.8 / 3.6-9.6 % in ``z0`` (docs/results.md). ``report`` gets the figures."""
    ok = np.isfinite(log_albedo)
    report["albedo_frames"] = int(ok.sum())
    if ok.sum() < 8:
        report["albedo_why_not"] = "fewer than 8 frames with an albedo"
        return None
    zs, err = z[ok], float(np.mean(log_albedo[ok])) - log_albedo[ok]
    before = float(np.mean(np.abs(err)))
    after, deg = min((_leave_one_out(_series_design(zs, domain, d, False, True), err), d)
                     for d in range(min(max_degree, _series_degree(len(zs))) + 1))
    report.update(albedo_mean_abs_before=before, albedo_mean_abs_leave_one_out=after, albedo_degree=deg)
    if not after < 0.9 * before:
        report["albedo_why_not"] = "no clear (10 %) gain out of sample: no trend over distance"
        return None
    coef = [float(c) for c in np.linalg.lstsq(_series_design(zs, domain, deg, False, True), err, rcond=None)[0]]
    if RangeCorrection.series_problem("albedo", coef) is not None:
        report["albedo_rejected"] = "albedo outside its physical range"
        return None
    return coef


def fit_range_correction(frames: Sequence[Frame], forward: ForwardParams, peak=None,
                         degree: int = MAX_SERIES_DEGREE, min_distance: float = 0.04, max_distance: float = 1.0,
                         progress: bool = True, options: SolverOptions | None = None) -> tuple[dict, dict]:
    """Fit the diff estimator's plane correction; returns (``diff`` section, report).

    Runs the fast differentiable estimator with ``forward`` on the frames with ground truth and fits
    Chebyshev series against the estimated ``z0`` to what it leaves over: ``z0_true - z0_est`` and, in the
    optical frame, the slope errors ``a_true - a_est`` and ``b_true - b_est``, for the slopes also with a gain
    (a series times the estimated slope, so a tilt read a fixed fraction too large is corrected; tilted
    calibration frames identify it, a level sweep does not). Each series is chosen by leave-one-out
    cross-validation among degrees 0..``degree`` (at most one per :data:`FRAMES_PER_DEGREE` frames) in ``z0``
    or in ``1 / z0`` (:func:`_best_series`), and kept only if it lowers the mean absolute error by at least 10 %
    (the gain: 10 % below the offset alone). On the real sweep's halves the slopes' series in ``1 / z0``
    follow diff's tilt error of 2-3 deg at 5 cm that a cubic in ``z0`` missed (docs/results.md). The frames' albedos
    give the log-albedo series (:func:`_albedo_series`: a sweep of one surface). ``options``: the diff solver's (as
    :func:`model_error.select_model_error`).
    """
    skipped: dict[str, int] = {}
    data = usable_frames(frames, min_distance, max_distance, skipped)
    est = DifferentiableEstimator(forward, peak, options=options)
    to_optical = mount_rotation(forward.mount_tilt).numpy().T
    rows = []  # (z0_est, dz0, da, db, a_est, b_est, log albedo or NaN)
    bar = tqdm(total=len(data), desc="plane correction", unit="frame",
               disable=None if progress else True, file=sys.stderr)
    for i in range(0, len(data), 16):
        chunk = data[i:i + 16]
        for e, f in zip(est.estimate_many(chunk), chunk):
            if e.ok:
                a_e, b_e, z_e = Plane(to_optical @ e.plane.normal, e.plane.offset).slopes
                a_t, b_t, z_t = Plane(to_optical @ f.truth.normal, f.truth.offset).slopes
                rows.append((z_e, z_t - z_e, a_t - a_e, b_t - b_e, a_e, b_e,
                             math.log(e.albedo) if e.albedo is not None and e.albedo > 0 else math.nan))
        bar.update(len(chunk))
    bar.close()
    if len(rows) < 8:
        return ({"range_correction": RangeCorrection().to_dict()},
                {"frames": len(rows), "frames_skipped": skipped, "kept": [], "why": "fewer than 8 recovered frames"})
    table = np.array(rows)
    z = table[:, 0]
    max_deg = _series_degree(len(z), degree)
    lo, hi = float(z.min()), float(z.max())
    domain = [lo, max(hi, lo + 1e-6)]
    n = len(z)
    series, inverse = {}, []
    report = {"frames": n, "frames_skipped": skipped, "max_degree": max_deg, "kept": []}
    for col, name, gain, unit in ((1, "coeffs", None, 1e3), (2, "slope_a", "gain_a", 1.0),
                                  (3, "slope_b", "gain_b", 1.0)):
        err = table[:, col]
        best = float(np.mean(np.abs(err)))
        report[f"{name}_mean_abs_before"] = best * unit
        # an offset in z0, then for the slopes also a gain (the error proportional to the slope itself). The
        # gain needs true slopes that differ between frames: over a level sweep the error is minus the
        # estimated slope itself, and a gain of -1 would "correct" every plane to the sweep's slope
        candidates = [((name,), None)]
        if gain is not None:
            slope = table[:, 4] if col == 2 else table[:, 5]
            true_slope = slope + err
            # what the frames can say about a gain (identifiability): the std of a constant gain beside a
            # constant offset (the Fisher information of the true slopes' spread) with the errors' own
            # scatter. Over a level sweep the true slopes do not differ and there is none (None): a level sweep
            # does not determine how a tilt is scaled
            spread = float(np.sqrt(np.sum((true_slope - true_slope.mean()) ** 2)))
            report[f"{gain}_std"] = float(np.std(err, ddof=min(2, n - 1)) / spread) if spread > 1e-9 else None
            if np.ptp(np.arctan(true_slope)) >= MIN_TILT_SPREAD:
                candidates.append(((name, gain), slope))
            else:
                report[f"{gain}_why_not"] = "true slopes differ by less than the tilt spread a gain needs"
        for names, extra in candidates:
            after, inv, deg = _best_series(z, err, domain, max_deg, extra)
            key = "+".join(names)
            report[f"{key}_mean_abs_leave_one_out"] = after * unit
            report[f"{key}_series"] = {"variable": "1/z0" if inv else "z0", "degree": deg}
            if after < 0.9 * best:  # kept only for a clear (10 %) out-of-sample gain over the simpler model
                design = _series_design(z, domain, deg, inv)
                if extra is not None:
                    design = np.hstack([design, design * extra[:, None]])
                coef = np.linalg.lstsq(design, err, rcond=None)[0]
                parts = {k: [float(c) for c in coef[i * (deg + 1):(i + 1) * (deg + 1)]]
                         for i, k in enumerate(names)}
                bad = [k for k, v in parts.items() if RangeCorrection.series_problem(k, v) is not None]
                if bad:  # outside its physical range: not a correction
                    report[f"{key}_rejected"] = f"{bad[0]} outside its physical range"
                    continue
                best = after
                series.update(parts)
                inverse = [k for k in inverse if k not in names] + (list(names) if inv else [])
    alb = _albedo_series(z, table[:, 6], domain, max_deg, report)
    if alb is not None:
        series["albedo"] = alb
    report["kept"] = sorted(series)
    report["inverse"] = sorted(inverse)
    try:
        corr = RangeCorrection(series.get("coeffs", []), domain, series.get("slope_a", []),
                               series.get("slope_b", []), series.get("gain_a", []), series.get("gain_b", []),
                               series.get("albedo", []), sorted(k for k in inverse if k in series))
    except CalibrationError as exc:  # a "correction" outside its physical range is not one: keep none
        corr = RangeCorrection()
        report.update(kept=[], why=f"fitted correction rejected: {exc}")
    return {"range_correction": corr.to_dict()}, report
