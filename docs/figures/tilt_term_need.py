"""Diff's stated tilt term on level-calibrated units: what each unit's tilted frames need, and what other constants
would give, without calibrating again.

    python docs/figures/tilt_term_need.py --out ../scorecard                      # NEES as calibrated, and each need
    python docs/figures/tilt_term_need.py --out ../scorecard --floor 0.005        # the stated term with another floor
    python docs/figures/tilt_term_need.py --out ../scorecard --units 43 57 --floor 0.0025 0.003 0.0035

``--out``: a directory of ``docs/figures/unit_scorecard.py`` (``{unit}_cal.json`` from a level sweep,
``{unit}_tilt.json`` tilted frames). For each unit whose calibration stated its tilt term (a level sweep; not one sized
on tilted frames) the term is made again by :func:`~place_safe.calibration.uncertainty.diff_tilt_term` from the inputs
the calibration report keeps (model error, crosstalk, the readings' difference, the mount left), with the module's
constants or those given, and diff reads the tilted frames as ``recover`` returns it (fallbacks and the blend included:
the term weighs diff against peak, so the angle may move too). Printed per unit: the term (tilt / offset part), NEES per
dof, its tilt components and offset (each 1 for honest variances), the mean angle (deg), and for ``--need`` the tilt and
offset parts that give each component NEES 1 with every stated term off (what the frames need beyond the fit's
covariance and the level floor). The level floor, the fit's covariance and the fallback limits are the calibration's: a
lower tilt floor changes nothing else a level sweep fits (the level frames' tilts are the sweep's own).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from tilted_nees import components  # noqa: E402  (diff's errors and variances per component, as tilted_nees reads them)


def read_with_term(cal_path: Path, tilt_path: Path, term_for):
    """Diff's estimates of the tilted frames with the calibration's stated term made by ``term_for(report)`` (an
    ``Uncertainty`` or None to keep the file's); returns (frames, estimates, term) or None where the term was sized on
    tilted frames or the report lacks its inputs."""
    from place_safe.calibration import Calibration
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    raw = json.loads(cal_path.read_text())
    rep = raw["reports"]["uncertainty"]["diff"]
    if "tilt_model_error" not in rep or isinstance(rep.get("tilt_term_sized"), dict) and \
            "tilt_factor" in rep["tilt_term_sized"]:
        return None
    term = term_for(rep)
    raw["uncertainty"]["diff"]["tilt_rel"] = term.tilt_rel
    raw["uncertainty"]["diff"]["tilt_offset_rel"] = term.tilt_offset_rel
    with tempfile.NamedTemporaryFile("w", suffix=".json", delete=False) as tmp:
        json.dump(raw, tmp)
    cal = Calibration.load(tmp.name)
    Path(tmp.name).unlink()
    frames = [f for f in load_frames(str(tilt_path)) if f.truth is not None]
    return frames, make_estimator("diff", cal).estimate_many(frames), term


def need(e2: np.ndarray, level_var: np.ndarray, lever: np.ndarray) -> float:
    """The ``r`` with mean ``e2 / (level_var + (r lever)^2)`` = 1 (0 where the level variance already covers)."""
    from scipy.optimize import brentq

    def excess(lr: float) -> float:
        return float(np.mean(e2 / (level_var + math.exp(2.0 * lr) * lever ** 2))) - 1.0

    lo, hi = math.log(1e-6), math.log(1.0)
    if excess(lo) <= 0.0:
        return 0.0
    return math.exp(brentq(excess, lo, hi)) if excess(hi) < 0.0 else 1.0


def main(argv: list[str] | None = None) -> int:
    import place_safe.calibration.uncertainty as U
    from place_safe.evaluation.metrics import angular_error, nees

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="a unit_scorecard.py directory")
    ap.add_argument("--units", nargs="+", default=None, help="units (default: every calibrated one in --out)")
    ap.add_argument("--floor", type=float, nargs="+", default=[U.DIFF_TILT_FLOOR],
                    help=f"DIFF_TILT_FLOOR values to state the term with (default: {U.DIFF_TILT_FLOOR})")
    ap.add_argument("--need", action="store_true", help="also each unit's need, read with every stated term off")
    a = ap.parse_args(argv)
    units = a.units or sorted((p.name[:-len("_cal.json")] for p in a.out.glob("*_cal.json")
                               if "_few" not in p.name and "_unlabelled" not in p.name), key=lambda u: (len(u), u))

    def term(floor: float | None):
        def make(rep: dict):
            if floor is None:  # every stated term off
                return U.Uncertainty(tilt_rel=0.0, tilt_offset_rel=0.0, tilt_pivot=U.DIFF_TILT_PIVOT)
            saved, U.DIFF_TILT_FLOOR = U.DIFF_TILT_FLOOR, floor
            try:
                left = rep.get("tilt_mount_left_deg")
                return U.diff_tilt_term(rep["tilt_model_error"], rep["tilt_crosstalk"], rep.get("tilt_readings"),
                                        None if left is None else math.radians(left))
            finally:
                U.DIFF_TILT_FLOOR = saved
        return make

    print("| unit | floor | tilt / offset part | NEES/dof | tilt comps / offset | angle deg |"
          + (" need tilt / offset |" if a.need else ""))
    print("|---|---|---|---|---|---|" + ("---|" if a.need else ""))
    for u in units:
        cal, tilt = a.out / f"{u}_cal.json", a.out / f"{u}_tilt.json"
        if not (cal.exists() and tilt.exists()):
            print(f"| {u} | no calibration or tilted frames in {a.out} |")
            continue
        wants = ""
        if a.need:
            got = read_with_term(cal, tilt, term(None))
            if got is not None:
                err, var, tan, z0 = components(*got[:2])
                wants = (f" {need(np.r_[err[:, 0], err[:, 1]] ** 2, np.r_[var[:, 0], var[:, 1]], np.r_[tan, tan]):.4f}"
                         f" / {need(err[:, 2] ** 2, var[:, 2], z0 * tan):.4f} |")
        for floor in a.floor:
            got = read_with_term(cal, tilt, term(floor))
            if got is None:
                print(f"| {u} | - | sized on tilted frames or not stated |")
                break
            frames, ests, t = got
            err, var, _, _ = components(frames, ests)
            v = np.array(nees(ests, [f.truth for f in frames]), dtype=float)
            ang = float(np.degrees(np.mean([angular_error(e.plane, f.truth) for e, f in zip(ests, frames) if e.ok])))
            print(f"| {u} | {floor:g} | {t.tilt_rel:.4f} / {t.tilt_offset_rel:.4f} | {np.nanmean(v):.2f} | "
                  f"{np.mean(err[:, :2] ** 2 / var[:, :2]):.2f} / {np.mean(err[:, 2] ** 2 / var[:, 2]):.2f} | "
                  f"{ang:.3f} |" + wants, flush=True)
            wants = " |" if a.need else ""
    return 0


if __name__ == "__main__":
    sys.exit(main())
