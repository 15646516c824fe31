"""Calibration of the peak method's near-range table (``PeakParams.near_depths``, ``near_errors``,
``near_min_fraction``; see :mod:`place_safe.recovery.points`).

Closer than a few centimetres the TMF8820's emitter, beside its receiver, lights each zone's footprint
only in part: on the real sweep's level table the centre zone goes dark below 3 cm (6e3 counts at 2 cm
against 2e5-9e5 in the corners) and each zone's return comes from a point off its nominal direction.
Zone ranges there are off by up to 10 mm, in a way that changes smoothly with depth above 2 cm and
differs between zones, so a tilt appears that the surface does not have (a 3 deg error needs the ranges
consistent to 0.2 mm at 2 cm). The table learns each zone's range error against depth from the
calibration frames closer than :data:`NEAR_END`, and a zone whose return is below a fraction of the
frame's highest there is dropped.

How it is fitted (:func:`fit_near_range`):

1. readings with the far-range mapping; a frame is near when a zone lies closer than :data:`NEAR_END` (its median
   zone depth, in front of the sensor: one the mapping reads behind it gives no knot);
2. knots at the near frames' median zone depths (merged within :data:`NEAR_MERGE`, at most
   :data:`NEAR_MAX_KNOTS`), and one more at :data:`NEAR_END` where every zone's error is 0;
3. per zone, least squares of the range errors on the knots' hat functions with a second-difference
   penalty (zones without data at a knot take it from their neighbours);
4. the penalty and the weak-zone fraction are chosen by cross-validation over the near frames (leave
   one out, or :data:`NEAR_FOLDS` folds) on the mean point error of the frames between knots (those of
   the shallowest knot would be extrapolated, which the table never does: it holds its first value
   there), in two forms. *Knot-kept*: a left-out frame's knot stays in the table, its value set by the
   neighbours through the penalty. *Knot-out*: the table has the other frames' knots only, so the left-out
   frame lies between knots as a new frame does (:func:`_knot_out_errors`). The table is kept only if its
   knot-kept score beats the far-range mapping alone by :data:`NEAR_ADOPT` and :data:`NEAR_MIN_GAIN`, and is
   fitted with the knot-kept form's penalty and fraction unless the knot-out form's own choice reads its frames
   better than that one by :data:`NEAR_MIN_GAIN` or more (report ``chosen_by``). On the real sweep the knot-kept
   form smooths the table across the knots inside the overlap (5-12.5 mm): the 2.75 cm frame, left out of the sweep
   with its knot, read 3.8 deg off with its choice and 0.56 deg with the knot-out form's; the simulated units' knot-out
   choice gains 0.004 mm at most, and they keep the knot-kept one (docs/results.md, "The near-range
   table's smoothing chosen on frames between knots").

The report's ``held_out`` gives each near frame's tilt error (deg) by depth with the far-range mapping alone
and, where the table is kept, with the table fitted without that frame (knot-kept, at the chosen penalty). On the
whole real sweep (knots 7.5 mm apart), at 27.2 / 35.0 / 42.6 mm: 3.6, 1.2 and 0.72 deg (the mapping alone: 7.5,
0.78, 0.57), and 19 deg at 19.5 mm and 76-78 deg at 8-9 mm, frames too close to read in use. Read as a new frame is,
with its knot left out too, the 27.5 mm frame is 0.56 deg off (docs/results.md).

:func:`near_range_std` gives the zones' cross-validated range errors per knot, for the peak method's near-range
uncertainty (:meth:`place_safe.recovery.estimator.Uncertainty.near_std`).

Held out on the real sweep (calibrated on the even frames, measured on the odd ones), the table took the
2.75 and 4.25 cm frames from 8.1 and 0.17 deg to 3.3 and 0.09 deg, and the 5-40 cm frames from 0.16 to
0.13 deg (p95 0.39 -> 0.24; docs/results.md, near range). The other way round cross-validation rejects it: the odd
half's 2.75 cm frame, left out, lies between its 1.25 and 4.25 cm ones. It rejects it too on frames of the
independent generator (tilted, 2-30 cm, no near-range effect) and on both simulated sensors' captures.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from place_safe.calibration.point_errors import FAILED_FIT_ERROR, frame_point_errors, plane_point_errors, true_ranges
from place_safe.recovery.points import PeakParams, fit_planes, near_table, near_table_errors
from place_safe.sensor.frame import N_ZONES, Frame
from place_safe.sensor.histogram import find_peaks
from place_safe.evaluation.metrics import angular_errors

#: m: the near-range table covers depths below this; the last knot, where every zone's error is 0.
NEAR_END = 0.09
#: m: near frames whose median zone depths lie closer than this share a knot.
NEAR_MERGE = 0.003
#: Most knots of a table (frames are grouped by depth quantiles beyond this).
NEAR_MAX_KNOTS = 24
#: Second-difference penalties tried (relative to one frame's weight at a knot).
NEAR_PENALTIES = (1e-3, 1e-2, 1e-1, 1.0, 10.0)
#: Fractions of a frame's highest return below which a zone is dropped at near range, tried.
NEAR_MIN_FRACTIONS = (0.0, 0.01, 0.05)
#: The table is kept only when its cross-validated mean point error is at most this fraction of the
#: far-range mapping's on the same frames, and lower by :data:`NEAR_MIN_GAIN` (m) or more. Ten candidates
#: are compared, so the best of them looks better than it is by chance: on 80 frames of the independent
#: generator (no near-range effect to learn) the best scored 0.95 of none and did 16 % worse held out. The
#: real sweep's halves score 0.47-0.78 and gain 0.13-0.22 mm.
NEAR_ADOPT = 0.9
NEAR_MIN_GAIN = 0.02e-3
#: Near frames needed for a table; with more than :data:`NEAR_LOO_MAX`, cross-validation uses
#: :data:`NEAR_FOLDS` folds (frames dealt by depth) instead of leaving one out at a time.
NEAR_MIN_FRAMES = 4
NEAR_LOO_MAX = 30
NEAR_FOLDS = 10
#: m: largest error a table may hold (a zone that far off is not a near-range effect).
NEAR_MAX_ERROR = 0.05


def _knots(depths: np.ndarray) -> np.ndarray:
    """Knot depths (m) from the near frames' median depths: merged within :data:`NEAR_MERGE`, at most
    :data:`NEAR_MAX_KNOTS` - 1 of them, then :data:`NEAR_END`."""
    d = np.sort(depths[depths < NEAR_END - NEAR_MERGE])
    if len(d) > NEAR_MAX_KNOTS - 1:
        d = np.quantile(d, np.linspace(0.0, 1.0, NEAR_MAX_KNOTS - 1))
    knots: list[float] = []
    for v in d:
        if not knots or v - knots[-1] > NEAR_MERGE:
            knots.append(float(v))
    return np.array(knots + [NEAR_END])


def _hat(knots: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where depths (m, clipped to the knots) fall among the knots: the knot index ``j`` at or below each and
    the fraction ``t`` of the way to the next (hat-function weights ``1 - t`` on knot ``j``, ``t`` on ``j + 1``)."""
    x = np.clip(depth, knots[0], knots[-1])
    j = np.clip(np.searchsorted(knots, x, side="right") - 1, 0, len(knots) - 2)
    return j, (x - knots[j]) / (knots[j + 1] - knots[j])


def _fit_errors(knots: np.ndarray, depth: np.ndarray, err: np.ndarray, valid: np.ndarray,
                penalty: float) -> np.ndarray:
    """Per-zone errors (K, 9) at the knots: least squares on the hat functions of the knots with a
    second-difference penalty, the last knot held at 0. ``depth``, ``err``, ``valid``: (F, 9)."""
    return _fit_errors_many(knots, depth, err, valid, (penalty,))[0]


def _fit_errors_many(knots: np.ndarray, depth: np.ndarray, err: np.ndarray, valid: np.ndarray,
                     penalties) -> np.ndarray:
    """:func:`_fit_errors` for each of ``penalties`` (P,): (P, K, 9), the normal equations of the 9 zones built once
    (from each zone return's two hat weights) and solved together."""
    k = len(knots)
    diff2 = np.diff(np.eye(k), 2, axis=0)[:, :-1]
    reg = np.asarray(penalties, dtype=float)[:, None, None] * (diff2.T @ diff2) + 1e-9 * np.eye(k - 1)  # (P, K-1, K-1)
    with np.errstate(invalid="ignore"):
        m = valid & np.isfinite(depth) & (depth < NEAR_END)
    zone = np.broadcast_to(np.arange(N_ZONES), m.shape)[m]
    j, t = _hat(knots, depth[m])
    e = err[m]
    ata = np.zeros((N_ZONES, k, k))  # each zone's hat^T hat, and hat^T err, with the last knot's column
    atb = np.zeros((N_ZONES, k))
    for a, wa in ((j, 1.0 - t), (j + 1, t)):
        np.add.at(atb, (zone, a), wa * e)
        for b, wb in ((j, 1.0 - t), (j + 1, t)):
            np.add.at(ata, (zone, a, b), wa * wb)
    out = np.zeros((len(reg), k, N_ZONES))
    sol = np.linalg.solve(ata[None, :, :-1, :-1] + reg[:, None], atb[None, :, :-1, None])[..., 0]  # (P, 9, K-1)
    out[:, :-1] = sol.transpose(0, 2, 1)
    return out


def _table_point_errors(base_ranges: np.ndarray, dirs: np.ndarray, knots: np.ndarray, tables: np.ndarray,
                        group: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray) -> np.ndarray:
    """The point errors (P, F) of frames read through near-range tables at ``knots``: frame ``f`` through each of
    the P tables ``tables[group[f]]`` (``tables``: (G, P, K, 9)). Their zones' ranges are those of the far-range
    mapping ``base_ranges`` (F, 9) less the table's error there (as :meth:`PeakParams.ranges
    <place_safe.recovery.points.PeakParams.ranges>` reads them), along the zone directions ``dirs`` (9, 3); mask
    ``valid`` (F, 9), true planes ``tn`` (F, 3), ``td`` (F,). One PCHIP holds all the tables."""
    n, p = len(base_ranges), tables.shape[1]
    errors = near_table_errors(near_table(knots, np.moveaxis(tables, 2, 0)), knots, base_ranges * dirs[:, 2])
    errors = errors[np.arange(n), group]  # (F, P, 9): each frame's own group
    points = (base_ranges[:, None, :] - errors)[..., None] * dirs  # (F, P, 9, 3)
    rep = lambda a: np.repeat(a[:, None], p, axis=1).reshape((-1,) + a.shape[1:])  # noqa: E731  (F, ...) -> (F P, ...)
    return plane_point_errors(points.reshape(-1, N_ZONES, 3), rep(valid), rep(tn), rep(td)).reshape(n, p).T


def _knot_stds(knots: np.ndarray, depth: np.ndarray, err: np.ndarray, valid: np.ndarray) -> list[float]:
    """RMS zone range error (m) at each knot: the errors ``err`` (F, 9) of the zones in ``valid`` (F, 9),
    weighted by the hat function of their depth (``depth`` (F, 9), m; clipped to the knots), and 0 at the
    last knot (from there on the far-range floor holds). A knot without data takes its neighbours'."""
    k = len(knots)
    m = valid & np.isfinite(depth) & np.isfinite(err) & (depth < knots[-1])
    j, t = _hat(knots, depth[m])
    weight = np.zeros(k)
    square = np.zeros(k)
    e2 = err[m] ** 2
    np.add.at(weight, j, 1.0 - t)
    np.add.at(weight, j + 1, t)
    np.add.at(square, j, (1.0 - t) * e2)
    np.add.at(square, j + 1, t * e2)
    inner = np.arange(k - 1)
    has = weight[:-1] > 1e-6
    if not has.any():
        return [0.0] * k
    std = np.sqrt(np.interp(inner, inner[has], square[:-1][has] / weight[:-1][has]))
    return [float(v) for v in std] + [0.0]


def near_range_std(frames: Sequence[Frame], params: PeakParams) -> tuple[list[float], list[float], dict]:
    """Depths (m) and the RMS zone range error (m) at each, with which ``params`` read frames closer than
    :data:`NEAR_END`, judged on ``frames`` (with ground truth): the cross-validated errors of the table that
    :func:`fit_near_range` fits on them (or of the far-range mapping, where it keeps none), or the errors of
    ``params`` itself on them where those are larger (``params`` fitted on other frames: these are held out
    for it). Empty lists where the frames hold too few near frames. For the peak method's near-range
    uncertainty (:class:`~place_safe.recovery.estimator.Uncertainty`)."""
    frames = [f for f in frames if f.truth is not None]
    h = np.array([np.asarray(f.hists, dtype=float) for f in frames]) if frames else None
    _, rep = fit_near_range(frames, params, h)
    if "zone_std_mm" not in rep:
        return [], [], {"why": rep.get("why", "no near-range errors")}
    knots = np.asarray(rep["knots_m"])
    cv = np.asarray(rep["zone_std_mm"]) * 1e-3
    pos, valid, _ = params.peaks(h)
    dirs = params.directions()
    r = params.ranges(pos)
    tn = np.array([f.truth.normal for f in frames])
    td = np.array([f.truth.offset for f in frames])
    with np.errstate(invalid="ignore", divide="ignore"):
        own = np.asarray(_knot_stds(knots, r * dirs[:, 2], r - true_ranges(tn, td, dirs), valid))
    std = np.maximum(cv, own)
    return [float(v) for v in knots], [float(v) for v in std], {
        "knots_mm": [float(v) * 1e3 for v in knots], "cross_validated_mm": [float(v) * 1e3 for v in cv],
        "of_the_mapping_mm": [float(v) * 1e3 for v in own]}


def _knot_out_errors(fold_knots, fold, depth, err, keep, far_ranges, dirs, tn, td) -> np.ndarray:
    """The point errors (P, F) of the near frames, each read by the tables (one per penalty) fitted on the other folds
    with the knots of those folds' frames only (``fold_knots[f]``: :func:`_knots` of the frames not in fold ``f``): the
    frame lies between knots of other frames, as a new frame does."""
    out = np.full((len(NEAR_PENALTIES), len(fold)), FAILED_FIT_ERROR)
    for f, k_f in enumerate(fold_knots):
        test = fold == f
        if len(k_f) < 3:
            continue
        tables = _fit_errors_many(k_f, depth[~test], err[~test], keep[~test], NEAR_PENALTIES)  # (P, K, 9)
        e = _table_point_errors(far_ranges[test], dirs, k_f, tables[None], np.zeros(int(test.sum()), dtype=int),
                                keep[test], tn[test], td[test])
        ok = np.array([_usable(t) for t in tables])
        out[np.ix_(ok, np.flatnonzero(test))] = e[ok]
    return out


def _tilt_errors(params: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray) -> np.ndarray:
    """Angle (deg, (F,)) between each frame's plane through its zone points and the true normal ``tn`` (F, 3);
    NaN where the points give no plane."""
    n, _, _, ok = fit_planes(params.points(readings), valid)
    out = np.full(len(tn), np.nan)
    out[ok] = np.degrees(angular_errors(n[ok], tn[ok]))
    return out


def _usable(table: np.ndarray) -> bool:
    """Whether a fitted table's errors are finite and within :data:`NEAR_MAX_ERROR`."""
    largest = float(np.max(np.abs(table)))
    return math.isfinite(largest) and largest <= NEAR_MAX_ERROR


def _with_table(params: PeakParams, knots: np.ndarray, errors: np.ndarray, fraction: float) -> PeakParams:
    return params.replace(near_depths=[float(v) for v in knots], near_errors=[float(v) for v in errors.ravel()],
                          near_min_fraction=float(fraction))


def _zone_readings(frames: Sequence[Frame], base: PeakParams, hists: np.ndarray | None = None):
    """Each zone's reading of ``frames`` (with ground truth) by the far-range mapping ``base``: peak positions,
    validity and heights (F, 9), depths (m) and range errors against the truth (m, F x 9), the truths' normals
    (F, 3) and offsets (F,), each frame's median zone depth (F,) and whether it is near (3 or more valid zones,
    median depth under :data:`NEAR_END`)."""
    h = np.array([np.asarray(f.hists, dtype=float) for f in frames]) if hists is None else np.asarray(hists, float)
    pos, valid, _, heights = find_peaks(h, base.pileup, base.subbin, base.subbin_half_width, heights=True)
    tn = np.array([f.truth.normal for f in frames])
    td = np.array([f.truth.offset for f in frames])
    dirs = base.directions()
    r0 = base.ranges(pos)
    depth = r0 * dirs[:, 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        err = r0 - true_ranges(tn, td, dirs)
        frame_depth = np.nanmedian(np.where(valid, depth, np.nan), axis=-1) if valid.any() else np.full(len(frames), np.nan)
    # (in front of the sensor: a mapping fitted on far frames alone, 30 cm and more, read 5-28 mm frames at negative
    # depths, whose knots no table can have; the fit ended "peak parameters: near_depths.0: Input should be greater
    # than or equal to 0", session 82)
    near = (valid.sum(-1) >= 3) & np.isfinite(frame_depth) & (frame_depth >= 0.0) & (frame_depth < NEAR_END)
    return pos, valid, heights, depth, err, tn, td, frame_depth, near


def fit_near_range(frames: Sequence[Frame], params: PeakParams, hists: np.ndarray | None = None) -> tuple[PeakParams, dict]:
    """``params`` with a near-range table fitted on ``frames`` (with ground truth; histograms (F, 9, 128) may
    be passed in), or unchanged when the frames do not support one; and a report.

    ``params`` is the far-range mapping (its own table, if any, is replaced). See the module doc.
    """
    base = params.without_near_table()
    frames = [f for f in frames if f.truth is not None]
    report: dict = {"end_m": NEAR_END, "adopted": False}
    if not frames:
        report["why"] = "no frames with ground truth"
        return base, report
    pos, valid, heights, depth, err, tn, td, frame_depth, near = _zone_readings(frames, base, hists)
    report["frames"] = int(near.sum())
    if near.sum() < NEAR_MIN_FRAMES:
        report["why"] = (f"{int(near.sum())} frame(s) with ground truth closer than {NEAR_END * 1e3:.0f} mm; "
                         f"a table needs {NEAR_MIN_FRAMES}")
        return base, report
    idx = np.flatnonzero(near)
    pos, valid, heights, depth, err, tn, td = (a[idx] for a in (pos, valid, heights, depth, err, tn, td))
    frame_depth = frame_depth[idx]
    knots = _knots(frame_depth)
    if len(knots) < 3:
        report["why"] = "the near frames lie at fewer than 2 distinct depths"
        return base, report
    order = np.argsort(frame_depth, kind="stable")
    n_folds = len(idx) if len(idx) <= NEAR_LOO_MAX else NEAR_FOLDS
    fold = np.empty(len(idx), dtype=int)
    fold[order] = np.arange(len(idx)) % n_folds
    scored = frame_depth > knots[0] + NEAR_MERGE  # the shallowest knot's frames would be extrapolated: not scored
    cv = {"none": float(np.mean(frame_point_errors(base, pos, valid, tn, td)[scored]))}
    best: tuple[float, float, float] | None = None
    chosen: tuple[float, float, float] | None = None
    cv_out: dict[str, float] = {}
    kept: dict[float, np.ndarray] = {}  # the return mask after the weak-zone rule, per fraction
    dirs = base.directions()
    fold_knots = [_knots(frame_depth[fold != f]) for f in range(n_folds)]  # the knot-out form's tables' knots
    for fraction in NEAR_MIN_FRACTIONS:
        keep = kept[fraction] = _with_table(base, knots, np.zeros((len(knots), N_ZONES)), fraction).drop_weak(
            pos, valid, heights)
        with np.errstate(invalid="ignore"):
            far_ranges = base.ranges(np.where(keep, pos, np.nan))  # each table then takes its errors off these
        # every fold's table for every penalty (folds, P, K, 9), each frame read by its fold's
        tables = np.stack([_fit_errors_many(knots, depth[fold != f], err[fold != f], keep[fold != f], NEAR_PENALTIES)
                           for f in range(n_folds)])
        e_all = _table_point_errors(far_ranges, dirs, knots, tables, fold, keep, tn, td)  # (P, frames)
        for f, i in zip(*np.nonzero([[not _usable(t) for t in by_penalty] for by_penalty in tables])):
            e_all[i, fold == f] = FAILED_FIT_ERROR
        e_out = _knot_out_errors(fold_knots, fold, depth, err, keep, far_ranges, dirs, tn, td)
        for penalty, e, eo in zip(NEAR_PENALTIES, e_all, e_out):
            score = float(np.mean(e[scored]))
            cv[f"fraction {fraction:g}, penalty {penalty:g}"] = score
            out_score = float(np.mean(eo[scored]))
            cv_out[f"fraction {fraction:g}, penalty {penalty:g}"] = out_score
            if best is None or score < best[0]:
                best = (score, fraction, penalty)
            if chosen is None or out_score < chosen[0]:
                chosen = (out_score, fraction, penalty)
    assert best is not None and chosen is not None
    score, fraction, penalty = best  # whether to keep a table: the knot-kept score at its best
    # the table's smoothing: the knot-out choice where it reads frames between knots better by what a table must gain
    knot_out = cv_out[f"fraction {fraction:g}, penalty {penalty:g}"] - chosen[0] >= NEAR_MIN_GAIN
    if knot_out:
        _, fraction, penalty = chosen
    report.update(knots_m=[float(v) for v in knots], folds=n_folds,
                  cv_point_error_mm={k: v * 1e3 for k, v in cv.items()},
                  cv_knot_out_point_error_mm={k: v * 1e3 for k, v in cv_out.items()},
                  chosen_by="knot-out" if knot_out else "knot-kept", min_fraction=fraction, penalty=penalty)
    # each near frame's tilt error by depth: the far-range mapping alone, and (below) the table fitted without it
    report["held_out"] = {"depth_mm": [round(float(v) * 1e3, 2) for v in frame_depth[order]],
                          "tilt_error_deg_without_table": [round(float(v), 3) for v in
                                                           _tilt_errors(base, pos, valid, tn)[order]]}
    if not (score <= NEAR_ADOPT * cv["none"] and cv["none"] - score >= NEAR_MIN_GAIN):
        report["why"] = (f"cross-validated point error {score * 1e3:.3f} mm with the table against "
                         f"{cv['none'] * 1e3:.3f} mm without")
        # the far-range mapping's errors (fitted on frames from 3 cm, so in sample from there to the table's end)
        report["zone_std_mm"] = [v * 1e3 for v in _knot_stds(knots, depth, err, valid)]
        return base, report
    held = err.copy()  # each frame's zone errors under the table fitted without it (none where that one failed)
    tilt = np.full(len(idx), np.nan)  # and the tilt error of its plane (deg)
    for f in range(n_folds):
        test = fold == f
        table = _fit_errors(knots, depth[~test], err[~test], kept[fraction][~test], penalty)
        if _usable(table):
            with_table = _with_table(base, knots, table, fraction)
            r0 = depth[test] / base.directions()[:, 2]
            held[test] = err[test] - with_table.near_correction(r0)
            tilt[test] = _tilt_errors(with_table, np.where(kept[fraction][test], pos[test], np.nan),
                                      kept[fraction][test], tn[test])
    report["zone_std_mm"] = [v * 1e3 for v in _knot_stds(knots, depth, held, kept[fraction])]
    report["held_out"]["tilt_error_deg"] = [round(float(v), 3) for v in tilt[order]]
    keep = kept[fraction]
    table = _fit_errors(knots, depth, err, keep, penalty)
    report["largest_error_mm"] = float(np.max(np.abs(table))) * 1e3
    if not _usable(table):
        report["why"] = f"the table's largest error is not below {NEAR_MAX_ERROR * 1e3:.0f} mm"
        return base, report
    report["adopted"] = True
    report["zones_dropped"] = int((valid & ~keep).sum())
    return _with_table(base, knots, table, fraction), report


def held_out_fits(frames: Sequence[Frame], params: PeakParams, width: int = 1,
                  mapping: Callable[[list[Frame], PeakParams], PeakParams] | None = None) -> dict[int, PeakParams]:
    """For each near frame of ``frames`` (with ground truth, a zone closer than :data:`NEAR_END`), ``params`` with
    the near-range table that :func:`fit_near_range` fits without it, keyed by the frame's ``id``: the whole fit
    again (knots, penalty, weak-zone fraction, whether to keep a table), so the frame lies between knots of other
    frames as a new frame does. ``width`` adjacent near frames (by depth) are left out together, so their gap
    is wider; groups are left out one at a time up to :data:`NEAR_LOO_MAX` of them, else in :data:`NEAR_FOLDS`
    folds dealt by depth. ``mapping(frames, params)``: the far-range mapping fitted again on the frames left in
    (:func:`~place_safe.calibration.points.refit_mapping`); None keeps ``params``'s, fitted with the frames (from 3 cm
    on they are in its sample, and a sweep with few near frames then reads them as no new frame is read: a 20-frame
    level sweep of a simulated unit with 4 of them stated peak's planes at 5-9 cm with a NEES per dof of 10 held out,
    5 with the mapping refitted). For the near-range uncertainty (:mod:`place_safe.calibration.uncertainty`)."""
    frames = [f for f in frames if f.truth is not None]
    base = params.without_near_table()
    if not frames:
        return {}
    *_, frame_depth, near = _zone_readings(frames, base)
    idx = np.flatnonzero(near)
    group = np.empty(len(idx), dtype=int)
    group[np.argsort(frame_depth[idx], kind="stable")] = np.arange(len(idx)) // max(int(width), 1)
    groups = int(group.max()) + 1 if len(idx) else 0
    n_folds = groups if groups <= NEAR_LOO_MAX else NEAR_FOLDS
    fold = group % max(n_folds, 1)
    out: dict[int, PeakParams] = {}
    for k in range(n_folds):
        test = {int(i) for i in idx[fold == k]}
        rest = [f for i, f in enumerate(frames) if i not in test]
        fitted, _ = fit_near_range(rest, base if mapping is None else mapping(rest, base))
        out.update({id(frames[i]): fitted for i in test})
    return out


__all__ = ["fit_near_range", "near_range_std", "held_out_fits", "NEAR_END"]
