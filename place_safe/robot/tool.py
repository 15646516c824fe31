"""Tool frames: where the sensor and the held object sit relative to the robot's flange.

Concept: a :class:`ToolFrames` is the fixed geometry a placement needs besides the arm's own
kinematics: ``flange_T_tcp`` (tool centre point), ``flange_T_sensor`` (the TMF8820: +z its optical
axis, x/y as in the zone table) and ``flange_T_cup`` (the held cup: origin at the centre of its bottom,
+z up out of the cup). It comes from the robot configuration (``robots/ur5/config.json`` or a user's
robot file after ``place-safe calibrate-mount``), never from a simulator's ground truth, so the
simulation exercises the same mount errors a real arm has.

Conventions: 4x4 homogeneous matrices ``a_T_b`` map b-coordinates to a-coordinates; metres, radians.
Rotations given as ``rpy`` are fixed-axis roll-pitch-yaw (x, then y, then z), as in URDF.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from place_safe.exceptions import ConfigError
from place_safe.geometry import transform_problem
from place_safe.robot.description import ur5_config


def pose_from_xyz_rpy(xyz: Any, rpy: Any = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 transform from a translation (m) and fixed-axis roll-pitch-yaw (rad)."""
    from scipy.spatial.transform import Rotation

    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", np.asarray(rpy, dtype=float)).as_matrix()
    T[:3, 3] = np.asarray(xyz, dtype=float)
    return T


def check_transform(T: Any, what: str) -> np.ndarray:
    """``T`` as a float64 rigid 4x4 transform; raises ConfigError naming ``what`` otherwise."""
    if (why := transform_problem(T)) is not None:
        raise ConfigError(f"{what} {why}")
    return np.array(T, dtype=np.float64)


@dataclass(frozen=True)
class ToolFrames:
    """Fixed frames on the flange (see module docstring). Construct with :meth:`from_robot_config` or
    :meth:`ur5_default`; the matrices are validated rigid transforms."""

    flange_T_tcp: np.ndarray
    flange_T_sensor: np.ndarray
    flange_T_cup: np.ndarray

    def __post_init__(self) -> None:
        for name in ("flange_T_tcp", "flange_T_sensor", "flange_T_cup"):
            object.__setattr__(self, name, check_transform(getattr(self, name), f"tool frame {name}"))

    @property
    def tcp_T_sensor(self) -> np.ndarray:
        return np.linalg.inv(self.flange_T_tcp) @ self.flange_T_sensor

    @property
    def tcp_T_cup(self) -> np.ndarray:
        return np.linalg.inv(self.flange_T_tcp) @ self.flange_T_cup

    def with_sensor(self, flange_T_sensor: Any) -> "ToolFrames":
        """The same tool with another sensor mount (e.g. from ``calibrate-mount``)."""
        return ToolFrames(self.flange_T_tcp, np.asarray(flange_T_sensor, dtype=float), self.flange_T_cup)

    @classmethod
    def from_robot_config(cls, cfg: dict[str, Any]) -> "ToolFrames":
        """From a robot description dict shaped like ``robots/ur5/config.json`` (keys ``gripper.tcp_xyz``,
        ``sensor.flange_T_sensor_xyz/rpy``, ``cup.flange_T_cup_xyz/rpy``)."""
        try:
            tcp = pose_from_xyz_rpy(cfg["gripper"]["tcp_xyz"])
            sensor = pose_from_xyz_rpy(cfg["sensor"]["flange_T_sensor_xyz"], cfg["sensor"]["flange_T_sensor_rpy"])
            cup = pose_from_xyz_rpy(cfg["cup"]["flange_T_cup_xyz"], cfg["cup"]["flange_T_cup_rpy"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ConfigError(f"robot configuration lacks a valid tool frame ({exc})") from None
        return cls(tcp, sensor, cup)

    @classmethod
    def ur5_default(cls) -> "ToolFrames":
        """The packaged UR5 gripper, TMF8820 mount and cup (``robots/ur5/config.json``)."""
        return cls.from_robot_config(ur5_config())

    def to_dict(self) -> dict[str, list[list[float]]]:
        return {k: np.asarray(getattr(self, k)).tolist() for k in ("flange_T_tcp", "flange_T_sensor", "flange_T_cup")}


__all__ = ["ToolFrames", "pose_from_xyz_rpy", "check_transform"]
