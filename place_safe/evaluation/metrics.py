"""Plane-recovery errors as the paper defines them (Sifferman et al., RA-L 2023, Sec. V).

* angular error (rad): the angle between the estimated and the true normal;
* linear error (m): ``|z0_est - z0_true|``, where each plane crosses the optical axis;
* point error (m): the mean distance between the points where an 8 x 8 grid of rays spanning the
  whole field of view meets the estimated and the true plane. The grid spans the union of the zone
  rectangles on ``z = 1``, x in [-0.294, 0.294], y in [-0.291, 0.291] (edges included).

Scalar versions take :class:`place_safe.geometry.Plane`; the ``*_errors`` versions take arrays of
normals (F, 3) and offsets (F,) and return (F,) arrays. Everything is in SI units.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from place_safe.geometry import Plane
from place_safe.recovery.estimator import tilt_offset
from place_safe.sensor.frame import ZONE_RECTS

#: Rays per side of the point-error grid (the paper's 8 x 8).
GRID_SIZE = 8


def grid_directions(n: int = GRID_SIZE) -> np.ndarray:
    """Unit directions (n*n, 3) of an n x n grid spanning the field of view on z = 1."""
    xs = np.linspace(ZONE_RECTS[:, 0].min(), ZONE_RECTS[:, 1].max(), n)
    ys = np.linspace(ZONE_RECTS[:, 2].min(), ZONE_RECTS[:, 3].max(), n)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    v = np.stack([gx.ravel(), gy.ravel(), np.ones(n * n)], axis=1)
    return v / np.linalg.norm(v, axis=1, keepdims=True)


_GRID = grid_directions()


def _as_arrays(normals: np.ndarray, offsets: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    n = np.asarray(normals, dtype=float).reshape(-1, 3)
    d = np.asarray(offsets, dtype=float).reshape(-1)
    return n, d


def angular_errors(est_normals: np.ndarray, true_normals: np.ndarray) -> np.ndarray:
    """Angles (rad) between normals (F, 3) and (F, 3)."""
    a = np.asarray(est_normals, dtype=float).reshape(-1, 3)
    b = np.asarray(true_normals, dtype=float).reshape(-1, 3)
    cross = np.linalg.norm(np.cross(a, b), axis=1)
    dot = (a * b).sum(1)
    return np.arctan2(cross, dot)


def linear_errors(est_normals: np.ndarray, est_offsets: np.ndarray, true_normals: np.ndarray,
                  true_offsets: np.ndarray) -> np.ndarray:
    """``|z0_est - z0_true|`` (m) for arrays of planes."""
    ne, de = _as_arrays(est_normals, est_offsets)
    nt, dt = _as_arrays(true_normals, true_offsets)
    return np.abs(de / ne[:, 2] - dt / nt[:, 2])


def point_errors(est_normals: np.ndarray, est_offsets: np.ndarray, true_normals: np.ndarray,
                 true_offsets: np.ndarray, grid: np.ndarray | None = None) -> np.ndarray:
    """Mean distance (m) between the grid rays' intersections with estimated and true planes."""
    ne, de = _as_arrays(est_normals, est_offsets)
    nt, dt = _as_arrays(true_normals, true_offsets)
    g = _GRID if grid is None else np.asarray(grid, dtype=float)
    # ray t along unit g meets n.x = d at t = d / (n.g); the points differ by |t_e - t_t| along g
    with np.errstate(divide="ignore", invalid="ignore"):
        te = de[:, None] / (ne @ g.T)
        tt = dt[:, None] / (nt @ g.T)
    return np.abs(te - tt).mean(axis=1)


def angular_error(est: Plane, true: Plane) -> float:
    """Angle (rad) between the normals of two planes."""
    return float(angular_errors(est.normal[None], true.normal[None])[0])


def linear_error(est: Plane, true: Plane) -> float:
    """``|z0_est - z0_true|`` (m)."""
    return abs(est.z0 - true.z0)


def point_error(est: Plane, true: Plane) -> float:
    """Mean distance (m) between the 8 x 8 grid rays' intersections with the two planes."""
    return float(point_errors(est.normal[None], [est.offset], true.normal[None], [true.offset])[0])


def summarise(errors: np.ndarray) -> dict[str, float]:
    """Mean, median and 95th percentile of finite errors (NaN entries ignored; all NaN if none)."""
    e = np.asarray(errors, dtype=float).reshape(-1)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"mean": float("nan"), "median": float("nan"), "p95": float("nan"), "count": 0}
    return {"mean": float(e.mean()), "median": float(np.median(e)), "p95": float(np.percentile(e, 95)),
            "count": int(e.size)}


def nees(estimates: Sequence, truths: Sequence) -> np.ndarray:
    """Normalised estimation error squared per frame, divided by its 3 degrees of freedom (NaN without a
    plane or covariance). Its mean is about 1 when the covariances are honest."""
    out = np.full(len(estimates), np.nan)
    for i, (e, t) in enumerate(zip(estimates, truths)):
        if e.ok and e.covariance is not None and t is not None:
            err = tilt_offset(e.plane) - tilt_offset(t)  # (n_x, n_y, d), the covariance's order
            out[i] = float(err @ np.linalg.solve(e.covariance, err)) / 3.0
    return out


__all__ = ["nees", "GRID_SIZE", "grid_directions", "angular_error", "linear_error", "point_error", "angular_errors",
           "linear_errors", "point_errors", "summarise"]
