"""The narrow robot interface the placement code drives (the real UR5 over ur-rtde, or MuJoCo).

Concept: a :class:`Robot` is what ur_rtde's ``RTDEControlInterface`` + ``RTDEReceiveInterface`` offer,
reduced to what placing a held object needs: read joints and poses, straight-line moves (moveL),
Cartesian velocity (speedL), stop, gripper, contact force, faults and a clock.

Conventions
-----------
* All poses are 4x4 homogeneous matrices in the robot base frame (DH frame 0, see
  :mod:`place_safe.robot.kinematics`): ``tcp_pose()`` is base_T_tcp, ``sensor_pose()`` is base_T_sensor
  (TMF8820 frame, +z optical axis).
* Twists are ``(vx, vy, vz, wx, wy, wz)`` of the TCP in the base frame, m/s and rad/s.
* Speeds in m/s, accelerations in m/s^2; the same numbers are used for rad/s and rad/s^2 of the
  orientation part (as URScript's movel/speedl do).
* Faults (protective stop on excessive contact force, joint limit, unreachable pose, lost connection)
  raise :class:`place_safe.exceptions.RobotFault`. A runtime fault is latched: the robot stops and keeps
  holding the object (the gripper is never opened on a fault), ``is_faulted()`` is True and further
  motion commands raise until ``clear_fault()``. A target rejected before any motion (unreachable,
  NaN) raises without latching and without moving.
* Time: ``time()`` is the robot clock in seconds; ``step(dt)`` lets ``dt`` seconds pass (the simulator
  advances physics, a real robot waits for the end of its control period). Blocking commands advance
  time themselves.
* Lifecycle: ``connect()`` opens the robot's connections (idempotent), ``disconnect()`` stops any
  motion and closes them (idempotent; it never opens the gripper). ``with robot:`` does both.
* Tool frames: ``tool`` (:class:`place_safe.robot.tool.ToolFrames`) holds ``flange_T_tcp``,
  ``flange_T_sensor`` and ``flange_T_cup`` from the robot's configuration. The placement pipeline
  computes the sensor and cup poses from ``tcp_pose()`` and ``tool``, never from a simulator's
  ground truth.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar

import numpy as np

from pydantic import Field, model_validator

from place_safe.config import ParamModel
from place_safe.exceptions import RobotFault
from place_safe.geometry import transform_problem
from place_safe.robot.tool import ToolFrames

_TWO_PI = 2.0 * math.pi


#: rad, one joint limit (a UR5-class joint turns at most two turns either way)
_JointLimit = Annotated[float, Field(ge=-4 * math.pi, le=4 * math.pi)]


class RobotLimits(ParamModel):
    """Motion and safety limits (SI units). Loadable from / saveable to JSON.

    Defaults: the UR5's joint ranges (+-2 pi, elbow +-pi) and joint speeds (about 180 deg/s) from the
    published UR5 data; Cartesian limits chosen for placing a cup (well under the UR5's 1 m/s tool speed).
    Every range is what a UR5-class arm can do at all; each joint's lower limit must be below its upper one.
    """

    what: ClassVar[str] = "robot limits"

    max_linear_speed: Annotated[float, Field(gt=0.0, le=3.0, description="m/s")] = 0.25  # TCP
    max_linear_accel: Annotated[float, Field(gt=0.0, le=50.0, description="m/s^2")] = 1.2
    max_angular_speed: Annotated[float, Field(gt=0.0, le=10.0, description="rad/s")] = 1.0  # TCP orientation
    max_angular_accel: Annotated[float, Field(gt=0.0, le=100.0, description="rad/s^2")] = 3.0
    max_joint_speed: Annotated[list[Annotated[float, Field(gt=0.0, le=10.0)]],
                               Field(min_length=6, max_length=6, description="rad/s")] = \
        Field(default_factory=lambda: [3.15, 3.15, 3.15, 3.2, 3.2, 3.2])
    joint_lower: Annotated[list[_JointLimit], Field(min_length=6, max_length=6, description="rad")] = \
        Field(default_factory=lambda: [-_TWO_PI, -_TWO_PI, -math.pi, -_TWO_PI, -_TWO_PI, -_TWO_PI])
    joint_upper: Annotated[list[_JointLimit], Field(min_length=6, max_length=6, description="rad")] = \
        Field(default_factory=lambda: [_TWO_PI, _TWO_PI, math.pi, _TWO_PI, _TWO_PI, _TWO_PI])
    # N, protective stop threshold on the gripper/held object
    max_contact_force: Annotated[float, Field(gt=0.0, le=1000.0, description="N")] = 60.0
    # m, path deviation that counts as a fault (singularity, blocked)
    max_tracking_error: Annotated[float, Field(gt=0.0, le=1.0, description="m")] = 0.02

    @model_validator(mode="after")
    def _lower_below_upper(self) -> "RobotLimits":
        if np.any(np.asarray(self.joint_lower) >= np.asarray(self.joint_upper)):
            raise ValueError("joint_lower must be below joint_upper for every joint")
        return self



def check_pose(pose: Any, what: str = "pose") -> np.ndarray:
    """Validate a 4x4 homogeneous transform; return it as float64. Raises ValueError otherwise."""
    if (why := transform_problem(pose)) is not None:
        raise ValueError(f"{what} {why}")
    return np.asarray(pose, dtype=np.float64)


def check_twist(twist: Any) -> np.ndarray:
    """Validate a 6-vector twist (m/s, rad/s). Raises ValueError otherwise."""
    v = np.asarray(twist, dtype=np.float64)
    if v.shape != (6,):
        raise ValueError(f"twist must have shape (6,) = (vx, vy, vz, wx, wy, wz); got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("twist contains NaN or inf; expected finite m/s and rad/s")
    return v


def stop_decel(requested: float, max_linear_accel: float, emergency_decel: float) -> float:
    """m/s^2 a stop asked at ``requested`` gets: as asked up to ``max_linear_accel``; a harder one is an
    emergency stop, at most ``emergency_decel`` (what the ur_rtde driver gives, and the simulated arm with it)."""
    return float(requested) if requested <= max_linear_accel else min(float(requested), emergency_decel)


def clamp_twist(v: np.ndarray, limits: RobotLimits) -> np.ndarray:
    """Scale a twist's linear and angular parts (in place) down to ``limits.max_linear_speed`` and
    ``max_angular_speed``, keeping their directions; returns ``v``."""
    nv, nw = float(np.linalg.norm(v[:3])), float(np.linalg.norm(v[3:]))
    if nv > limits.max_linear_speed:
        v[:3] *= limits.max_linear_speed / nv
    if nw > limits.max_angular_speed:
        v[3:] *= limits.max_angular_speed / nw
    return v


@dataclass(frozen=True)
class TrapezoidProfile:
    """Time-optimal trapezoidal (or triangular) speed profile over a distance, from rest to rest."""

    distance: float
    v_max: float
    a_max: float

    def __post_init__(self) -> None:
        if not (self.distance >= 0 and self.v_max > 0 and self.a_max > 0):
            raise ValueError(f"profile needs distance >= 0 and positive v_max, a_max; got {self}")

    @property
    def v_peak(self) -> float:
        return min(self.v_max, math.sqrt(self.distance * self.a_max))

    @property
    def t_accel(self) -> float:
        return self.v_peak / self.a_max

    @property
    def duration(self) -> float:
        if self.distance == 0:
            return 0.0
        vp, ta = self.v_peak, self.t_accel
        return 2 * ta + (self.distance - vp * ta) / vp

    def at(self, t: float) -> tuple[float, float]:
        """(position, speed) at time t (clamped to [0, duration])."""
        T, ta, vp, a = self.duration, self.t_accel, self.v_peak, self.a_max
        if t <= 0 or T == 0:
            return 0.0, 0.0
        if t >= T:
            return self.distance, 0.0
        if t < ta:
            return 0.5 * a * t * t, a * t
        if t <= T - ta:
            return 0.5 * a * ta * ta + vp * (t - ta), vp
        r = T - t
        return self.distance - 0.5 * a * r * r, a * r


class Robot(ABC):
    """A 6-axis arm with a parallel gripper and a wrist TMF8820 (see the module docstring)."""

    limits: RobotLimits
    _tool: ToolFrames | None = None

    # --- lifecycle ----------------------------------------------------------------------------
    def connect(self) -> None:
        """Open the robot's connections (idempotent). In-process robots are always connected."""

    def disconnect(self) -> None:
        """Stop any motion and close the connections (idempotent). Never opens the gripper."""

    def is_connected(self) -> bool:
        """Whether commands can reach the robot."""
        return True

    def close(self) -> None:
        """Same as :meth:`disconnect`."""
        self.disconnect()

    def __enter__(self) -> "Robot":
        self.connect()
        return self

    def __exit__(self, *exc: Any) -> None:
        self.disconnect()

    # --- tool frames --------------------------------------------------------------------------
    @property
    def tool(self) -> ToolFrames:
        """The tool frames from configuration (default: the packaged UR5 gripper, sensor mount and cup)."""
        if self._tool is None:
            self._tool = ToolFrames.ur5_default()
        return self._tool

    @tool.setter
    def tool(self, value: ToolFrames) -> None:
        if not isinstance(value, ToolFrames):
            raise TypeError(f"tool must be a ToolFrames, got {type(value).__name__}")
        self._tool = value

    # --- state --------------------------------------------------------------------------------
    @abstractmethod
    def joint_positions(self) -> np.ndarray:
        """Actual joint angles, shape (6,), radians."""

    @abstractmethod
    def tcp_pose(self) -> np.ndarray:
        """Actual base_T_tcp (4x4)."""

    def sensor_pose(self) -> np.ndarray:
        """base_T_sensor (4x4, TMF8820 frame with +z the optical axis) from the TCP pose and the
        configured tool frames."""
        return self.tcp_pose() @ self.tool.tcp_T_sensor

    @abstractmethod
    def tcp_twist(self) -> np.ndarray:
        """Actual TCP twist (6,) in the base frame (m/s, rad/s)."""

    @abstractmethod
    def contact_force(self) -> float:
        """Magnitude (N) of the net force the environment exerts on the held object and the gripper."""

    def contact_latency(self) -> float | None:
        """s: how late the contact detector behind :meth:`contact_force` reports a 10 N touch (95th percentile) at
        the force noise it measured at rest; None when the robot cannot say (the placement then keeps its
        ``contact_latency``). A placement loop made for this robot uses the longer of the two."""
        return None

    @abstractmethod
    def time(self) -> float:
        """Robot clock (s)."""

    # --- motion -------------------------------------------------------------------------------
    @abstractmethod
    def move_linear(self, pose: Any, speed: float = 0.05, accel: float = 0.2,
                    asynchronous: bool = False) -> None:
        """Straight-line TCP move to ``pose`` (base_T_tcp) with a trapezoidal speed profile (moveL).

        Blocking unless ``asynchronous``; then the motion proceeds as time passes (``step``) and
        ``is_moving()`` tells when it is done. ``speed``/``accel`` above ``limits`` are clamped to them.
        Raises ValueError for a malformed pose, speed or acceleration and RobotFault if the pose is
        unreachable (checked before moving; nothing moves) or a fault occurs on the way.
        """

    def move_joint(self, q: Any, speed: float = 1.05, accel: float = 1.4, asynchronous: bool = False) -> None:
        """Joint-space move to ``q`` (6 rad) with a synchronised trapezoidal profile (moveJ; rad/s,
        rad/s^2). Optional for implementations: the default raises NotImplementedError."""
        raise NotImplementedError(f"{type(self).__name__} does not implement move_joint")

    @abstractmethod
    def speed_linear(self, twist: Any, accel: float = 0.5, duration: float | None = None) -> None:
        """Move the TCP at ``twist`` (base frame), ramping with ``accel`` (speedL).

        ``duration=None``: non-blocking, the velocity holds until another command or ``stop``.
        ``duration=T``: blocking, holds the velocity for T seconds and then decelerates to rest.
        Speeds above the limits are scaled down to them.
        """

    @abstractmethod
    def stop(self, decel: float = 1.0, asynchronous: bool = False) -> None:
        """Decelerate the TCP to rest at ``decel`` (stopL); blocking unless ``asynchronous``."""

    @abstractmethod
    def is_moving(self) -> bool:
        """True while a commanded motion is in progress."""

    @abstractmethod
    def step(self, dt: float) -> None:
        """Let ``dt`` seconds pass (servicing motion, safety checks and, in simulation, physics)."""

    # --- gripper and faults --------------------------------------------------------------------
    @abstractmethod
    def gripper(self, open: bool) -> None:
        """Open (release the held object) or close the gripper. Never called by the robot on a fault."""

    @abstractmethod
    def fault(self) -> str | None:
        """The latched fault message, or None."""

    def is_faulted(self) -> bool:
        return self.fault() is not None

    @abstractmethod
    def clear_fault(self) -> None:
        """Acknowledge a latched fault (like unlocking a protective stop)."""



__all__ = ["Robot", "ToolFrames", "RobotLimits", "TrapezoidProfile", "check_pose", "check_twist", "clamp_twist", "RobotFault"]
