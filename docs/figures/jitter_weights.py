"""Diff's own plane (the fallback's limits and the blend off in a copy of the calibration) on held-out real frames at
5-40 cm, with a timing-jitter term in its residual weights: each bin's variance h + 1 + (model_error h)^2 +
(sigma_t dh/dbin)^2, the slope of the observed counts by central differences (sigma_t in bins; 0 is the code as it is).
Session 79's experiment (docs/results.md, "A timing-jitter term in diff's weights"); peak is printed for the first.

    python docs/figures/jitter_weights.py cal_even.json odd.json 0 0.02 0.05 0.1 0.2 0.4
"""
import json
import sys

import numpy as np
from place_safe.io.frame_file import load_frames
from place_safe.calibration import Calibration
from place_safe.evaluation.evaluate import evaluate
import place_safe.recovery.differentiable as D
import place_safe.recovery.forward as F

cal_path, frames_path = sys.argv[1], sys.argv[2]
sigmas = [float(s) for s in sys.argv[3:]]
d = json.load(open(cal_path))
for k in ("chi2_limit", "consistency_limit", "prefer_ratio"):
    d["uncertainty"]["diff"][k] = None
d["uncertainty"]["diff"]["blend"] = False
cal = Calibration.from_dict(d)
frames = [f for f in load_frames(frames_path) if f.truth is not None and f.truth.z0 >= 0.05]
orig = F.residual_weights
for st in sigmas:
    def rw(h, model_error=F.MODEL_ERROR, st=st):
        h = np.clip(np.asarray(h, dtype=float), 0.0, None)
        slope = np.gradient(h, axis=-1)
        return 1.0 / np.sqrt(h + 1.0 + (model_error * h) ** 2 + (st * slope) ** 2)
    D.residual_weights = rw if st > 0 else orig
    rep = evaluate(frames, cal, methods=("diff", "peak") if st == sigmas[0] else ("diff",))
    for m, r in rep.results.items():
        print(f"sigma_t {st:5.3f} {m:5s} ang {np.degrees(np.nanmean(r.angular)):.3f} (p95 {np.degrees(np.nanpercentile(r.angular, 95)):.3f}) "
              f"lin {np.nanmean(r.linear)*1e3:.3f} mm  n={np.isfinite(r.angular).sum()} used={set(r.used)}", flush=True)
