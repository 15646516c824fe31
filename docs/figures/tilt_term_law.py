"""Diff's stated tilt term for level sweeps (``uncertainty.diff_tilt_term``) with other floors: for each unit, its
calibration's uncertainty sections fitted again by the code on the path (forward, peak and diff as they are), diff's
own planes of its tilted frames (no fallback, no floor: fit covariances), then their mean NEES per dof with the
calibration's floor and a tilt term ``hypot(tilt floor, DIFF_TILT_PER_ERROR e)`` per tan(tilt), ``hypot(offset floor,
DIFF_TILT_OFFSET_PER_ERROR e)`` per z0 tan(tilt), ``e`` the unit's model error (the report's ``tilt_model_error``).
Also what the frames need: the term ``size_tilt_term`` sizes on all of them (docs/results.md, "The forward fit's two
basins, landed").

    python docs/figures/tilt_term_law.py NAME,CAL.json,LEVEL.json,TILTED.json [...] [--floors 0.008,0 0.005,0.001 ...]

e.g. a ``unit_scorecard.py`` directory D: ``A,D/A_cal.json,D/A_level.json,D/A_tilt.json``.
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from place_safe.calibration import Calibration
from place_safe.calibration import uncertainty as U
from place_safe.calibration.points import tilt_angles
from place_safe.evaluation.metrics import nees
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator
from place_safe.recovery.estimator import PlaneEstimate

OPEN = dict(chi2_limit=math.inf, consistency_limit=math.inf, prefer_ratio=math.inf)


def floors(text: str) -> tuple[float, float]:
    tilt, offset = (float(v) for v in text.split(","))
    return tilt, offset


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("units", nargs="+", help="NAME,CAL.json,LEVEL.json,TILTED.json")
    ap.add_argument("--floors", type=floors, nargs="+",
                    default=[(0.008, 0.0), (0.008, 0.0015), (0.005, 0.001), (0.004, 0.0015), (0.004, 0.002)],
                    help="tilt floor,offset floor pairs (default: the table of docs/results.md)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    for spec in a.units:
        name, cal_path, level_path, tilted_path = spec.split(",")
        cal = Calibration.load(cal_path)
        U.update_calibration(cal, [f for f in load_frames(level_path) if f.truth is not None], "diff")
        e = float(cal.reports["uncertainty"]["diff"].get("tilt_model_error") or 0.0)
        est = make_estimator("diff", cal)
        unc = est.uncertainty
        # diff's own planes with their fit covariances: no floor, no term, no fallback
        est.uncertainty = unc.replace(scale=1.0, tilt_std=0.0, tilt_range_std=0.0, offset_std=0.0, offset_rel=0.0,
                                      tilt_rel=0.0, tilt_offset_rel=0.0, **OPEN)
        tilted = [f for f in load_frames(tilted_path) if f.truth is not None]
        own = [(x, f.truth) for x, f in zip(est.estimate_many(tilted), tilted) if x.ok and x.covariance is not None]
        line = [f"{name} (e {e:.3f})"]
        for tf, of in a.floors:
            term = unc.replace(tilt_rel=math.hypot(tf, U.DIFF_TILT_PER_ERROR * e),
                               tilt_offset_rel=math.hypot(of, U.DIFF_TILT_OFFSET_PER_ERROR * e))
            stated = [PlaneEstimate(x.plane, covariance=term.apply(x.covariance, x.plane.offset, x.plane.normal))
                      for x, _ in own]
            line.append(f"({tf:g}, {of:g}) {np.nanmean(nees(stated, [t for _, t in own])):.2f}")
        tilts = tilt_angles(np.array([t.normal for _, t in own]).reshape(-1, 3))
        steep = [xt for xt, tilt in zip(own, tilts) if tilt >= math.radians(3.0)]
        _, need = U.size_tilt_term([x for x, _ in steep], [t for _, t in steep], unc)
        line.append(f"need: tilt {need.get('tilt_rel_sized', math.nan):.4f}, "
                    f"offset {need.get('tilt_offset_rel_sized', math.nan):.5f} (frames tilted >= 3 deg)")
        print(" | ".join(line), flush=True)


if __name__ == "__main__":
    main()
