"""Peak's held-out NEES per dof and tilt error closer than 5 cm (and 5-40 cm as a check), with the number of frames
and a 90 % interval for every NEES figure: the real sweep's halves (each calibrated by ``calibrate --method peak``
on one half and read on the other, both ways), the real sweep with one distance left out at a time, and simulated
mismatched units (each calibrated on its own level sweep of 100 frames 5 mm-40 cm and read on a second sweep of 80
frames 5 mm-40 cm plus a dense near sweep of 40 frames 19-51 mm, so 2-5 cm holds 30+ frames at every place
between the table's knots).

    python docs/figures/near_nees.py                      # everything (a few minutes)
    python docs/figures/near_nees.py --real               # the real figures only
    python docs/figures/near_nees.py --units 21 22 23     # the simulated units only
    python docs/figures/near_nees.py --frames             # and each 2-5 cm frame's depth, gap position, error, NEES
    python docs/figures/near_nees.py --units 11 --tilted  # and 30 frames at 2-5 cm tilted 0-20 deg per unit

The interval: the mean NEES per dof ``x`` of ``n`` frames (``3 n`` dof) is read as ``c`` times a chi-square mean
with ``3 n`` dof; the 90 % interval of ``c`` is ``[3 n x / chi2_0.95, 3 n x / chi2_0.05]``. Honest covariances
have ``c = 1``. "gap position" is a frame's depth's place between the calibration's near-range table knots
(0 at a knot, 0.5 mid-gap; "-" without a table).
"""
from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.stats import chi2

from place_safe.calibration import Calibration
from place_safe.calibration.fit import fit_method
from place_safe.evaluation.metrics import angular_error, nees
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator

ROOT = Path(__file__).resolve().parents[2]
SWEEP = ROOT / "tests" / "data" / "tmf8820_ur5_sweep.json"
BANDS = (("2-5 cm", 0.02, 0.05), ("5-40 cm", 0.05, 0.40))


def calibrate(frames) -> Calibration:
    cal = Calibration()
    fit_method(cal, frames, "peak", progress=False, log=None)
    return cal


def gap_position(depth: float, knots) -> float | None:
    if not knots or depth >= knots[-1]:
        return None
    k = np.asarray(knots)
    j = int(np.clip(np.searchsorted(k, depth, side="right") - 1, 0, len(k) - 2))
    t = (depth - k[j]) / (k[j + 1] - k[j])
    return float(min(max(t, 0.0), 1.0 - max(t, 0.0))) if depth >= k[0] else None


def read(cal: Calibration, frames) -> list[dict]:
    est = make_estimator("peak", cal)
    knots = cal.peak().near_depths
    rows = []
    for f in frames:
        e = est.estimate(f)
        v = float(nees([e], [f.truth])[0])
        rows.append({"depth": f.truth.z0, "gap": gap_position(f.truth.z0, knots), "plane": e.ok,
                     "deg": math.degrees(angular_error(e.plane, f.truth)) if e.ok else None,
                     "nees": v if math.isfinite(v) else None})
    return rows


def interval(values) -> str:
    v = [x for x in values if x is not None]
    if not v:
        return "-"
    n, x = len(v), float(np.mean(v))
    lo, hi = 3 * n * x / chi2.ppf(0.95, 3 * n), 3 * n * x / chi2.ppf(0.05, 3 * n)
    return f"{x:.2f} [{lo:.2f}-{hi:.2f}] n={n}"


def summary(name: str, rows: list[dict], show: bool) -> None:
    for band, lo, hi in BANDS:
        r = [x for x in rows if lo <= x["depth"] < hi]
        planes = [x for x in r if x["plane"]]
        if not r:
            continue
        deg = [x["deg"] for x in planes]
        acc = f"tilt mean {np.mean(deg):.2f} max {np.max(deg):.2f} deg" if deg else "no planes"
        print(f"{name:28s} {band:8s} frames {len(r):3d} (too close {len(r) - len(planes)})  {acc:30s} "
              f"NEES/dof {interval([x['nees'] for x in planes])}")
        if show and band == "2-5 cm":
            for x in planes:
                g = "-" if x["gap"] is None else f"{x['gap']:.2f}"
                print(f"    {x['depth'] * 1e3:6.2f} mm  gap {g:>4s}  {x['deg']:6.2f} deg  NEES/dof {x['nees']:.3f}")


def real(show: bool) -> None:
    sweep = load_frames(SWEEP)
    even, odd = sweep[0::2], sweep[1::2]
    summary("real even -> odd", read(calibrate(even), odd), show)
    summary("real odd -> even", read(calibrate(odd), even), show)
    rows = []
    for i, f in enumerate(sweep):
        if 0.02 <= f.truth.z0 < 0.09:
            rows += read(calibrate(sweep[:i] + sweep[i + 1:]), [f])
    summary("real, one distance out", rows, show)


#: the level sweep's heights (m) and frames; its spacing; the interleaved near sweep's frames (half a spacing above
#: each of the level sweep's frames closer than 9 cm)
LEVEL, LEVEL_FRAMES = (0.005, 0.40), 100
SPACING = (LEVEL[1] - LEVEL[0]) / (LEVEL_FRAMES - 1)
INTERLEAVED_FRAMES = 21


#: ``--tilted``: frames at 2-5 cm tilted 0 to this (rad), their number and seed
TILTED_MAX, TILTED_FRAMES, TILTED_SEED = math.radians(20.0), 30, 8


def unit(seed: int, data: Path, show: bool, interleaved: bool = False, tilted: bool = False) -> None:
    sweeps = {"level": (LEVEL_FRAMES, 3, LEVEL), "test": (80, 5, (0.005, 0.40)), "near": (40, 7, (0.019, 0.051)),
              "inter": (INTERLEAVED_FRAMES, 9, (LEVEL[0] + SPACING / 2,
                                                LEVEL[0] + SPACING / 2 + (INTERLEAVED_FRAMES - 1) * SPACING)),
              "tilted": (TILTED_FRAMES, TILTED_SEED, (0.02, 0.05))}
    files = {k: data / f"u{seed}_{k}.json" for k in sweeps}
    from place_safe.io.frame_file import write_frames
    from place_safe.sim.calibration_capture import capture_level_sweep
    from place_safe.sim.tof_mismatch import MismatchConfig
    u = MismatchConfig(seed=seed)
    for k, (n, s, h) in sweeps.items():
        if not files[k].exists() and (k != "inter" or interleaved) and (k != "tilted" or tilted):
            write_frames(files[k], capture_level_sweep("mismatch", n, s, heights=h, mismatch=u, temperature=45.0,
                                                       max_tilt=TILTED_MAX if k == "tilted" else 0.0))
    level = load_frames(files["level"]) + (load_frames(files["inter"]) if interleaved else [])
    cal = calibrate(level)
    name = f"unit {seed}" + (" + interleaved" if interleaved else "")
    if show:
        law = cal.reports.get("uncertainty", {}).get("peak", {}).get("near_range", {}).get("law", {})
        print(f"    law: share {law.get('share_independent_of_knots')} ({law.get('share_how')}), "
              f"held-out NEES/dof {law.get('nees_per_dof_held_out')}, knots {law.get('table_knots')}")
    summary(name, read(cal, load_frames(files["test"]) + load_frames(files["near"])), show)
    if tilted:
        summary(name + " tilted", read(cal, load_frames(files["tilted"])), show)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--real", action="store_true", help="the real figures only")
    ap.add_argument("--units", type=int, nargs="*", help="simulated mismatched units (MismatchConfig seeds)")
    ap.add_argument("--data", default=os.environ.get("NEAR_NEES_DATA", ""),
                    help="folder for the simulated units' frames (made there when missing; default: a temporary one)")
    ap.add_argument("--frames", action="store_true", help="each 2-5 cm frame too")
    ap.add_argument("--interleaved", action="store_true",
                    help="units: calibrate on the level sweep plus a second near sweep half a spacing above its "
                         "frames closer than 9 cm (the capture issue 26c proposed)")
    ap.add_argument("--tilted", action="store_true",
                    help=f"units: also {TILTED_FRAMES} frames at 2-5 cm tilted 0-{math.degrees(TILTED_MAX):.0f} deg")
    a = ap.parse_args()
    if a.units is None or a.real:
        real(a.frames)
    if a.units is None and not a.real:
        a.units = [11, 12, 13, 21, 22, 23]
    with tempfile.TemporaryDirectory() as tmp:
        for s in a.units or []:
            unit(s, Path(a.data or tmp), a.frames, a.interleaved, a.tilted)
    return 0


if __name__ == "__main__":
    sys.exit(main())
