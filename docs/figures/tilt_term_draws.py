"""How many tilted frames size diff's stated tilt term (``uncertainty.size_tilt_term``)? For level-calibrated units,
draw a few of each unit's tilted frames, size the term on them, and read the NEES per dof of the other tilted frames.

    python docs/figures/tilt_term_draws.py --out ../scorecard --units A B 31 32 33 synth synth3 --few 10 20

``--out``: a directory of ``docs/figures/unit_scorecard.py`` (``{unit}_cal.json`` from a level sweep,
``{unit}_tilt.json``). Each tilted frame is read once by diff as ``recover`` returns it; frames diff kept (no
fallback) take part. A draw: ``--few`` frames tilted 5 deg or more, chosen at random, whose fit covariances (the
reported ones less the calibration's floor, scale and term) size the term; the others are read with the sized term.
(``calibrate`` sizes the term on the frames under diff's chi-square limit, which include the few the consistency and
preference checks send to peak: these draws leave those out, so they read a little better than ``calibrate`` would.)
Printed per unit: NEES per dof of the held-out frames with the term as calibrated, and over ``--draws`` draws the
median and range with the sized term, the share of draws in 0.5-2, and the factors' ranges.
"""
from __future__ import annotations

import argparse
import math
from dataclasses import replace
from pathlib import Path

import numpy as np


def read_rows(out: Path, unit: str):
    """(estimate with its fit covariance, truth, tilt in deg) of each tilted frame diff kept; and the calibration's
    diff uncertainty."""
    from place_safe.calibration import Calibration
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    est = make_estimator("diff", Calibration.load(out / f"{unit}_cal.json"))
    est.uncertainty = est.uncertainty.replace(blend=False)  # diff's own plane and covariance where it keeps them
    unc = est.uncertainty
    rows = []
    for f in load_frames(out / f"{unit}_tilt.json"):
        e = est.estimate(f)
        if not e.ok or e.method_used != "diff" or e.covariance is None:
            continue
        n, d = e.plane.normal, e.plane.offset
        fit = (np.asarray(e.covariance) - unc.tilt_floor(n, d)) / unc.scale - unc.floor(d)
        rows.append((replace(e, covariance=fit), f.truth, math.degrees(math.acos(min(1.0, abs(f.truth.normal[2]))))))
    return rows, unc


def held_out_nees(rows, unc) -> float:
    from place_safe.recovery.estimator import tilt_offset

    v = []
    for e, t, _ in rows:
        err = tilt_offset(e.plane) - tilt_offset(t)
        v.append(float(err @ np.linalg.solve(unc.apply(e.covariance, e.plane.offset, e.plane.normal), err)) / 3.0)
    return float(np.mean(v))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="unit_scorecard.py directory (level calibrations)")
    ap.add_argument("--units", nargs="+", default=["A", "B", "31", "32", "33", "synth", "synth3"])
    ap.add_argument("--few", type=int, nargs="+", default=[10, 20], help="tilted frames that size the term")
    ap.add_argument("--draws", type=int, default=20, help="random draws of the few (default 20)")
    args = ap.parse_args(argv)

    from place_safe.calibration.uncertainty import size_tilt_term

    print("| unit | few | as calibrated | sized: median [min-max] | in 0.5-2 | tilt factor | offset factor |")
    print("|---|---|---|---|---|---|---|")
    for unit in args.units:
        rows, unc = read_rows(args.out, unit)
        for few in args.few:
            res = []
            for seed in range(args.draws):
                order = np.random.default_rng(seed).permutation(len(rows))
                pick = [int(i) for i in order if rows[i][2] >= 5.0][:few]
                chosen = set(pick)
                test = [r for i, r in enumerate(rows) if i not in chosen]
                sized, rep = size_tilt_term([rows[i][0] for i in pick], [rows[i][1] for i in pick], unc)
                if "tilt_factor" not in rep:  # no usable frame among the few
                    continue
                res.append((held_out_nees(test, unc), held_out_nees(test, sized), rep["tilt_factor"],
                            rep["offset_factor"]))
            r = np.array(res)
            inside = float(np.mean((r[:, 1] >= 0.5) & (r[:, 1] <= 2.0)))
            print(f"| {unit} | {few} | {r[:, 0].mean():.2f} | {np.median(r[:, 1]):.2f} [{r[:, 1].min():.2f}-"
                  f"{r[:, 1].max():.2f}] | {inside:.0%} | {r[:, 2].min():.2f}-{r[:, 2].max():.2f} | "
                  f"{r[:, 3].min():.2f}-{r[:, 3].max():.2f} |", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
