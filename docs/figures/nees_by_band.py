"""Peak's and diff's held-out errors and NEES per dof by depth band (2-5, 5-9, 9-40 cm) for a calibration whose
uncertainty section is fitted again on its own level sweep with this code (``update_calibration``; the mapping, the
forward model and diff's section are the file's), read on test frames. Session 79 used it to measure the near law's
frames read by a far mapping fitted without them (docs/results.md); run it with the code before on PYTHONPATH for the
"before" column.

    python docs/figures/nees_by_band.py c13_20.json l13_20.json t13.json
"""
from __future__ import annotations

import json
import sys

import numpy as np

from place_safe.calibration import Calibration
from place_safe.calibration.uncertainty import update_calibration
from place_safe.evaluation.evaluate import evaluate
from place_safe.io.frame_file import load_frames

BANDS = ((0.0, 0.05), (0.05, 0.09), (0.09, 0.5), (0.05, 0.5))


def main(cal_path: str, level_path: str, test_path: str) -> None:
    cal = Calibration.from_dict(json.load(open(cal_path)))
    report = update_calibration(cal, load_frames(level_path), "diff" if "diff" in cal.sections else "peak")
    law = report["peak"].get("near_range", {}).get("law") or {}
    print("near law:", {k: law.get(k) for k in ("frames", "std_at_reference_mm", "power", "nees_per_dof_held_out")})
    methods = ("peak", "diff") if "diff" in cal.sections else ("peak",)
    r = evaluate(load_frames(test_path), cal, methods=methods)
    for lo, hi in BANDS:
        s = (r.z0 >= lo) & (r.z0 < hi)
        if not s.any():
            continue
        print(f"{lo * 100:.0f}-{hi * 100:.0f} cm, n = {int(s.sum())}: " + "; ".join(
            f"{m} {np.degrees(np.nanmean(r.results[m].angular[s])):.3f} deg, {np.nanmean(r.results[m].linear[s]) * 1e3:.3f} mm, "
            f"NEES per dof {np.nanmean(r.results[m].nees[s]):.2f}" for m in methods))


if __name__ == "__main__":
    if len(sys.argv) != 4:
        sys.exit(__doc__)
    main(*sys.argv[1:4])
