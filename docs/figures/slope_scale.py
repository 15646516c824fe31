"""How a method reads the slopes of tilted planes: its slopes ``(n_x / n_z, n_y / n_z)`` against the truth's, fitted
as ``est = M true + c`` by least squares over the frames (``M`` 2 x 2: a diagonal of 1.05 reads every slope 5 % too
steep along that axis). Diff's own plane (the calibration's fallback limits taken off), or ``--method peak``.

    python docs/figures/slope_scale.py TILTED_FRAMES.json CALIBRATION.json [--method diff|peak]

docs/results.md, "The independent generator's other sensors, by a level sweep alone": seeds 1 and 7 of the
generator, calibrated by a level sweep, read their slopes 3-7 % too steep.
"""
from __future__ import annotations

import argparse

import numpy as np

from place_safe.calibration import Calibration
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator


def slope_map(frames, estimator) -> tuple[np.ndarray, np.ndarray, float, float, int]:
    """``(M, c, rms before, rms after, frames)`` of the estimator's slopes against the frames' true ones."""
    true, est = [], []
    for f in frames:
        if f.truth is None:
            continue
        e = estimator.estimate(f)
        if e.plane is None:
            continue
        t, n = np.asarray(f.truth.normal, float), np.asarray(e.plane.normal, float)
        true.append(t[:2] / t[2])
        est.append(n[:2] / n[2])
    if len(true) < 3:
        raise SystemExit(f"slope_scale: {len(true)} frames with a truth and a plane; need at least 3")
    true, est = np.array(true), np.array(est)
    a = np.c_[true, np.ones(len(true))]
    coef, *_ = np.linalg.lstsq(a, est, rcond=None)
    resid = est - a @ coef
    return (coef[:2].T, coef[2], float(np.sqrt(((est - true) ** 2).mean())), float(np.sqrt((resid ** 2).mean())),
            len(true))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("frames", help="frame file with ground truth (tilted planes)")
    ap.add_argument("calibration", help="calibration file")
    ap.add_argument("--method", default="diff", choices=("diff", "peak"), help="diff's own plane (default) or peak")
    a = ap.parse_args(argv)
    from place_safe.exceptions import PlaceSafeError

    try:
        cal = Calibration.load(a.calibration)
        est = make_estimator(a.method, cal.without_fallback() if a.method == "diff" else cal)
        frames = load_frames(a.frames)
    except PlaceSafeError as exc:
        raise SystemExit(f"slope_scale: {exc}") from None
    m, c, before, after, n = slope_map(frames, est)
    print(f"{a.method} on {n} frames: slopes read as M = [[{m[0, 0]:.4f}, {m[0, 1]:.4f}], [{m[1, 0]:.4f}, "
          f"{m[1, 1]:.4f}]] times the truth's, plus ({c[0]:.4f}, {c[1]:.4f}); slope error RMS {before:.4f} "
          f"({after:.4f} about the fit)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
