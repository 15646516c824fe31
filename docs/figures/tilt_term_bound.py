"""Diff's NEES on held-out tilted frames with the tilted calibration frames' factor on its stated tilt term bounded
below at ``--bound`` (``uncertainty.TILT_TERM_SCALES[0]``), the uncertainty section fitted again and nothing else.

    python docs/figures/tilt_term_bound.py --dir SCORECARD --units 43_few12 50_few12 --bound 0.5 0.35 0.25

``--dir``: a ``docs/figures/unit_scorecard.py --few-tilts N`` directory (``{unit}_fewN_cal.json``,
``{unit}_level_fewN.json``, ``{unit}_tilt.json``). Each row's calibration gets its ``uncertainty`` section fitted again
(``update_calibration`` on its own calibration frames) with the bound; at the landed bound that reproduces the stored
section (``same`` in the output). Then diff reads the unit's tilted frames: NEES per dof, the tilt components' and
the offset's mean ``e^2 / var``, and the mean angle error (deg) of what diff returns (docs/results.md, "The tilted
frames' factor on diff's stated tilt term").
"""
from __future__ import annotations

import argparse
import json
import tempfile
from pathlib import Path

import numpy as np


def main() -> None:
    import place_safe.calibration.uncertainty as U
    from place_safe.calibration import Calibration
    from place_safe.evaluation.metrics import angular_error, nees
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator
    from place_safe.recovery.estimator import tilt_offset

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dir", type=Path, required=True)
    ap.add_argument("--units", nargs="+", required=True, help="rows, e.g. 43_few12")
    ap.add_argument("--bound", type=float, nargs="+", default=[U.TILT_TERM_SCALES[0]])
    a = ap.parse_args()
    upper = U.TILT_TERM_SCALES[1]
    print("| row | bound | same as stored | factor (tilt / offset) | NEES per dof | tilt comps | offset | angle deg |")
    print("|---|---|---|---|---|---|---|---|")
    for bound in a.bound:
        U.TILT_TERM_SCALES = (bound, upper)
        for row in a.units:
            unit, few = row.split("_few")
            cal = Calibration.load(str(a.dir / f"{row}_cal.json"))
            stored = json.dumps(cal.sections["uncertainty"]["diff"], sort_keys=True)
            rep = U.update_calibration(cal, load_frames(str(a.dir / f"{unit}_level_few{few}.json"), strict=False), "diff")
            same = json.dumps(cal.sections["uncertainty"]["diff"], sort_keys=True) == stored
            with tempfile.TemporaryDirectory() as tmp:
                cal.save(str(Path(tmp) / "c.json"))
                est = make_estimator("diff", Calibration.load(str(Path(tmp) / "c.json")))
            test = [f for f in load_frames(str(a.dir / f"{unit}_tilt.json")) if f.truth is not None]
            ests = est.estimate_many(test)
            ok = [i for i, e in enumerate(ests) if e.ok and e.covariance is not None]
            err = np.array([tilt_offset(ests[i].plane) - tilt_offset(test[i].truth) for i in ok])
            var = np.array([np.diag(ests[i].covariance) for i in ok])
            sz = rep["diff"].get("tilt_term_sized", {})
            print(f"| {row} | {bound:g} | {same} | {sz.get('tilt_factor', float('nan')):.3f} / "
                  f"{sz.get('offset_factor', float('nan')):.3f} | "
                  f"{np.nanmean(np.array(nees(ests, [f.truth for f in test]), dtype=float)):.3f} | "
                  f"{np.mean(err[:, :2] ** 2 / var[:, :2]):.3f} | {np.mean(err[:, 2] ** 2 / var[:, 2]):.3f} | "
                  f"{np.degrees(np.mean([angular_error(ests[i].plane, test[i].truth) for i in ok])):.4f} |",
                  flush=True)


if __name__ == "__main__":
    main()
