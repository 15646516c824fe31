"""Diff's and peak's planes of the same frame combined by their stated covariances: what a fusion of the two methods
would return, against each method alone and against diff as it returns today (its fallback to peak).

    python docs/figures/fusion.py FRAMES.json CALIBRATION.json [--min-distance 0.05] [--max-distance 0.41]

Per frame, with diff's own plane ``x_d`` (the calibration's fallback limits taken off) and peak's ``x_p``, each a
vector ``(n_x, n_y, d)`` with its stated covariance ``C_d``, ``C_p``, the rows are:

* ``diff``, ``peak``: each method alone; ``returned``: diff as ``recover --method diff`` returns it (peak's plane
  where it falls back);
* ``fused``: the inverse-covariance weighting ``(C_d^-1 + C_p^-1)^-1 (C_d^-1 x_d + C_p^-1 x_p)``, which treats the
  two errors as independent (they are not: both read the same histograms);
* ``fused where kept``: the fused plane where diff keeps its own, peak's where it falls back;
* ``fused where consistent``: the fused plane wherever diff passes the fallback's gates but its preference (its
  chi-square limit, its consistency with peak, 5 cm and farther), peak's elsewhere: the weighting then decides
  between the two continuously where ``prefer_ratio`` chose one;
* ``intersection``: covariance intersection (``P^-1 = w C_d^-1 + (1 - w) C_p^-1``, ``w`` in [0, 1] maximising
  ``det P^-1``), a combination that stays consistent whatever the two errors' correlation, and its ``where kept``.

Errors: the angle between the normals (deg, mean) and ``|d - d_true|`` (mm, mean). Printed with the median weight
``w`` given to diff. docs/results.md, "Diff and peak combined by their covariances".
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from place_safe.calibration import Calibration
from place_safe.evaluation.metrics import angular_errors
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator
from place_safe.recovery.diff_settings import NEAR_FALLBACK_RANGE


def _vec(plane) -> np.ndarray:
    n = np.asarray(plane.normal, dtype=float)
    return np.array([n[0], n[1], float(plane.offset)])


def _errors(x: np.ndarray, truth) -> tuple[float, float]:
    """(angle deg, |offset error| mm) of the plane vector ``x`` against ``truth``."""
    n = np.array([x[0], x[1], math.sqrt(max(1.0 - x[0] ** 2 - x[1] ** 2, 0.0))])
    ang = math.degrees(float(angular_errors(n[None], np.asarray(truth.normal, dtype=float)[None])[0]))
    return ang, abs(float(x[2]) - float(truth.offset)) * 1e3


def fuse(xd: np.ndarray, cd: np.ndarray, xp: np.ndarray, cp: np.ndarray) -> np.ndarray:
    """The inverse-covariance weighting of two estimates taken as independent."""
    id_, ip = np.linalg.inv(cd), np.linalg.inv(cp)
    return np.linalg.solve(id_ + ip, id_ @ xd + ip @ xp)


def intersect(xd: np.ndarray, cd: np.ndarray, xp: np.ndarray, cp: np.ndarray,
              steps: int = 101) -> tuple[np.ndarray, float]:
    """Covariance intersection of two estimates (any correlation): the estimate and diff's weight ``w``."""
    id_, ip = np.linalg.inv(cd), np.linalg.inv(cp)
    w = max(np.linspace(0.0, 1.0, steps), key=lambda v: np.linalg.det(v * id_ + (1.0 - v) * ip))
    info = w * id_ + (1.0 - w) * ip
    return np.linalg.solve(info, w * id_ @ xd + (1.0 - w) * ip @ xp), float(w)


ROWS = ("diff", "peak", "returned", "fused", "fused where kept", "fused where consistent", "intersection",
        "intersection where kept")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n\n", 1)[1])
    ap.add_argument("frames", help="frame file with ground truth")
    ap.add_argument("calibration", help="calibration file with a diff calibration")
    ap.add_argument("--min-distance", type=float, default=0.05, help="m (default 0.05)")
    ap.add_argument("--max-distance", type=float, default=0.41, help="m (default 0.41)")
    a = ap.parse_args(argv)
    from place_safe.exceptions import PlaceSafeError

    try:
        cal = Calibration.load(a.calibration)
        missing = [k for k in ("forward", "diff", "uncertainty") if k not in cal.sections]
        if missing:
            raise SystemExit(f"fusion: {a.calibration} has no {', '.join(missing)} section: calibrate it with "
                             "--method diff")
        own, peak, ret = (make_estimator("diff", cal.without_fallback()), make_estimator("peak", cal),
                          make_estimator("diff", cal))
        frames = [f for f in load_frames(a.frames)
                  if f.truth is not None and a.min_distance <= f.truth.z0 <= a.max_distance]
    except PlaceSafeError as exc:
        raise SystemExit(f"fusion: {exc}") from None
    rows: dict[str, list] = {k: [] for k in ROWS}
    weights, nees = [], []
    for f in frames:
        d, p, r = own.estimate(f), peak.estimate(f), ret.estimate(f)
        if d.plane is None or p.plane is None or r.plane is None or d.covariance is None or p.covariance is None:
            continue
        xd, xp, xr = _vec(d.plane), _vec(p.plane), _vec(r.plane)
        cd, cp = np.asarray(d.covariance, dtype=float), np.asarray(p.covariance, dtype=float)
        kept = r.method_used in (None, "diff", "diff+peak")  # diff returned its own plane or its blend with peak's
        unc = ret.uncertainty  # the fallback's gates but its preference (the weighting weighs the two itself)
        gated = (d.residual is not None and d.residual ** 2 <= unc.chi2_limit and unc.consistent(d, p)
                 and p.plane.offset >= NEAR_FALLBACK_RANGE)
        try:
            xf = fuse(xd, cd, xp, cp)
            xi, w = intersect(xd, cd, xp, cp)
            cf = np.linalg.inv(np.linalg.inv(cd) + np.linalg.inv(cp))
        except np.linalg.LinAlgError:  # a singular covariance: no weighting of this frame
            continue
        weights.append(w)
        if gated:  # the fused plane's NEES per dof under diff's covariance and under the weighting's
            e = xf - _vec(f.truth)
            nees.append((e @ np.linalg.solve(cd, e) / 3.0, e @ np.linalg.solve(cf, e) / 3.0))
        for k, x in zip(ROWS, (xd, xp, xr, xf, xf if kept else xr, xf if gated else xp, xi, xi if kept else xr)):
            rows[k].append(_errors(x, f.truth))
    if not weights:
        raise SystemExit("fusion: no frame with a truth and both methods' planes and covariances")
    for k, v in rows.items():
        v = np.array(v)
        print(f"{k:24s} {v[:, 0].mean():.3f} deg  {v[:, 1].mean():.3f} mm")
    print(f"{len(weights)} frames; intersection's weight on diff: median {np.median(weights):.2f}")
    if nees:
        m = np.mean(nees, axis=0)
        print(f"fused where consistent ({len(nees)} frames): NEES per dof {m[0]:.2f} under diff's covariance, "
              f"{m[1]:.2f} under the weighting's")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
