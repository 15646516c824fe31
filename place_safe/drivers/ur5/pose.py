"""UR pose vectors <-> 4x4 transforms.

The UR controller (and ur_rtde) writes a pose as ``[x, y, z, rx, ry, rz]``: position in metres and the
rotation as an axis-angle vector (radians), both in the base frame. Everything else in place_safe uses
4x4 homogeneous matrices; these two functions are the only conversion.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation


def pose_to_vector(T: Any) -> list[float]:
    """4x4 transform -> UR pose ``[x, y, z, rx, ry, rz]`` (m, axis-angle rad)."""
    M = np.asarray(T, dtype=float)
    return [float(v) for v in (*M[:3, 3], *Rotation.from_matrix(M[:3, :3]).as_rotvec())]


def vector_to_pose(p: Any) -> np.ndarray:
    """UR pose ``[x, y, z, rx, ry, rz]`` -> 4x4 transform; ValueError for anything else."""
    v = np.asarray(p, dtype=float)
    if v.shape != (6,) or not np.all(np.isfinite(v)):
        raise ValueError(f"a UR pose is 6 finite numbers [x, y, z, rx, ry, rz]; got {p!r}")
    T = np.eye(4)
    T[:3, :3] = Rotation.from_rotvec(v[3:]).as_matrix()
    T[:3, 3] = v[:3]
    return T


__all__ = ["pose_to_vector", "vector_to_pose"]
