"""Forward kinematics of the UR5 with gripper and TMF8820: joint angles -> poses in the robot base frame.

Concept: one :class:`Kinematics` object per robot description (URDF). It answers ``base_T_<frame>(q)`` for
the frames the placement pipeline needs, batched, in float64, using pytorch-kinematics over the URDF
generated from ``robots/ur5/config.json`` (imported lazily so ``place_safe`` imports without it).

Conventions
-----------
* Joint vector ``q``: 6 angles in radians, UR order ``shoulder_pan, shoulder_lift, elbow, wrist_1,
  wrist_2, wrist_3``, equal to the standard DH ``theta_i`` of the UR5 (no offsets), i.e. the angles the
  UR controller (and ur_rtde ``getActualQ``) reports.
* Base frame: DH frame 0 = the UR controller's base frame (z up through the shoulder axis). Note that
  ROS' ``base_link`` of the UR description is rotated by 180 deg about z from this frame.
* Frames (URDF link names): ``flange`` (DH frame 6, z out of the tool flange), ``tcp`` (between the
  fingertips), ``tof_sensor`` (TMF8820 frame: +z optical axis, x/y as in the zone table) and ``cup``
  (held cup frame: origin at the centre of its bottom, +z up through the opening).
* Poses are 4x4 homogeneous matrices ``base_T_frame`` mapping frame coordinates to base coordinates.
* Input ``q`` of shape (6,) gives (4, 4); shape (B, 6) gives (B, 4, 4). Numpy in, numpy out.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from place_safe.exceptions import RobotFault
from place_safe.robot.description import ur5_urdf_path

#: Frames :class:`Kinematics` knows by default (URDF link names).
FRAMES = ("flange", "tcp", "tof_sensor", "cup")
N_JOINTS = 6


def _default_urdf() -> Path:
    return ur5_urdf_path()


def check_joints(q: Any, n: int = N_JOINTS) -> tuple[np.ndarray, bool]:
    """Validate a joint vector or batch; return it as float64 (B, n) and whether it was a single vector.

    Raises ValueError for a wrong shape and RobotFault for non-finite angles (a sensor or driver fault).
    """
    try:
        arr = np.asarray(q, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"joint angles must be numbers of shape ({n},) or (B, {n}); got {q!r}") from exc
    single = arr.ndim == 1
    if single:
        arr = arr[None, :]
    if arr.ndim != 2 or arr.shape[1] != n:
        raise ValueError(f"joint angles must have shape ({n},) or (B, {n}); got {np.shape(q)}")
    if not np.all(np.isfinite(arr)):
        raise RobotFault(f"joint angles contain NaN or inf: {arr.tolist() if arr.size <= 12 else '...'}; "
                         "expected finite angles in radians")
    return arr, single


class Kinematics:
    """Forward kinematics and Jacobians from a URDF (default: the packaged UR5 + gripper + TMF8820).

    Parameters
    ----------
    urdf_path:
        URDF file; default :func:`place_safe.robot.description.ur5_urdf_path`.
    root:
        Root link (the base frame). Default ``base_link``.
    frames:
        Link names to build serial chains for (more are built on demand by :meth:`base_T`).
    """

    def __init__(self, urdf_path: str | Path | None = None, root: str = "base_link",
                 frames: tuple[str, ...] = FRAMES) -> None:
        self.urdf_path = Path(urdf_path) if urdf_path is not None else _default_urdf()
        if not self.urdf_path.is_file():
            raise FileNotFoundError(f"URDF not found: {self.urdf_path}")
        self._urdf = self.urdf_path.read_bytes()
        self.root = root
        self._chains: dict[str, Any] = {}
        for f in frames:
            self._chain(f)

    def _chain(self, link: str) -> Any:
        chain = self._chains.get(link)
        if chain is None:
            import pytorch_kinematics as pk  # lazy: optional dependency ([sim]/[hw] extras)
            import torch

            try:
                chain = pk.build_serial_chain_from_urdf(self._urdf, link, self.root)
            except Exception as exc:  # pk raises assorted errors for unknown links
                raise ValueError(f"cannot build a chain {self.root} -> {link} from {self.urdf_path}: {exc}") from exc
            chain = chain.to(dtype=torch.float64)
            n = len(chain.get_joint_parameter_names())
            if n != N_JOINTS:
                raise ValueError(f"chain {self.root} -> {link} has {n} joints; expected {N_JOINTS} (the arm)")
            self._chains[link] = chain
        return chain

    @property
    def joint_names(self) -> list[str]:
        return list(self._chain("flange").get_joint_parameter_names())

    def base_T(self, q: Any, link: str) -> np.ndarray:
        """Pose of ``link`` in the base frame: (4, 4) for q of shape (6,), (B, 4, 4) for (B, 6)."""
        import torch

        arr, single = check_joints(q)
        chain = self._chain(link)
        with torch.no_grad():
            T = chain.forward_kinematics(torch.from_numpy(arr)).get_matrix().numpy().copy()
        return T[0] if single else T

    def fk(self, q: Any) -> dict[str, np.ndarray]:
        """Poses of all default frames (``flange``, ``tcp``, ``tof_sensor``, ``cup``) in the base frame."""
        return {f: self.base_T(q, f) for f in FRAMES}

    def base_T_flange(self, q: Any) -> np.ndarray:
        return self.base_T(q, "flange")

    def base_T_tcp(self, q: Any) -> np.ndarray:
        return self.base_T(q, "tcp")

    def base_T_sensor(self, q: Any) -> np.ndarray:
        """Pose of the TMF8820 frame (+z optical axis) in the robot base frame."""
        return self.base_T(q, "tof_sensor")

    def base_T_cup(self, q: Any) -> np.ndarray:
        """Pose of the held cup frame (origin at the cup bottom, +z up out of the cup) in the base frame."""
        return self.base_T(q, "cup")

    def jacobian(self, q: Any, link: str = "tcp") -> np.ndarray:
        """Geometric Jacobian of ``link``'s origin in the base frame, rows (vx, vy, vz, wx, wy, wz).

        Shape (6, 6) for q of shape (6,), (B, 6, 6) for (B, 6).
        """
        import torch

        arr, single = check_joints(q)
        with torch.no_grad():
            J = self._chain(link).jacobian(torch.from_numpy(arr)).numpy().copy()
        return J[0] if single else J


__all__ = ["Kinematics", "FRAMES", "N_JOINTS", "check_joints"]
