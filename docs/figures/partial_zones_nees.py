"""Peak's errors and NEES per dof on frames whose returns come from only some zones (a table edge, a narrow board):
the frames of FRAMES at 5-40 cm with every other zone's histogram zeroed, read through CAL.

    python docs/figures/partial_zones_nees.py cal_even.json odd.json    # cal_even: place-safe calibrate even.json

Session 89 (docs/results.md, "Bad input"): three zones read NEES per dof 12-29 before ``partial_grid_floor``.
"""
from __future__ import annotations

import math
import sys

import numpy as np

from place_safe.calibration import Calibration
from place_safe.evaluation.metrics import angular_error, nees
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator
from place_safe.sensor.frame import Frame

SHAPES = {"L (0,1,3)": (0, 1, 3), "corners (0,2,6)": (0, 2, 6), "T (0,1,2,4)": (0, 1, 2, 4),
          "square (0,1,3,4)": (0, 1, 3, 4), "two columns (0,1,3,4,6,7)": (0, 1, 3, 4, 6, 7),
          "ring-8": (0, 1, 2, 3, 5, 6, 7, 8), "all 9": tuple(range(9))}


def main(cal_path: str, frames_path: str) -> None:
    est = make_estimator("peak", Calibration.load(cal_path))
    frames = [f for f in load_frames(frames_path) if f.truth is not None and 0.05 <= f.truth.z0 <= 0.40]
    for name, zones in SHAPES.items():
        errs, ne = [], []
        for f in frames:
            h = np.zeros_like(f.hists)
            h[list(zones)] = f.hists[list(zones)]
            e = est.estimate(Frame(h, f.reference))
            if e.ok:
                errs.append(math.degrees(angular_error(e.plane, f.truth)))
                ne.append(nees([e], [f.truth])[0])
        if not errs:
            print(f"{name:28s} no plane on any frame")
            continue
        print(f"{name:28s} n {len(errs):3d}  tilt mean {np.mean(errs):.2f} p95 {np.percentile(errs, 95):.2f} deg  "
              f"NEES/dof mean {np.nanmean(ne):.2f} median {np.nanmedian(ne):.2f}")


if __name__ == "__main__":
    main(*sys.argv[1:3])
