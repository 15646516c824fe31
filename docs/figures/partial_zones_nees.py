"""Errors and NEES per dof on frames whose returns come from only some zones (a table edge, a narrow board): the
frames of FRAMES at 5-40 cm with every other zone's histogram zeroed, read through CAL.

    python docs/figures/partial_zones_nees.py cal_even.json odd.json    # cal_even: place-safe calibrate even.json
    python docs/figures/partial_zones_nees.py cal_g.json g_tilt.json --by-tilt    # NEES by the planes' tilt
    python docs/figures/partial_zones_nees.py cal_even.json odd.json --method diff

Session 89 (docs/results.md, "Bad input"): three zones read NEES per dof 12-29 before ``partial_grid_floor``; session
90: 2.8-6.4 before ``zone_std`` and the zones' tilt scatter (``ZONE_TILT_SCATTER``).
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from place_safe.calibration import Calibration
from place_safe.evaluation.metrics import angular_error, nees
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator
from place_safe.sensor.frame import Frame

SHAPES = {"L (0,1,3)": (0, 1, 3), "corners (0,2,6)": (0, 2, 6), "T (0,1,2,4)": (0, 1, 2, 4),
          "square (0,1,3,4)": (0, 1, 3, 4), "two columns (0,1,3,4,6,7)": (0, 1, 3, 4, 6, 7),
          "ring-8": (0, 1, 2, 3, 5, 6, 7, 8), "all 9": tuple(range(9))}
#: deg, the tilt bands of --by-tilt
TILT_EDGES = (0.0, 10.0, 20.0, 31.0)


def only(frame: Frame, zones) -> Frame:
    """``frame`` with every zone but ``zones`` dark (its histogram zeroed)."""
    h = np.zeros_like(frame.hists)
    h[list(zones)] = frame.hists[list(zones)]
    return Frame(h, frame.reference)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration")
    ap.add_argument("frames")
    ap.add_argument("--method", default="peak", choices=("peak", "diff"))
    ap.add_argument("--by-tilt", action="store_true", help="mean NEES per dof in the tilt bands of TILT_EDGES")
    a = ap.parse_args()
    est = make_estimator(a.method, Calibration.load(a.calibration))
    frames = [f for f in load_frames(a.frames) if f.truth is not None and 0.05 <= f.truth.z0 <= 0.40]
    bands = list(zip(TILT_EDGES, TILT_EDGES[1:]))
    if a.by_tilt:
        print("shape".ljust(28), " ".join(f"{lo:.0f}-{hi:.0f} deg".rjust(15) for lo, hi in bands))
    for name, zones in SHAPES.items():
        errs, ne, tilts = [], [], []
        for f in frames:
            e = est.estimate(only(f, zones))
            if e.ok:
                errs.append(math.degrees(angular_error(e.plane, f.truth)))
                ne.append(nees([e], [f.truth])[0])
                tilts.append(math.degrees(math.acos(min(1.0, float(f.truth.normal[2])))))
        if not errs:
            print(f"{name:28s} no plane on any frame")
            continue
        if a.by_tilt:
            t, n = np.array(tilts), np.array(ne)
            cells = [f"{np.nanmean(n[m]):6.2f} (n {m.sum():3d})" if (m := (t >= lo) & (t < hi)).any() else "-"
                     for lo, hi in bands]
            print(name.ljust(28), " ".join(c.rjust(15) for c in cells))
            continue
        print(f"{name:28s} n {len(errs):3d}  tilt mean {np.mean(errs):.2f} p95 {np.percentile(errs, 95):.2f} deg  "
              f"NEES/dof mean {np.nanmean(ne):.2f} median {np.nanmedian(ne):.2f}")


if __name__ == "__main__":
    main()
