"""The residual weighting of diff's solver (the relative model error) chosen by the planes it recovers.

The forward model weighs each bin by its shot noise and a relative model error ``e``
(:func:`~place_safe.recovery.forward.residual_weights`): ``e`` sets how much the brightest bins count against the
rest. The chi-square value of the forward fit's residuals
(:func:`forward_fit.measure_model_error`) over-weights a real sensor's structured mismatch, so
calibration tries each value of :data:`MODEL_ERROR_GRID` with diff on the frames with ground truth and keeps the one
that recovers their planes best (:func:`select_model_error`). Units: ``e`` is relative (a fraction of the counts).
"""
from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np
from tqdm import tqdm

from place_safe.calibration.forward_fit import usable_frames
from place_safe.calibration.plane_correction import corrected_offset_error
from place_safe.evaluation.metrics import point_error
from place_safe.recovery.differentiable import DifferentiableEstimator, SolverOptions
from place_safe.recovery.forward import ForwardParams
from place_safe.sensor.frame import Frame


#: Relative model errors tried by :func:`select_model_error`.
MODEL_ERROR_GRID = (0.0, 0.005, 0.01, 0.02, 0.04)


def select_model_error(frames: Sequence[Frame], forward: ForwardParams, peak=None,
                       grid: Sequence[float] = MODEL_ERROR_GRID, min_distance: float = 0.04,
                       max_distance: float = 1.0, progress: bool = True,
                       options: SolverOptions | None = None) -> tuple[float, dict]:
    """The residual weighting (relative model error) that recovers these frames' planes best.

    The model error sets how much the brightest bins count against the rest
    (:func:`~place_safe.recovery.forward.residual_weights`). Shot noise alone (0) is right when the model is exact; a
    real sensor's model mismatch is structured, and the chi-square value (:func:`forward_fit.measure_model_error`) then
    over-weights it. So each value of ``grid`` is tried with the fast differentiable estimator on the frames with ground
    truth, and scored by the worse of two errors, each in units of its smallest value over the grid: the mean angular
    error, and the mean offset error left after the plane correction that calibration fits next
    (:func:`plane_correction.fit_range_correction`: a Chebyshev series in the estimated ``z0`` or ``1 / z0``, here
    cross-validated leave-one-out). The raw point error is not the score: a bias in ``z0`` that the correction removes
    would decide it. (It chose 0.02 on the level sweeps of the independent generator and two mismatched units, where the
    angle and the corrected offset both say 0.01; on those units' tilted frames diff's mean angular error went 0.32 ->
    0.27, 0.15 -> 0.12 and 0.27 -> 0.22 deg.) The lowest
    score wins, fewest frames without a plane first; the report gives every value's errors. ``options``: the diff
    solver's (default :class:`~place_safe.recovery.differentiable.SolverOptions`; the staged unit model's ambient).
    """
    skipped: dict[str, int] = {}
    data = usable_frames(frames, min_distance, max_distance, skipped)
    if not data:
        return forward.model_error, {"why": "no usable frames", "frames_skipped": skipped}
    scores, angles, corrected, failures = {}, {}, {}, {}
    for e in tqdm(grid, desc="model error", unit="value", disable=None if progress else True, file=sys.stderr):
        est = DifferentiableEstimator(forward.replace(model_error=float(e)), peak, options=options)
        ests = est.estimate_many(data)
        rows = [(x.plane, f.truth) for x, f in zip(ests, data) if x.ok]
        failures[float(e)] = len(data) - len(rows)
        errs = [point_error(p, t) for p, t in rows]
        errs = [v for v in errs if np.isfinite(v)]
        scores[float(e)] = float(np.mean(errs)) if errs else math.inf
        ang = [math.acos(min(1.0, abs(float(np.dot(p.normal, t.normal))))) for p, t in rows]
        angles[float(e)] = float(np.mean(ang)) if ang else math.inf
        corrected[float(e)] = corrected_offset_error(np.array([p.z0 for p, _ in rows]),
                                                      np.array([t.z0 for _, t in rows]))
    finite = [e for e in scores if math.isfinite(scores[e])]
    report = {"frames": len(data), "frames_skipped": skipped,
              "mean_point_error_mm": {str(k): (v * 1e3 if math.isfinite(v) else None) for k, v in scores.items()},
              "mean_angular_error_deg": {str(k): (math.degrees(v) if math.isfinite(v) else None)
                                         for k, v in angles.items()},
              "corrected_offset_error_mm": {str(k): (v * 1e3 if math.isfinite(v) else None)
                                            for k, v in corrected.items()},
              "frames_without_plane": {str(k): v for k, v in failures.items()}}
    if not finite:  # no value recovers any frame: keep what the parameters had rather than pick blindly
        report.update(chosen=forward.model_error, why="no value of the grid recovered a plane")
        return forward.model_error, report

    def relative(table: dict) -> dict:
        vals = [v for k, v in table.items() if k in finite and math.isfinite(v)]
        unit = max(min(vals), 1e-12) if vals else 1.0
        return {k: (table[k] / unit if math.isfinite(table[k]) else math.inf) for k in finite}

    ra, ro, rp = relative(angles), relative(corrected), relative(scores)
    # the worse of angle and corrected offset; where neither can be compared, the raw point error
    score = {e: (max(ra[e], ro[e]) if math.isfinite(max(ra[e], ro[e])) else 1e6 * rp[e]) for e in finite}
    report["score"] = {str(k): v for k, v in score.items()}
    # fewest frames without a plane first, then the lowest score
    best = min(finite, key=lambda e: (failures[e], score[e]))
    report["chosen"] = best
    return best, report
