"""Diff's NEES per dof on the tilted frames of level-calibrated simulated units, with a 90 % interval, per component
and by tilt; and whether two sets of calibrations return the same planes (only their covariances may differ).

    python docs/figures/tilted_nees.py --out ../scorecard --units A B 31 32 33 synth synth3
    python docs/figures/tilted_nees.py --out ../scorecard --units A_few12 32_few12     # unit_scorecard.py --few-tilts 12
    python docs/figures/tilted_nees.py --out ../scorecard_new --same-planes ../scorecard --units A B ...

``--out``: a directory of ``docs/figures/unit_scorecard.py`` (``{unit}_cal.json``, ``{unit}_tilt.json``). Each unit's
tilted frames are read by diff as ``recover`` returns it (fallbacks included, as ``evaluate`` scores it); NEES per dof
as :func:`~place_safe.evaluation.metrics.nees`; the interval as ``near_nees.py``'s (the mean of ``n`` frames read as
a scale times a chi-square mean with ``3 n`` dof). Components: the mean of ``e_k^2 / C_kk`` over the frames for the
two tilt components together and for the offset (each 1 for honest variances). ``--same-planes``: the largest
difference in normal (rad) and offset (m) against the calibrations of another directory, and how many frames changed
method (diff / its fallback to peak).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from near_nees import interval  # noqa: E402

TILT_BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 31.0))  # deg


def read(out: Path, unit: str):
    from place_safe.calibration import Calibration
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    tilt = out / f"{unit}_tilt.json"  # a unit_scorecard.py --few-tilts row (UNIT_fewN) reads its unit's frames
    tilt = tilt if tilt.exists() else out / f"{unit.split('_few')[0]}_tilt.json"
    frames = [f for f in load_frames(str(tilt)) if f.truth is not None]
    cal = Calibration.load(str(out / f"{unit}_cal.json"))
    return frames, make_estimator("diff", cal).estimate_many(frames), cal


def components(frames, ests):
    """(errors (n, 3), variances (n, 3), tan(tilt) (n,), z0 (n,)) of ``(n_x, n_y, d)`` over the frames diff read
    with a covariance (``ests`` one per frame)."""
    from place_safe.recovery.estimator import tilt_offset

    ok = [i for i, e in enumerate(ests) if e.ok and e.covariance is not None]
    err = np.array([tilt_offset(ests[i].plane) - tilt_offset(frames[i].truth) for i in ok]).reshape(-1, 3)
    var = np.array([np.diag(ests[i].covariance) for i in ok]).reshape(-1, 3)
    tan = np.array([math.tan(math.acos(min(abs(float(frames[i].truth.normal[2])), 1.0))) for i in ok])
    return err, var, tan, np.array([frames[i].truth.z0 for i in ok])


def main(argv: list[str] | None = None) -> int:
    from place_safe.evaluation.metrics import nees

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--units", nargs="+", default=["A", "B", "31", "32", "33", "synth", "synth3"])
    ap.add_argument("--same-planes", type=Path, default=None, help="another scorecard directory to compare planes with")
    a = ap.parse_args(argv)
    print("| unit | model error e | tilt_rel / tilt_offset_rel | NEES/dof [90 %] | tilt comps / offset | "
          + " | ".join(f"{lo:.0f}-{hi:.0f} deg" for lo, hi in TILT_BANDS) + " |")
    print("|" + "---|" * (5 + len(TILT_BANDS)))
    for u in a.units:
        frames, ests, cal = read(a.out, u)
        v = nees(ests, [f.truth for f in frames])
        deg = np.degrees([math.acos(min(abs(float(f.truth.normal[2])), 1.0)) for f in frames])
        err, var, _, _ = components(frames, ests)
        comp_t, comp_d = float(np.mean(err[:, :2] ** 2 / var[:, :2])), float(np.mean(err[:, 2] ** 2 / var[:, 2]))
        bands = [interval([x for x, g in zip(v, deg) if lo <= g < hi and math.isfinite(x)]) for lo, hi in TILT_BANDS]
        d = cal.uncertainty("diff")
        e = (cal.reports.get("forward") or {}).get("model_error_chi2")
        print(f"| {u} | {'-' if e is None else f'{e:.3f}'} | {d.tilt_rel:.4f} / {d.tilt_offset_rel:.4f} | "
              f"{interval([x for x in v if math.isfinite(x)])} | {comp_t:.2f} / {comp_d:.2f} | " + " | ".join(bands) + " |",
              flush=True)
        if a.same_planes is not None:
            _, other, _ = read(a.same_planes, u)
            dn = max((float(np.abs(x.plane.normal - y.plane.normal).max()) for x, y in zip(ests, other) if x.ok and y.ok),
                     default=0.0)
            dd = max((abs(x.plane.offset - y.plane.offset) for x, y in zip(ests, other) if x.ok and y.ok), default=0.0)
            moved = sum(x.method_used != y.method_used or x.ok != y.ok for x, y in zip(ests, other))
            print(f"|   against {a.same_planes.name}: largest normal difference {dn:.1e} rad, offset {dd:.1e} m, "
                  f"{moved} frames changed method |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
