"""How a near-range table should interpolate between its knots: the real sweep's zone errors by the far mapping alone
at three depths a, m, b (the frames' own), and the weight ``w`` of ``a`` in ``e(m) ~ w e(a) + (1 - w) e(b)`` that
fits the zones (least squares, the centre zone out), against what interpolation in depth (``(b - m) / (b - a)``),
in ``1 / z`` and in ``1 / z^2`` would use; then the tilt of the 27.5 mm frame's plane through its zones corrected by
``w e(20) + (1 - w) e(35)`` for a range of ``w`` (what a table with knots at 20 and 35 mm, and no frame between,
can do at best).

    python docs/figures/near_interpolation.py CAL.json FRAMES.json    # CAL: the far mapping (its near table unused)
"""
from __future__ import annotations

import sys

import numpy as np

from place_safe.calibration import Calibration
from place_safe.calibration.point_errors import true_ranges
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator
from place_safe.sensor.histogram import find_returns


def zone_errors(cal_path: str, frames_path: str, deepest: float = 0.095) -> dict[float, np.ndarray]:
    """Each frame's zone range errors (mm, (9,)) by the calibration's far mapping, by its depth (mm), to ``deepest``."""
    est = make_estimator("peak", Calibration.load(cal_path))
    p = est.params
    out = {}
    for f in load_frames(frames_path):
        if f.truth is None or f.truth.z0 > deepest:
            continue
        pos, _, _, _ = find_returns(np.asarray(f.hists, float), p.pileup, p.subbin, p.subbin_half_width)
        truth = true_ranges(np.array([f.truth.normal]), np.array([f.truth.offset]), p.directions())[0]
        out[round(f.truth.z0 * 1e3, 2)] = (est._far_ranges(pos) - truth) * 1e3
    return out


def tilt_deg(ranges_error: np.ndarray, depth_mm: float, dirs: np.ndarray) -> float:
    """Tilt (deg) of the plane through a level frame's zones at ``depth_mm`` with these range errors (mm)."""
    pts = (depth_mm / dirs[:, 2] + ranges_error)[:, None] * dirs
    _, _, vt = np.linalg.svd(pts - pts.mean(axis=0))
    n = vt[-1] * np.sign(vt[-1, 2])
    return float(np.degrees(np.arccos(min(1.0, n[2]))))


def main() -> None:
    from place_safe.sensor.zones import ZONE_DIRECTIONS

    errors = zone_errors(sys.argv[1], sys.argv[2])
    depths = sorted(errors)
    print("a m b (mm)            w fitted  depth  1/z  1/z^2")
    for a, m, b in zip(depths, depths[1:], depths[2:]):
        if a < 15.0:  # inside the overlap with the internal return: too close to read
            continue
        ea, em, eb = (np.delete(errors[k], 4) for k in (a, m, b))
        d = ea - eb
        w = float(d @ (em - eb) / (d @ d))
        inv = lambda q: (m ** -q - b ** -q) / (a ** -q - b ** -q)  # noqa: E731
        print(f"{a:5.1f} {m:5.1f} {b:5.1f}   {w:8.2f}  {(b - m) / (b - a):5.2f}  {inv(1):4.2f}  {inv(2):5.2f}")
    if {20.0, 27.5, 35.0} <= set(depths):
        dirs = np.asarray(ZONE_DIRECTIONS)
        print("27.5 mm frame corrected by w e(20) + (1 - w) e(35):")
        for w in (0.0, 0.2, 0.25, 0.29, 0.3, 0.35, 0.4, 0.5):
            r = errors[27.5] - w * errors[20.0] - (1 - w) * errors[35.0]
            print(f"  w {w:.2f}: tilt {tilt_deg(r, 27.5, dirs):.2f} deg")


if __name__ == "__main__":
    main()
