"""Calibration of the reading-to-point mapping (:class:`place_safe.recovery.points.PeakParams`).

:func:`fit_peak` and :func:`fit_proprietary` minimise the paper's point error over frames with ground
truth: Nelder-Mead over ``(m, b, s_e, s_c)`` as in the paper (``paper=True``), then the full model by
linear least squares (see :func:`fit_points`). The paper did not calibrate per-zone offsets; on the
real sweep zones differ by up to one bin (about 12 mm) at the same distance.
"""
from __future__ import annotations

import math
import sys
from typing import Any, Sequence

import numpy as np
from numpy.polynomial import chebyshev as cheb
from scipy.optimize import minimize

from place_safe.calibration.near_range import fit_near_range
from place_safe.calibration.point_errors import frame_point_errors, true_ranges
from place_safe.evaluation.metrics import angular_errors, linear_errors, point_errors
from place_safe.exceptions import CalibrationError, FrameError
from place_safe.recovery.proprietary import histogram_problem, on_sensor_readings
from place_safe.recovery.points import MAX_ZONE_RESIDUAL, MIN_DOMAIN_WIDTH, MM_PER_M, PeakParams, fit_planes
from place_safe.sensor.frame import N_ZONES, Frame
from place_safe.sensor.histogram import CENTROID_HALF_WIDTH, find_peaks

#: Spread of ground-truth tilts (rad) from which the edge/corner scales are identifiable and fitted.
MIN_TILT_SPREAD = math.radians(5.0)
#: Frames whose true axis distance is below this are left out of calibration: the peak stops
#: moving with range there (pulse and target overlap), see the shared sweep below 25 mm.
MIN_CALIBRATION_RANGE = 0.03  # m


def tilt_angles(normals: np.ndarray) -> np.ndarray:
    """rad: each unit plane normal's (F, 3) angle from the optical axis (:attr:`~place_safe.geometry.Plane.theta`;
    ``n_z > 0`` by the plane convention)."""
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    return np.arccos(np.clip(n[:, 2], -1.0, 1.0))


def level_frames(tilts: np.ndarray) -> bool:
    """Whether calibration frames of these tilts (rad, :func:`tilt_angles`) are level: none, or their tilts spread
    less than :data:`MIN_TILT_SPREAD`, so the frames cannot show what a tilt does."""
    return tilts.size == 0 or float(np.ptp(tilts)) < MIN_TILT_SPREAD

# ---------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------
def _truth_arrays(frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray]:
    n = np.array([f.truth.normal for f in frames])
    d = np.array([f.truth.offset for f in frames])
    return n, d


def _errors(params: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray) -> dict:
    n, d, _, ok = fit_planes(params.points(readings), valid)
    out = {"failures": int((~ok).sum())}
    if ok.any():
        out["point"] = point_errors(n[ok], d[ok], tn[ok], td[ok])
        out["angular"] = angular_errors(n[ok], tn[ok])
        out["linear"] = linear_errors(n[ok], d[ok], tn[ok], td[ok])
    return out


def _summary(errs: dict) -> dict:
    out: dict[str, Any] = {"failures": errs["failures"]}
    for key, scale, unit in (("point", 1e3, "mm"), ("linear", 1e3, "mm"), ("angular", 180 / np.pi, "deg")):
        e = errs.get(key)
        if e is None or len(e) == 0:
            continue
        out[f"{key}_mean_{unit}"] = float(np.mean(e) * scale)
        out[f"{key}_median_{unit}"] = float(np.median(e) * scale)
    return out


def fit_linear(edge_scale: float, corner_scale: float, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray,
               td: np.ndarray, degree: int = 2, harmonics: int = 2, fit_offsets: bool = True,
               fit_gains: bool = True, inverse: int = 0) -> PeakParams | None:
    """For fixed direction scales, the least-squares m, b, zone offsets, residual correction and phase
    correction: ``reading = m r + b + off_z + c(r) + s(reading)`` at the true ranges ``r`` along the
    scaled directions (reading units); with ``inverse`` K > 0 also each zone's terms in the inverse range,
    ``+ sum_{k <= K} a_kz (lo / r)^k`` (:meth:`PeakParams.inverse_correction`; ``lo`` the nearest range fitted).
    Returns None when the data do not determine them."""
    dirs = PeakParams(1.0, 0.0, edge_scale, corner_scale).directions()
    with np.errstate(divide="ignore", invalid="ignore"):
        r = true_ranges(tn, td, dirs)
    use = valid & np.isfinite(readings) & np.isfinite(r) & (r > 0)
    if use.sum() < 3:
        return None
    rows, zones = np.nonzero(use)
    y = readings[use]
    rr = r[use]
    lo, hi = float(rr.min()), float(rr.max())
    if hi - lo < MIN_DOMAIN_WIDTH:
        degree, hi = 0, lo + MIN_DOMAIN_WIDTH
    onehot = np.zeros((len(y), N_ZONES))
    onehot[np.arange(len(y)), zones] = 1.0
    seen = onehot.sum(0) > 0
    n_slope = N_ZONES if fit_gains else 1
    if fit_gains and not seen.all():
        return None  # a zone never seen cannot get its own gain
    cols = [rr[:, None] * onehot] if fit_gains else [rr[:, None]]
    if fit_offsets:
        if not seen.all():
            return None
        cols.append(onehot)
    else:
        cols.append(np.ones((len(y), 1)))
    if degree > 1:  # the constant and linear Chebyshev terms are b and m
        u = (2.0 * rr - (lo + hi)) / (hi - lo)
        cols.append(cheb.chebvander(u, degree)[:, 2:])
    if inverse > 0:
        if not seen.all():
            return None  # a zone never seen cannot get its own terms
        q = lo / rr
        cols.extend(onehot * q[:, None] ** k for k in range(1, inverse + 1))
    for k in range(harmonics):
        w = 2.0 * np.pi * (k + 1) * y
        cols.append(np.stack([np.sin(w), np.cos(w)], axis=1))
    A = np.concatenate(cols, axis=1)
    if np.linalg.matrix_rank(A) < A.shape[1]:
        return None
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    slopes = coef[:n_slope]
    m = float(slopes.mean())
    if not (m > 0 and np.all(slopes > 0)):
        return None
    gains = slopes / m if fit_gains else np.ones(N_ZONES)
    k = n_slope
    if fit_offsets:
        off = coef[k:k + N_ZONES]
        k += N_ZONES
        b = float(off.mean())
        offsets = off - b
    else:
        b = float(coef[k])
        k += 1
        offsets = np.zeros(N_ZONES)
    res_coeffs: list[float] = []
    if degree > 1:
        res_coeffs = [0.0, 0.0] + [float(v) for v in coef[k:k + degree - 1]]
        k += degree - 1
    zone_inverse = [float(v) for v in coef[k:k + inverse * N_ZONES]] if inverse > 0 else []
    k += len(zone_inverse)
    phase = [float(v) for v in coef[k:k + 2 * harmonics]]
    try:
        return PeakParams(m, b, edge_scale, corner_scale, list(offsets), res_coeffs, [lo, hi], phase, list(gains),
                          zone_inverse=zone_inverse)
    except CalibrationError:
        return None


def _mean_point_error(p: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray,
                      td: np.ndarray) -> float:
    return float(np.mean(frame_point_errors(p, readings, valid, tn, td)))


def _fit_scales(start: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray,
                bar: Any, max_iter: int, degree: int, harmonics: int, fit_offsets: bool,
                fit_gains: bool, inverse: int = 0) -> PeakParams:
    """Nelder-Mead over (s_e, s_c) on the mean point error, the rest solved linearly inside."""

    def make(x: np.ndarray) -> PeakParams | None:
        if not (0 < x[0] < 3 and 0 < x[1] < 3):
            return None
        return fit_linear(float(x[0]), float(x[1]), readings, valid, tn, td, degree, harmonics, fit_offsets,
                          fit_gains, inverse)

    def cost(x: np.ndarray) -> float:
        p = make(x)
        return 1e3 if p is None else _mean_point_error(p, readings, valid, tn, td)

    x0 = np.array([start.edge_scale, start.corner_scale])
    res = minimize(cost, x0, method="Nelder-Mead",
                   options={"maxiter": max_iter, "xatol": 1e-6, "fatol": 1e-10,
                            "initial_simplex": np.array([x0, x0 + [0.05, 0], x0 + [0, 0.05]])},
                   callback=(lambda *_: bar.update(1)) if bar is not None else None)
    p = make(res.x)
    return p if p is not None else start


def _nelder_mead(params: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray,
                 bar: Any, max_iter: int) -> PeakParams:
    """Nelder-Mead over (m, b, s_e, s_c) on the mean point error, other fields fixed."""
    fixed = dict(zone_offsets=params.zone_offsets, residual_coeffs=params.residual_coeffs,
                 residual_domain=params.residual_domain, phase_coeffs=params.phase_coeffs)
    x0 = np.array([params.m, params.b, params.edge_scale, params.corner_scale])
    scale = np.array([params.m, 1.0, 1.0, 1.0])  # optimise m relative to its start

    def make(x: np.ndarray) -> PeakParams | None:
        m, b, se, sc = x * scale
        if not (m > 0 and 0 < se < 3 and 0 < sc < 3):
            return None
        return PeakParams(float(m), float(b), float(se), float(sc), **fixed)

    def cost(x: np.ndarray) -> float:
        p = make(x)
        return 1e3 if p is None else _mean_point_error(p, readings, valid, tn, td)

    res = minimize(cost, x0 / scale, method="Nelder-Mead",
                   options={"maxiter": max_iter, "xatol": 1e-7, "fatol": 1e-9,
                            "initial_simplex": _simplex(x0 / scale)},
                   callback=(lambda *_: bar.update(1)) if bar is not None else None)
    p = make(res.x)
    return p if p is not None else params


def _simplex(x0: np.ndarray) -> np.ndarray:
    steps = np.array([0.02, 0.3, 0.03, 0.03])  # relative m, bins, scale, scale
    return np.vstack([x0] + [x0 + np.eye(len(x0))[i] * steps[i] for i in range(len(x0))])


#: Powers of the inverse range each zone's own term may have (:meth:`PeakParams.inverse_correction`), chosen by
#: :func:`select_inverse`: 0 (none), 1 or 2. On the real sweep (halves: calibrated on one, planes of the other at
#: 5-40 cm) the two powers took peak from 0.156 to 0.081 deg (odd -> even) and from 0.126 to 0.100 (even -> odd);
#: on simulated units' tilted frames they changed nothing (docs/results.md, "Each zone's own term in the inverse
#: range").
INVERSE_DEGREES = (0, 1, 2)
#: Folds of :func:`select_inverse` (frames sorted by range, every FOLDS-th in one fold) and the relative fall of the
#: held-out range error a higher power must bring to be chosen over a lower one.
INVERSE_FOLDS = 5
INVERSE_MIN_GAIN = 0.02
#: m: :func:`select_inverse` scores the held-out frames from this depth on. Closer, the zones' errors are the
#: near-range table's to follow (:mod:`~place_safe.calibration.near_range`) and the return merges with the
#: internal return: scored there too, the real odd half chose one power (its 3-5 cm frames decide), which left its
#: 5-40 cm tilt where it was (0.156 -> 0.146 deg held out) where two powers read 0.080.
INVERSE_SCORE_FROM = 0.05


def select_inverse(edge_scale: float, corner_scale: float, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray,
                   td: np.ndarray, degree: int, harmonics: int, fit_offsets: bool, fit_gains: bool,
                   candidates: Sequence[int] = INVERSE_DEGREES) -> tuple[int, dict]:
    """The power of each zone's own term in the inverse range (:func:`fit_linear`'s ``inverse``) among
    ``candidates`` by cross-validation over frames: each of :data:`INVERSE_FOLDS` folds (frames sorted by depth,
    interleaved) held out in turn, the mapping fitted on the rest, the RMS of the range errors (m) of the held-out
    frames' zones at depth :data:`INVERSE_SCORE_FROM` or more pooled. A higher power is chosen only where it lowers
    that RMS by :data:`INVERSE_MIN_GAIN` or more from the one chosen below it, and only where every fold could be
    fitted with it (a fold whose terms the mapping may not have, :meth:`PeakParams.inverse_problem`, scores None).
    Returns (power, {"rms_mm": {power: RMS in mm, or None where a fold could not be fitted}, "folds": n}); with
    fewer than 2 * INVERSE_FOLDS frames, the lowest candidate."""
    candidates = sorted(set(int(k) for k in candidates)) or [0]
    n = len(readings)
    if len(candidates) == 1 or n < 2 * INVERSE_FOLDS:
        return candidates[0], {"rms_mm": {}, "folds": 0}
    depth = td / np.maximum(tn[:, 2], 1e-9)
    order = np.argsort(depth)
    fold = np.empty(n, dtype=int)
    fold[order] = np.arange(n) % INVERSE_FOLDS
    rms: dict[int, float | None] = {}
    for k in candidates:
        sq, count = 0.0, 0
        for f in range(INVERSE_FOLDS):
            train, test = fold != f, (fold == f) & (depth >= INVERSE_SCORE_FROM)
            p = fit_linear(edge_scale, corner_scale, readings[train], valid[train], tn[train], td[train], degree,
                           harmonics, fit_offsets, fit_gains, k)
            if p is None:
                sq = math.nan
                break
            with np.errstate(divide="ignore", invalid="ignore"):
                err = p.ranges(np.where(valid[test], readings[test], np.nan)) - true_ranges(tn[test], td[test],
                                                                                             p.directions())
            use = valid[test] & np.isfinite(err)
            sq += float(np.sum(err[use] ** 2))
            count += int(use.sum())
        rms[k] = math.sqrt(sq / count) if count and math.isfinite(sq) else None
    chosen = candidates[0]
    for k in candidates[1:]:
        if rms[k] is not None and (rms[chosen] is None or rms[k] <= (1.0 - INVERSE_MIN_GAIN) * rms[chosen]):
            chosen = k
    return chosen, {"rms_mm": {str(k): (None if v is None else v * 1e3) for k, v in rms.items()},
                    "folds": INVERSE_FOLDS}


def fit_points(readings: np.ndarray, valid: np.ndarray, frames: Sequence[Frame], init: PeakParams,
               progress: bool = True, residual_degree: int = 3, harmonics: int = 2, fit_offsets: bool = True,
               fit_gains: bool = True, paper: bool = False, max_iter: int = 400,
               label: str = "calibrate", inverse_degrees: Sequence[int] = (0,)) -> tuple[PeakParams, dict]:
    """Calibrate a reading-to-point mapping on readings (F, 9) with mask (F, 9) and the frames' truth.

    First the paper's procedure: Nelder-Mead over (m, b, s_e, s_c) on the mean point error from
    ``init`` (its result is returned when ``paper`` is True). Otherwise the full model is fitted
    from ``init``'s scales: m, b, per-zone offsets and gains, the residual correction (Chebyshev
    ``residual_degree``) and the sub-bin phase correction (``harmonics`` sine/cosine pairs) by linear
    least squares (:func:`fit_linear`); the scales s_e, s_c are refined by Nelder-Mead on the point
    error only when the ground-truth planes are tilted by :data:`MIN_TILT_SPREAD` or more between
    frames. Otherwise (e.g. a sweep towards a level table) the scales are not identifiable: they
    would only trade the fit's lever arm and are kept at ``init``'s values. Each zone's own terms in the inverse
    range (:func:`fit_linear`'s ``inverse``) take the power :func:`select_inverse` chooses among
    ``inverse_degrees`` (the default: none).
    """
    from tqdm import tqdm

    tn, td = _truth_arrays(frames)
    before = _summary(_errors(init, readings, valid, tn, td))
    tilted = not level_frames(tilt_angles(tn))
    bar = tqdm(total=max_iter * (2 if tilted and not paper else 1), desc=label, unit="it",
               disable=None if progress else True,
               leave=False, file=sys.stderr)
    try:
        base = PeakParams(init.m, init.b, init.edge_scale, init.corner_scale)
        params = _nelder_mead(base, readings, valid, tn, td, bar, max_iter)
        paper_style = _summary(_errors(params, readings, valid, tn, td))
        inverse, inverse_report = 0, None
        if not paper:
            if fit_offsets and fit_gains:
                inverse, inverse_report = select_inverse(init.edge_scale, init.corner_scale, readings, valid, tn, td,
                                                         residual_degree, harmonics, fit_offsets, fit_gains,
                                                         inverse_degrees)
            full = fit_linear(init.edge_scale, init.corner_scale, readings, valid, tn, td, residual_degree, harmonics,
                              fit_offsets, fit_gains, inverse)
            while full is None and inverse > 0:  # (terms the mapping cannot have: PeakParams.inverse_problem)
                inverse -= 1
                full = fit_linear(init.edge_scale, init.corner_scale, readings, valid, tn, td, residual_degree,
                                  harmonics, fit_offsets, fit_gains, inverse)
            if full is None:
                raise CalibrationError("calibration data do not determine the per-zone parameters "
                                       "(every zone needs returns in several frames at different distances)")
            params = full
            if tilted:
                params = _fit_scales(params, readings, valid, tn, td, bar, max_iter, residual_degree, harmonics,
                                     fit_offsets, fit_gains, inverse)
    finally:
        bar.close()
    after = _summary(_errors(params, readings, valid, tn, td))
    report = {"frames": len(frames), "before": before, "paper_style_fit": paper_style, "after": after,
              "params": params.to_dict(), "residual_degree": residual_degree, "harmonics": harmonics,
              "fit_offsets": fit_offsets, "fit_gains": fit_gains, "scales_fitted": tilted or paper, "paper": paper,
              "readings": int((valid & np.isfinite(readings)).sum()),
              "parameters": mapping_parameters(params, fit_offsets, fit_gains, tilted or paper, paper)}
    if inverse_report is not None:
        report["zone_inverse"] = {"power": inverse, "held_out_range_rms_mm": inverse_report["rms_mm"],
                                  "folds": inverse_report["folds"]}
    return params, report


def mapping_parameters(params: PeakParams, fit_offsets: bool = True, fit_gains: bool = True,
                       scales_fitted: bool = False, paper: bool = False) -> int:
    """How many parameters :func:`fit_points` fitted for ``params``: the zones' gains (``m`` their mean) and offsets
    (``b`` theirs), or one of each; the residual series' terms beyond the linear part, the phase correction's, each
    zone's terms in the inverse range, and the two direction scales when they were fitted (the paper's procedure:
    ``m``, ``b`` and the two scales). What the calibration frames' readings must outnumber for the mapping's errors on
    them to say anything of its errors on new frames (:func:`small_sample_factor`)."""
    if paper:
        return 4
    return ((N_ZONES if fit_gains else 1) + (N_ZONES if fit_offsets else 1) + max(len(params.residual_coeffs) - 2, 0)
            + len(params.phase_coeffs) + len(params.zone_inverse) + (2 if scales_fitted else 0))


#: A calibration's fewest frames with ground truth at :data:`MIN_CALIBRATION_RANGE` or farther, and their fewest
#: distinct axis distances (:data:`~place_safe.recovery.points.MIN_DOMAIN_WIDTH` apart; ``fit_method`` refuses fewer).
#: The peak mapping fits about 24 parameters (9 zone gains, 9 offsets, 2 residual terms, 4 phase terms) to 9 readings
#: per frame: 3 frames leave 3 readings over and the fit reads its own frames to 0.005 mm, 4 leave 12. Held out on the
#: rest of the real sweep (41 frames from 9.5 to 39.5 cm; calibrated on 3-20 of them spread over that range), the
#: planes' mean NEES per dof was 20-130 from 3-4 frames, whatever the covariance scale: their in-sample errors are
#: fitted away, and no factor on them is honest. From 5 frames it was 1.1-6 (8-20 frames: 0.9-3). Each zone needs 3
#: distances for its gain and offset to leave one reading over. The project's own smallest calibrations: 6 synthetic
#: frames (tests/cli/test_app.py), 8 simulated ones (``calibrate --sim --frames`` at its least).
MIN_CALIBRATION_FRAMES = 5
MIN_CALIBRATION_DISTANCES = 3
#: Below this many frames a calibration is small: ``fit_method`` warns (a report note, printed even with -q) and widens
#: what its in-sample errors state by :func:`small_sample_factor`. From 10 frames on the held-out NEES per dof above was
#: 0.9-1.9 without a factor (one 14-frame split 3.0), as near 1 as the real sweep's halves (26 frames each) give; below
#: it, with the factor, 0.4-2.2.
FEW_CALIBRATION_FRAMES = 10


def small_sample_factor(report: dict) -> float:
    """What the variances a mapping's fit ``report`` (:func:`fit_points`: ``frames``, ``readings``, ``parameters``)
    measured on its own frames are multiplied by to hold for new frames: ``(n + p) / (n - p)`` for ``n`` readings and
    ``p`` parameters below :data:`FEW_CALIBRATION_FRAMES` frames, else 1. A least-squares fit of ``p`` parameters
    leaves its ``n`` data a mean squared error ``(1 - p / n)`` times the noise's, and errs on a new datum by
    ``(1 + p / n)`` times it: the ratio is the in-sample error's shortfall (5 frames of the peak mapping: 3.5, 9 frames:
    1.9). Held out on the rest of the real sweep (calibrated on 5-9 of its frames from 9.5 to 39.5 cm, two spreads each)
    it took peak's mean NEES per dof from 1.1-6.1 to 0.4-2.2; the on-sensor distances' with it, 0.7-1.5 (10-30 frames,
    no factor: peak 0.9-3.0, on-sensor 0.9-2.2). Raises :class:`CalibrationError` when the readings do not outnumber
    the parameters or fewer than :data:`MIN_CALIBRATION_FRAMES` frames were fitted."""
    frames, n, p = (int(report.get(k, 0)) for k in ("frames", "readings", "parameters"))
    if frames >= FEW_CALIBRATION_FRAMES:
        return 1.0
    if frames < MIN_CALIBRATION_FRAMES:  # (frames with truth, but too few with returns in 3 or more zones)
        raise CalibrationError(f"calibration: {frames} frames with returns in 3 or more zones; the mapping needs "
                               f"{MIN_CALIBRATION_FRAMES} or more ({FEW_CALIBRATION_FRAMES} or more recommended)")
    if n <= p:
        raise CalibrationError(f"calibration: {n} zone readings on {frames} frames for {p} parameters: nothing is left "
                               f"to measure the mapping's error (calibrate on {FEW_CALIBRATION_FRAMES} or more frames)")
    return (n + p) / (n - p)


def _calibration_frames(frames: Sequence[Frame], min_range: float) -> list[Frame]:
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= min_range]
    if len(use) < 3:
        raise CalibrationError(f"calibration needs 3 or more frames with ground truth at >= {min_range * 1e3:.0f} mm, "
                               f"got {len(use)}")
    return use


#: How far (a factor either way) a fitted mapping's slope ``m`` may lie from its family's built-in one (peak: the
#: TMF8820's bins, 72 a metre; on-sensor distances: 1000 mm a metre). Beyond it the readings do not follow the ground
#: truth as the sensor's do: a ground truth in other units or of other frames. The real sweep and the simulated units
#: fit 70-72 and 985-1000; a ground truth ten times too far wrote peak's m 7.2 (every plane ten times too far), and one
#: in centimetres failed with "peak parameters: m: Input should be greater than or equal to 1" (session 82).
MAX_SLOPE_FACTOR = 2.0


def slope_problem(m: float, like: PeakParams, what: str) -> str | None:
    """Why a mapping's slope ``m`` (reading units per metre of the ground truth's range) cannot be the sensor's --
    beyond :data:`MAX_SLOPE_FACTOR` of ``like.m``, the family's built-in one, or not a positive number -- or None.
    ``what``: the readings, e.g. ``"returns"``."""
    if like.m / MAX_SLOPE_FACTOR <= m <= like.m * MAX_SLOPE_FACTOR:
        return None
    unit = "bins" if like.m < 1000.0 / MAX_SLOPE_FACTOR else "mm"
    return (f"the {what} move {m:.3g} {unit} per metre of the ground truth's range, where the sensor's move about "
            f"{like.m:.4g} (within a factor {MAX_SLOPE_FACTOR:g}): is the ground truth in metres, and is it these "
            "frames'?")


def _initial_linear(readings: np.ndarray, valid: np.ndarray, frames: Sequence[Frame], like: PeakParams,
                    what: str = "readings") -> PeakParams:
    """Start values for m, b from a straight-line fit of readings vs. true ranges (nominal directions);
    :class:`CalibrationError` where its slope cannot be the sensor's (:func:`slope_problem`)."""
    tn, td = _truth_arrays(frames)
    r = true_ranges(tn, td, like.directions())
    use = valid & np.isfinite(readings)
    if use.sum() < 2 or np.ptp(r[use]) < 1e-3:
        return like
    m, b = np.polyfit(r[use], readings[use], 1)
    if (why := slope_problem(float(m), like, what)) is not None:
        raise CalibrationError(f"calibration: {why}")
    if not np.isfinite(b):
        return like
    return PeakParams(float(m), float(b), like.edge_scale, like.corner_scale)


#: 1/counts: SPAD pile-up values tried by :func:`fit_pileup` (0, then a log grid around the TMF8820's ~3e-7).
PILEUP_GRID = (0.0, 3e-8, 1e-7, 2e-7, 3e-7, 5e-7, 1e-6, 2e-6)


def fit_pileup(hists: np.ndarray, frames: Sequence[Frame], like: PeakParams, grid: Sequence[float] = PILEUP_GRID,
               residual_degree: int = 3, harmonics: int = 2) -> tuple[float, dict]:
    """The SPAD pile-up (1/counts) that calibrates the peak method best on ``frames`` (histograms (F, 9, 128)).

    For each candidate the peaks are found (with ``like``'s sub-bin estimator) after :func:`~place_safe.sensor.histogram.undo_pileup`, the
    linear part of the mapping is fitted (:func:`fit_linear`, ``like``'s direction scales) and the mean
    point error taken; the best grid value is refined by a bounded search between its neighbours (in
    log pile-up). Returns the value and ``{"tried_per_count", "point_error_mm"}`` lists and ``identified``. Pile-up
    moves bright zones' peaks earlier than dark ones', so it is identified by brightness differing at the same
    range (tilt, albedo, zone gains), not by range alone: the range correction absorbs a common shift. Where the best
    value lowers the point error by less than :data:`PILEUP_IDENTIFIED` from none, the frames do not identify it and
    0 is returned (``lowest_unidentified_per_count``: where the flat curve's minimum lay): 7 real frames at 30-40 cm
    put it at 1.0e-6 per count (the sweep's 3.0e-7), 3 % below none, and the mapping then read the real frames at
    5-15 cm 13 deg off (NEES per dof 38) as the brighter returns were over-corrected; with none 1.2 deg (NEES per dof
    2.1 before ``calibrate``'s small-sample widening, 0.92 after)
    (session 90, docs/results.md "Bad input"). A diff calibration then adopts the forward fit's value where it reads
    the frames as well (:func:`adopt_pileup`).
    """
    from scipy.optimize import minimize_scalar

    tn, td = _truth_arrays(frames)
    tried: dict[float, float] = {}

    def cost(k: float) -> float:
        if k not in tried:
            readings, valid, _ = find_peaks(hists, k, like.subbin, like.subbin_half_width)
            keep = valid.sum(1) >= 3
            p = None
            if keep.sum() >= 3:
                p = fit_linear(like.edge_scale, like.corner_scale, readings[keep], valid[keep], tn[keep], td[keep],
                               residual_degree, harmonics)
            tried[k] = math.inf if p is None else _mean_point_error(p, readings[keep], valid[keep], tn[keep], td[keep])
        return tried[k]

    values = sorted(float(k) for k in grid)
    errs = [cost(k) for k in values]
    i = int(np.argmin(errs))
    best = values[i]
    if best > 0.0 and math.isfinite(errs[i]):
        lo = values[i - 1] if i > 0 and values[i - 1] > 0 else best / 3.0
        hi = values[i + 1] if i + 1 < len(values) else best * 3.0
        res = minimize_scalar(lambda u: cost(float(math.exp(u))), bounds=(math.log(lo), math.log(hi)),
                              method="bounded", options={"xatol": 0.05})
        k = float(math.exp(res.x))
        if cost(k) < cost(best):
            best = k
    if not math.isfinite(cost(best)):
        best = 0.0
    identified = best > 0.0 and cost(best) <= (1.0 - PILEUP_IDENTIFIED) * cost(0.0)
    found = best
    if not identified:  # the frames do not show one: no correction rather than the flat curve's noise
        best = 0.0
    ks = sorted(tried)
    return best, {"tried_per_count": ks, "point_error_mm": [tried[k] * 1e3 for k in ks], "identified": identified,
                  **({} if identified or found == 0.0 else {"lowest_unidentified_per_count": found})}


def fit_peak(frames: Sequence[Frame], init: PeakParams | None = None, progress: bool = True,
             min_range: float = MIN_CALIBRATION_RANGE, residual_degree: int = 3, harmonics: int = 2,
             fit_offsets: bool = True, paper: bool = False, pileup: float | None = None,
             subbin: str = "centroid", subbin_half_width: float = CENTROID_HALF_WIDTH,
             near_range: bool = True, inverse_degrees: Sequence[int] = INVERSE_DEGREES) -> tuple[PeakParams, dict]:
    """Calibrate the peak method on frames with ground truth; returns the parameters and a report.

    Frames closer than ``min_range`` (m) and frames without a usable return are left out of the mapping;
    then, with ``near_range`` (and not ``paper``), the near-range table is fitted on the frames closer than
    :data:`~place_safe.calibration.near_range.NEAR_END`, all of them (:func:`~place_safe.calibration.near_range.fit_near_range`). With
    ``paper=True`` this is the paper's calibration (Nelder-Mead over m, b, s_e, s_c only, no pile-up).
    ``pileup`` (1/counts): the SPAD pile-up to undo before finding peaks; None fits it
    (:func:`fit_pileup`), 0 turns the correction off. ``subbin``, ``subbin_half_width``: the sub-bin
    estimator of the readings (:func:`~place_safe.sensor.histogram.find_peaks`; the windowed centroid by
    default, the spline's maximum with ``paper=True``). ``inverse_degrees``: the powers of each zone's own term in
    the inverse range to choose among (:func:`select_inverse`; ``(0,)``: none).

    The centroid replaced the spline's maximum because the spline's error has a period of one bin that
    the phase correction removes only on average. Held out (calibrated on one half, measured on the
    other; ``place-safe calibrate --method diff``, then ``evaluate``), the centroid took the real sweep's
    halves at 5-40 cm from 0.25 / 0.25 deg (p95 0.75 / 0.47) and 0.17 / 0.10 mm to 0.16 / 0.16 deg (p95
    0.39 / 0.53) and 0.13 / 0.08 mm, the independent generator's frames from 0.30 to 0.26 deg, and its
    linear-pulse sensors from 0.43 / 0.46 to 0.25 / 0.21 deg (docs/results.md).
    """
    use = _calibration_frames(frames, min_range)
    hists = np.array([np.asarray(f.hists, dtype=float) for f in use])
    search: dict[str, list[float]] = {}
    if paper:
        k, subbin = 0.0, "spline"
    elif pileup is None:
        like = (init if init is not None else PeakParams.default_peak()).replace(
            subbin=subbin, subbin_half_width=subbin_half_width)
        k, search = fit_pileup(hists, use, like, residual_degree=residual_degree, harmonics=harmonics)
    else:
        k = float(pileup)
    readings, valid, _ = find_peaks(hists, k, subbin, subbin_half_width)
    params, report = _fit_readings("peak", "returns", use, readings, valid, init, PeakParams.default_peak(), progress,
                                   residual_degree, harmonics, fit_offsets, paper, min_range, inverse_degrees)
    params = params.replace(pileup=k, subbin=subbin, subbin_half_width=subbin_half_width)
    if not paper and near_range:
        params, report["near_range"] = fit_near_range(frames, params)
    report["params"] = params.to_dict()
    search = dict(search)
    found = {key: search.pop(key) for key in ("identified", "lowest_unidentified_per_count") if key in search}
    report["pileup"] = {"value": k, "fitted": pileup is None and not paper,
                        "linear_fit_point_error_mm": search, **found}
    report["parameters"] += int(report["pileup"]["fitted"] and k > 0.0)
    report["inverse_degrees"] = [int(d) for d in inverse_degrees]
    return params, report


#: A pile-up from the forward fit replaces the peak method's own choice unless it makes the peak
#: calibration's mean point error worse than this factor (a level sweep of one material does not
#: identify pile-up from point errors alone; the histogram shapes the forward fit sees do). The
#: simulated sweeps gain 0-16 % with the forward fit's value; on the independent generator's frames (many
#: tilts and albedos) it cost 3.8 % on the calibration frames and 0.29 -> 0.33 deg on held-out ones.
PILEUP_ADOPT_TOLERANCE = 1.02
#: ... and unless the peak method's own search identified pile-up: its best value lowered the linear
#: fit's point error by this fraction or more from none (the real sweep: 19 %; a level sweep of one
#: material: 0-2 %). The forward fit's value absorbs other misfit where its model is not the sensor.
PILEUP_IDENTIFIED = 0.05


def adopt_pileup(frames: Sequence[Frame], params: PeakParams, report: dict, pileup: float,
                 progress: bool = False) -> tuple[PeakParams, dict, bool]:
    """Refit the peak method with the pile-up ``pileup`` (1/counts) that the forward model's fit found.

    Pile-up makes bright zones read near (see :func:`~place_safe.sensor.histogram.undo_pileup`). Point
    errors identify it only when brightness varies at the same range; the forward fit identifies it from
    the histograms' shapes. Nothing changes when ``report`` shows that the peak calibration identified
    pile-up itself (:data:`PILEUP_IDENTIFIED`); otherwise the refit is kept unless its mean point error
    on ``frames`` exceeds ``params``' by more than :data:`PILEUP_ADOPT_TOLERANCE`. Returns (parameters,
    report, adopted). ``pileup`` must come from a forward model whose ``pileup_shadow`` is 1 (Coates), the
    pile-up :func:`~place_safe.sensor.histogram.undo_pileup` inverts: the default forward fit holds it there."""
    k = float(pileup)
    if not (math.isfinite(k) and k > 0.0) or abs(k - params.pileup) <= 1e-3 * k:
        return params, report, False
    search = report.get("pileup", {}).get("linear_fit_point_error_mm") or {}
    tried, errs = list(search.get("tried_per_count", [])), list(search.get("point_error_mm", []))
    identified = report.get("pileup", {}).get("identified")  # (reports before it: read from the search's lists)
    if identified is None:
        identified = 0.0 in tried and len(errs) == len(tried) and min(errs) <= (
            1.0 - PILEUP_IDENTIFIED) * errs[tried.index(0.0)]
    if identified:
        kept = dict(report)
        kept["pileup_from_forward"] = {"value": k, "adopted": False,
                                       "why": "the peak calibration identified its own pile-up"}
        return params, kept, False
    new, new_report = fit_peak(frames, progress=progress, pileup=k, subbin=params.subbin,
                               subbin_half_width=params.subbin_half_width,
                               inverse_degrees=report.get("inverse_degrees", INVERSE_DEGREES))
    before = report.get("after", {}).get("point_mean_mm", math.inf)
    after = new_report.get("after", {}).get("point_mean_mm", math.inf)
    adopted = bool(after <= PILEUP_ADOPT_TOLERANCE * before)
    chosen, chosen_report = (new, new_report) if adopted else (params, report)
    chosen_report = dict(chosen_report)
    chosen_report["pileup_from_forward"] = {"value": k, "adopted": adopted, "point_mean_mm_own": before,
                                            "point_mean_mm_with_forward_pileup": after}
    return chosen, chosen_report, adopted


def _fit_readings(method: str, what: str, use: list[Frame], readings: np.ndarray, valid: np.ndarray,
                  init: PeakParams | None, default: PeakParams, progress: bool, residual_degree: int,
                  harmonics: int, fit_offsets: bool, paper: bool, min_range: float,
                  inverse_degrees: Sequence[int] = (0,)) -> tuple[PeakParams, dict]:
    """Fit readings (F, 9) of frames ``use`` for ``method``: frames with 3 or more valid zones, a
    straight-line start unless ``init`` is given, then :func:`fit_points`."""
    keep = valid.sum(1) >= 3
    if keep.sum() < 3:
        raise CalibrationError(f"fewer than 3 calibration frames have {what} in 3 or more zones")
    use = [f for f, k in zip(use, keep) if k]
    readings, valid = readings[keep], valid[keep]
    start = init if init is not None else _initial_linear(readings, valid, use, default, what)
    params, report = fit_points(readings, valid, use, start, progress, residual_degree, harmonics, fit_offsets,
                                fit_offsets, paper, label=f"calibrate {method}", inverse_degrees=inverse_degrees)
    if (why := slope_problem(params.m, default, what)) is not None:  # (a given start, or a fit that went there)
        raise CalibrationError(f"calibration: {why}")
    report["method"] = method
    report["min_range_m"] = min_range
    return params, report


def refit_mapping(frames: Sequence[Frame], params: PeakParams, min_range: float = MIN_CALIBRATION_RANGE) -> PeakParams:
    """``params``' far-range mapping fitted again on ``frames`` (those with ground truth at ``min_range`` or farther and
    returns in 3 or more zones, as :func:`fit_peak` keeps them): its linear terms (:func:`fit_linear`: gains, offsets,
    residual series, phase and inverse-range terms, as many as ``params`` has) by least squares, with its direction
    scales, pile-up and sub-bin estimator held. Without its near-range table; ``params``' own mapping where the frames
    do not determine one. For reading a calibration frame as a new frame is read: by a mapping fitted without it
    (:func:`~place_safe.calibration.near_range.held_out_fits`)."""
    base = params.without_near_table()
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= min_range]
    if len(use) < 3:
        return base
    hists = np.array([np.asarray(f.hists, dtype=float) for f in use])
    readings, valid, _ = find_peaks(hists, base.pileup, base.subbin, base.subbin_half_width)
    keep = valid.sum(1) >= 3
    if keep.sum() < 3:
        return base
    tn, td = _truth_arrays([f for f, k in zip(use, keep) if k])
    zones = any(g != 1.0 for g in base.zone_gains) or any(o != 0.0 for o in base.zone_offsets)
    degree = len(base.residual_coeffs) - 1 if base.residual_coeffs else 0
    fitted = fit_linear(base.edge_scale, base.corner_scale, readings[keep], valid[keep], tn, td, degree,
                        len(base.phase_coeffs) // 2, zones, zones, len(base.zone_inverse) // N_ZONES)
    if fitted is None:
        return base
    return fitted.replace(pileup=base.pileup, subbin=base.subbin, subbin_half_width=base.subbin_half_width,
                          zone_residual=base.zone_residual, common_residual=base.common_residual)


def proprietary_readings(frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """On-sensor distances in mm (F, 9) and validity (F, 9) of frames: the zones the proprietary method reads
    (:func:`~place_safe.recovery.proprietary.on_sensor_readings`; none of a frame it refuses: one with corrupt
    histograms too, :func:`~place_safe.recovery.proprietary.histogram_problem`). (A frame with distances beyond what
    the sensor reports, or at confidence 0, entered the fit and broke it.)"""
    out = np.full((len(frames), N_ZONES), np.nan)
    valid = np.zeros((len(frames), N_ZONES), dtype=bool)
    for i, f in enumerate(frames):
        if histogram_problem(f) is not None:  # (a count beyond the 24-bit counters passes Frame.validate)
            continue
        try:
            dist, valid[i] = on_sensor_readings(f)
        except FrameError:
            continue
        out[i] = dist * MM_PER_M
    return out, valid


def zone_residuals(params: PeakParams, readings: np.ndarray, valid: np.ndarray,
                   frames: Sequence[Frame]) -> tuple[float, float]:
    """(own, shared) parts (m) of the zones' range errors that the mapping ``params`` leaves on readings (F, 9)
    with mask (F, 9) of ``frames`` with ground truth (the true range along each zone's direction): ``own``, the
    RMS of each zone's error about its frame's mean error (``n - 1`` degrees of freedom per frame of ``n`` zones);
    ``shared``, the spread of the frames' mean errors (RMS about 0) less the share ``own^2 / n`` the own parts
    put into a mean of ``n`` zones (0 when that is all of it). Frames with fewer than 2 zones do not count;
    (0, 0) without any."""
    tn, td = _truth_arrays(frames)
    with np.errstate(divide="ignore", invalid="ignore"):
        err = params.ranges(np.where(valid, readings, np.nan)) - true_ranges(tn, td, params.directions())
    use = valid & np.isfinite(err)
    n = use.sum(1)
    rows = n >= 2
    if not rows.any():
        return 0.0, 0.0
    e, use, n = np.where(use, err, 0.0)[rows], use[rows], n[rows]
    mean = e.sum(1) / n
    own2 = float(np.sum(np.where(use, e - mean[:, None], 0.0) ** 2) / np.sum(n - 1))
    shared2 = float(np.mean(mean ** 2) - own2 * np.mean(1.0 / n))
    return math.sqrt(own2), math.sqrt(max(shared2, 0.0))


def fit_proprietary(frames: Sequence[Frame], init: PeakParams | None = None, progress: bool = True,
                    min_range: float = MIN_CALIBRATION_RANGE, residual_degree: int = 3, fit_offsets: bool = True,
                    paper: bool = False, inverse_degrees: Sequence[int] = INVERSE_DEGREES) -> tuple[PeakParams, dict]:
    """Calibrate the on-sensor distances (mm readings) on frames with ground truth (no phase
    correction: the readings are whole millimetres, not sub-bin peaks). The mapping carries what it leaves of
    the zones' range errors on these frames (:func:`zone_residuals`: ``zone_residual``, ``common_residual``),
    from which the method states its covariance; the report gives them in mm (``zone_residual_mm``). Each zone's
    own terms in the inverse range as for peak (``inverse_degrees``, :func:`select_inverse`): the sensor's own
    distances carry the same error falling with range (the real odd half, one power: held out 0.81 -> 0.74 deg,
    0.52 -> 0.28 mm; on the even half the folds' fits with the terms move its far-off 3-5 cm distances by more than
    a mapping may, :meth:`~place_safe.recovery.points.PeakParams.inverse_problem`, and it takes none)."""
    use = _calibration_frames(frames, min_range)
    readings, valid = proprietary_readings(use)
    params, report = _fit_readings("proprietary", "on-sensor distances", use, readings, valid, init,
                                   PeakParams.default_proprietary(), progress, residual_degree, 0, fit_offsets,
                                   paper, min_range, inverse_degrees)
    keep = valid.sum(1) >= 3  # the frames the mapping was fitted on (_fit_readings)
    own, shared = zone_residuals(params, readings[keep], valid[keep], [f for f, k in zip(use, keep) if k])
    if (widen := small_sample_factor(report)) > 1.0:  # the residuals on its own few frames, as new frames see them
        report["small_sample"] = {"factor": widen, "zone_residual_mm_in_sample": {"own": own * 1e3,
                                                                                 "shared": shared * 1e3}}
        own, shared = own * math.sqrt(widen), shared * math.sqrt(widen)
    params = params.replace(zone_residual=min(own, MAX_ZONE_RESIDUAL), common_residual=min(shared, MAX_ZONE_RESIDUAL))
    report["params"] = params.to_dict()
    report["zone_residual_mm"] = {"own": own * 1e3, "shared": shared * 1e3}
    return params, report


__all__ = ["fit_points", "fit_peak", "refit_mapping", "fit_proprietary", "proprietary_readings", "zone_residuals", "MIN_CALIBRATION_RANGE",
           "MIN_CALIBRATION_FRAMES", "MIN_CALIBRATION_DISTANCES", "FEW_CALIBRATION_FRAMES", "mapping_parameters",
           "small_sample_factor", "slope_problem", "MAX_SLOPE_FACTOR",
           "tilt_angles", "level_frames"]
