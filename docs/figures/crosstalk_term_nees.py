"""What diff returns on tilted frames with the crosstalk's parts of its stated tilt term changed (a what-if).

    python docs/figures/crosstalk_term_nees.py s1:s1_cal.json:s1_tilt.json s7:s7_cal.json:s7_tilt.json [--k 1 0.5 0.25]

For each ``NAME:CALIBRATION:FRAMES`` prints peak, diff's own plane (the blend off) and diff as returned (the blend of
diff's and peak's planes) with the calibration's diff tilt term as written (k = 1), with the crosstalk's part of its
tilt component (:data:`~place_safe.calibration.uncertainty.DIFF_TILT_PER_CROSSTALK` times the fitted crosstalk) times
each other ``k``, and with the crosstalk's offset part
(:data:`~place_safe.calibration.uncertainty.DIFF_TILT_OFFSET_PER_CROSSTALK`) taken out: mean angle (deg), mean
``|d - d_true|`` (mm), NEES per dof and the mean squared error over the stated variance of each of ``n_x``, ``n_y``
and ``d``. The calibration file is not changed (edited copies in a temporary folder). docs/results.md, "Each frame's
own crosstalk", "The crosstalk's stated terms, tried smaller".
"""
from __future__ import annotations

import argparse
import json
import math
import tempfile
from pathlib import Path

import numpy as np

from place_safe.calibration import Calibration
from place_safe.calibration.uncertainty import DIFF_TILT_OFFSET_PER_CROSSTALK, DIFF_TILT_PER_CROSSTALK
from place_safe.evaluation.metrics import angular_error
from place_safe.io.frame_file import iter_frames
from place_safe.recovery import make_estimator


def score(cal: Calibration, frames: list, method: str = "diff") -> str:
    """Mean angle, mean offset error, NEES per dof and the per-component ratios of ``method`` on ``frames``."""
    est = make_estimator(method, cal).estimate_many(frames)
    ang = np.degrees([angular_error(x.plane, f.truth) for x, f in zip(est, frames)])
    off = np.array([abs(x.plane.offset - f.truth.offset) for x, f in zip(est, frames)]) * 1e3
    comp, nees = [], []
    for x, f in zip(est, frames):
        r = np.array([x.plane.normal[0] - f.truth.normal[0], x.plane.normal[1] - f.truth.normal[1],
                      x.plane.offset - f.truth.offset])
        comp.append(r ** 2 / np.diag(x.covariance))
        nees.append(float(r @ np.linalg.solve(x.covariance, r)) / 3)
    c = np.mean(comp, axis=0)
    return (f"{ang.mean():.3f} deg {off.mean():.3f} mm NEES {np.mean(nees):.2f} "
            f"(n_x {c[0]:.2f} n_y {c[1]:.2f} d {c[2]:.2f})")


def variant(path: str, folder: Path, k: float = 1.0, offset_part: bool = True, blend: bool = True) -> Calibration:
    """The calibration at ``path`` with the crosstalk's tilt part times ``k``, its offset part kept or not, the blend
    on or off."""
    doc = json.loads(Path(path).read_text())
    xt = float(doc["forward"]["crosstalk"])
    u = doc["uncertainty"]["diff"]
    tilt, offset = float(u["tilt_rel"]), float(u["tilt_offset_rel"])
    u["tilt_rel"] = math.sqrt(max(tilt ** 2 - (DIFF_TILT_PER_CROSSTALK * xt) ** 2, 0.0)
                              + (k * DIFF_TILT_PER_CROSSTALK * xt) ** 2)
    if not offset_part:
        u["tilt_offset_rel"] = math.sqrt(max(offset ** 2 - (DIFF_TILT_OFFSET_PER_CROSSTALK * xt) ** 2, 0.0))
    u["blend"] = blend
    out = folder / f"cal_{k}_{int(offset_part)}_{int(blend)}.json"
    out.write_text(json.dumps(doc))
    return Calibration.load(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("units", nargs="+", help="NAME:CALIBRATION:FRAMES (tilted frames with truth)")
    ap.add_argument("--k", type=float, nargs="+", default=[1.0, 0.5, 0.25],
                    help="factors on the crosstalk's part of the tilt term (default 1 0.5 0.25)")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        for spec in args.units:
            name, cal, path = spec.split(":")
            frames = [f for f in iter_frames(path) if f.truth is not None]
            print(f"{name}: peak {score(Calibration.load(cal), frames, 'peak')}; "
                  f"diff's own {score(variant(cal, folder, blend=False), frames)}", flush=True)
            for k in args.k:
                print(f"  k = {k:g}: {score(variant(cal, folder, k), frames)}", flush=True)
            print(f"  k = 1, no offset part: {score(variant(cal, folder, 1.0, offset_part=False), frames)}", flush=True)


if __name__ == "__main__":
    main()
