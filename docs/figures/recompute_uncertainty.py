"""A calibration's uncertainty sections fitted again by the code on the path (its forward, peak and diff sections as
they are), then its unit's tilted frames read: diff as returned (fallback rate, mean angle and offset error, NEES per
dof) and peak (the same). For trying a change to the covariances or the fallback rule without refitting the forward
model (docs/results.md, "The near law's share held": peak's tilt term with an offset part).

    python docs/figures/recompute_uncertainty.py NAME,CAL.json,CALIBRATION_FRAMES.json,TILTED_FRAMES.json [...]

e.g. a ``unit_scorecard.py --few-tilts 12`` directory: ``A_few12,D/A_few12_cal.json,D/A_level_few12.json,D/A_tilt.json``.
"""
from __future__ import annotations

import math
import sys

import numpy as np

from place_safe.calibration import Calibration
from place_safe.calibration.uncertainty import update_calibration
from place_safe.evaluation.metrics import angular_error, linear_error, nees
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator


def main(specs: list[str]) -> int:
    for spec in specs:
        name, cal_path, frames_path, tilted_path = spec.split(",")
        cal = Calibration.load(cal_path)
        update_calibration(cal, [f for f in load_frames(frames_path) if f.truth is not None], "diff")
        tilted = [f for f in load_frames(tilted_path) if f.truth is not None]
        line = [name]
        for method in ("diff", "peak"):
            read = [(e, f) for e, f in zip(make_estimator(method, cal).estimate_many(tilted), tilted) if e.ok]
            deg = np.mean([math.degrees(angular_error(e.plane, f.truth)) for e, f in read])
            mm = np.mean([linear_error(e.plane, f.truth) * 1e3 for e, f in read])
            v = np.nanmean(nees([e for e, _ in read], [f.truth for _, f in read]))
            fb = f", fallback {np.mean([e.method_used == 'peak' for e, _ in read]):.0%}" if method == "diff" else ""
            line.append(f"{method}: {deg:.3f} deg / {mm:.3f} mm, NEES/dof {v:.2f}{fb}")
        print(" | ".join(line), flush=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) < 2 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0)
    sys.exit(main(sys.argv[1:]))
