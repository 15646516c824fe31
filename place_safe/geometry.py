"""Planes, rays and rigid transforms in the sensor frame.

Conventions
-----------
* Sensor frame: origin at the sensor, optical axis +z, x/y as in the TMF8820 zone table.
* A plane is ``n . x = d`` with unit normal ``n`` pointing away from the sensor (``n_z > 0``) and
  ``d > 0`` the perpendicular distance in metres.
* The paper's parametrisation: angle of incidence ``theta`` (between ``n`` and +z), azimuth ``phi``
  of ``n`` about +z, and ``z0``, where the plane crosses the optical axis: ``d = z0 cos(theta)``.
* The solver's parametrisation: slopes ``(a, b)`` and ``z0`` with ``n ~ (a, b, 1)``; smooth at
  ``theta = 0`` where ``(theta, phi)`` is singular.
All angles are radians.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from place_safe.exceptions import NoPlaneError


@dataclass(frozen=True)
class Plane:
    """A plane ``n . x = d`` in the sensor frame (unit ``n`` with ``n_z > 0``, ``d`` in metres)."""

    normal: np.ndarray
    offset: float

    def __post_init__(self) -> None:
        try:
            n = np.asarray(self.normal, dtype=float).reshape(3)
            d = float(self.offset)
        except (TypeError, ValueError, OverflowError):
            raise ValueError(f"plane needs a normal of 3 numbers and a number offset; got normal of shape "
                               f"{np.shape(self.normal)} and offset {str(self.offset)[:40]!r}") from None
        if not (all(map(math.isfinite, n.tolist())) and math.isfinite(d)):
            raise NoPlaneError(f"plane is not finite: normal={n}, offset={d}")
        norm = math.sqrt(float(n @ n))
        if norm < 1e-12:
            raise NoPlaneError("plane normal has zero length")
        n, d = n / norm, d / norm  # n . x = d scaled so that |n| = 1
        if n[2] < 0:
            n, d = -n, -d
        if n[2] <= 1e-9:
            raise NoPlaneError("plane contains the optical axis direction (n_z = 0); it is never hit along +z")
        object.__setattr__(self, "normal", n)
        object.__setattr__(self, "offset", d)

    # -- conversions ---------------------------------------------------------------------------
    @property
    def theta(self) -> float:
        """Angle of incidence: angle between the normal and the optical axis (rad)."""
        return float(np.arccos(np.clip(self.normal[2], -1.0, 1.0)))

    @property
    def phi(self) -> float:
        """Azimuth of the normal about +z (rad, in (-pi, pi])."""
        return float(np.arctan2(self.normal[1], self.normal[0]))

    @property
    def z0(self) -> float:
        """Where the plane crosses the optical axis (m)."""
        return self.offset / float(self.normal[2])

    @classmethod
    def from_angles(cls, theta: float, phi: float, z0: float) -> "Plane":
        """Plane from angle of incidence, azimuth (rad) and axis crossing ``z0`` (m)."""
        n = np.array([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        return cls(n, z0 * np.cos(theta))

    @classmethod
    def from_slopes(cls, a: float, b: float, z0: float) -> "Plane":
        """Plane ``z = z0 - a x - b y``, i.e. normal proportional to ``(a, b, 1)``."""
        s = float(np.sqrt(1.0 + a * a + b * b))
        return cls(np.array([a, b, 1.0]) / s, z0 / s)

    @property
    def slopes(self) -> tuple[float, float, float]:
        """``(a, b, z0)`` with ``n ~ (a, b, 1)``."""
        n = self.normal
        return float(n[0] / n[2]), float(n[1] / n[2]), self.z0

    def intersect(self, directions: np.ndarray) -> np.ndarray:
        """Points where rays from the origin along ``directions`` (..., 3) meet the plane (..., 3).

        Rays parallel to or pointing away from the plane give NaN.
        """
        dirs = np.asarray(directions, dtype=float)
        denom = dirs @ self.normal
        with np.errstate(divide="ignore", invalid="ignore"):
            t = np.where(denom > 1e-12, self.offset / denom, np.nan)
        return dirs * t[..., None]

    def to_dict(self) -> dict:
        return {"normal": [float(v) for v in self.normal], "offset": float(self.offset)}

    @classmethod
    def from_dict(cls, d: dict) -> "Plane":
        return cls(np.asarray(d["normal"], dtype=float), float(d["offset"]))


def fit_plane(points: np.ndarray, weights: np.ndarray | None = None) -> tuple[Plane, float]:
    """Least-squares plane through ``points`` (N, 3) by SVD of the centred, weighted points.

    Returns the plane and the weighted RMS perpendicular residual (m). Needs 3 or more
    non-collinear finite points.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 3)
    w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=float).reshape(-1)
    ok = np.all(np.isfinite(pts), axis=1) & np.isfinite(w) & (w > 0)
    pts, w = pts[ok], w[ok]
    if len(pts) < 3:
        raise NoPlaneError(f"a plane needs 3 or more valid points, got {len(pts)}")
    w = w / w.sum()
    centroid = w @ pts
    centred = (pts - centroid) * np.sqrt(w)[:, None]
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    if s[1] < 1e-9 * max(s[0], 1e-30):
        raise NoPlaneError("points are collinear; the plane is not determined")
    n = vt[-1]
    plane = Plane(n, float(n @ centroid))
    rms = float(s[-1])
    return plane, rms


#: Default tolerance of :func:`is_rotation` (largest entry of ``|R^T R - I|``): a transform computed in double
#: precision or read from a file with 15 or more significant digits.
ROTATION_TOL = 1e-6
_EYE3 = np.eye(3)
_LAST_ROW = np.array([0.0, 0.0, 0.0, 1.0])


def is_rotation(r: np.ndarray, tol: float = ROTATION_TOL) -> bool:
    """Whether the finite 3x3 array ``r`` is a proper rotation: orthonormal to ``tol`` (largest entry of
    ``|R^T R - I|``) and of positive determinant (the triple product: numpy's determinant costs 5 us, a
    noticeable share of reading a frame)."""
    if float(np.abs(r.T @ r - _EYE3).max()) > tol:
        return False
    (a, b, c), (d, e, f), (g, h, i) = r.tolist()
    return a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g) > 0


def finite_number(v: Any) -> float | None:
    """``v`` as a finite float, or None (bools, strings, NaN, inf, integers beyond any float and arrays are not
    numbers here): the one test of a time stamp, a force or a reading a robot, a clock or a frame hands over."""
    if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
        return None
    try:
        v = float(v)
    except OverflowError:  # an int too large for a float
        return None
    return v if math.isfinite(v) else None


#: m: no pose of the arm's flange, tool or sensor lies farther than this from its base along any axis (a UR5 reaches
#: 0.85 m, the largest UR 1.75 m). A pose beyond it is not a robot's: at 1e15 m a float's step is 0.125 m, and the
#: footprint's geometry collapsed there into a release over a table's edge (an adversarial round, session 73).
MAX_REACH = 2.0


def transform_problem(t: Any, tol: float = ROTATION_TOL, reach: float | None = None) -> str | None:
    """Why ``t`` is not a rigid 4x4 homogeneous transform (a phrase to follow its name), or None when it is:
    numbers, shape (4, 4), finite, a proper rotation block (:func:`is_rotation` to ``tol``) and the last row
    ``[0, 0, 0, 1]`` to 1e-9; with ``reach`` (m), a translation within it along every axis (a robot's pose in its
    base frame: :data:`MAX_REACH`). The one check of the robot's poses, its tool frames and the placement's
    robot states; callers raise their own error type with the name of what they checked."""
    try:
        m = np.asarray(t, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        return "is not a 4x4 matrix of numbers"
    if m.shape != (4, 4):
        return f"must be a 4x4 homogeneous matrix; got shape {m.shape}"
    if not np.all(np.isfinite(m)):
        return "is not a finite 4x4 transform (it contains NaN or inf)"
    if not is_rotation(m[:3, :3], tol):
        return "rotation part is not a proper rotation (R^T R != I or det < 0)"
    if float(np.abs(m[3] - _LAST_ROW).max()) > 1e-9:
        return f"last row must be [0, 0, 0, 1]; got {m[3].tolist()}"
    if reach is not None and float(np.abs(m[:3, 3]).max()) > reach:
        return f"translation {float(np.abs(m[:3, 3]).max()):.3g} m from the base is beyond any arm's reach (> {reach:g} m)"
    return None


def rotation_angle_between(n1: np.ndarray, n2: np.ndarray) -> float:
    """Angle between two unit vectors (rad), numerically safe near 0."""
    a = np.asarray(n1, dtype=float)
    b = np.asarray(n2, dtype=float)
    return float(np.arctan2(np.linalg.norm(np.cross(a, b)), np.dot(a, b)))


def plane_from_pose(pose: np.ndarray, dist_to_plane: float) -> Plane:
    """Ground-truth plane in the sensor frame from a sensor (or flange) pose in the base frame.

    The plane is horizontal in the base frame (normal +z there) at ``dist_to_plane`` from the
    sensor origin, as in the shared sweep: its normal in the sensor frame is ``R^T e_z`` up to sign.
    """
    T = np.asarray(pose, dtype=float).reshape(4, 4)
    n = T[:3, :3].T @ np.array([0.0, 0.0, 1.0])
    return Plane(n if n[2] > 0 else -n, float(dist_to_plane))
