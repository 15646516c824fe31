"""A kinematic UR5: the :class:`~place_safe.robot.interface.Robot` interface without physics, for CI stand-ins.

Concept: :class:`KinematicArm` moves the joint angles of the UR5 (forward kinematics and Jacobians from
:class:`place_safe.robot.kinematics.Kinematics`) along the reference motion a UR controller would
follow -- moveL with a trapezoidal profile, moveJ, speedL ramped at the commanded acceleration, stopL --
with ideal servo tracking, one resolved-rate step per controller cycle. Optional contact with one plane
(``contact_plane``) gives a spring force on chosen points of the tool; above
``limits.max_contact_force`` the arm protective-stops (latched, gripper untouched), like the real one.
It is what :class:`~place_safe.drivers.ur5.fake_rtde.FakeUR` moves when MuJoCo is not wanted.

Conventions: as :mod:`place_safe.robot.interface` (base frame, SI units, TCP twists in the base frame).
The TCP and sensor are the URDF's ``tcp`` / ``tof_sensor`` links (the packaged tool frames).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from place_safe.exceptions import RobotFault
from place_safe.robot.interface import Robot, RobotLimits, TrapezoidProfile, check_pose, check_twist, clamp_twist
from place_safe.robot.description import ur5_config
from place_safe.robot.kinematics import Kinematics

_GAIN_PER_S = 20.0  # Cartesian error feedback of the resolved-rate loop (1/s)
_DLS = 1e-6  # damped least squares lambda^2


def _rotvec(R: np.ndarray) -> np.ndarray:
    return Rotation.from_matrix(R).as_rotvec()


def _rotm(w: np.ndarray) -> np.ndarray:
    return Rotation.from_rotvec(w).as_matrix()


class KinematicArm(Robot):
    """A UR5 without dynamics (see module docstring).

    ``q_init``: start joints (default the packaged home, tool pointing down). ``period``: controller
    cycle (s). ``contact_plane``: ``(n, d)`` in the base frame (``n . x = d``, n pointing to free space) or
    None. ``contact_points``: points in the TCP frame that can touch it (default the TCP itself).
    ``stiffness``: N/m of the contact spring.
    """

    def __init__(self, q_init: Any = None, *, limits: RobotLimits | None = None, period: float = 0.008,
                 kinematics: Any = None, contact_plane: tuple[Any, float] | None = None,
                 contact_points: Any = ((0.0, 0.0, 0.0),), stiffness: float = 20000.0) -> None:
        self.kin = kinematics if kinematics is not None else Kinematics()
        self.limits = limits if limits is not None else RobotLimits()
        self.period = float(period)
        self.q = np.asarray(ur5_config()["arm"]["home"] if q_init is None else q_init, dtype=float).copy()
        self.qd = np.zeros(6)
        self._t = 0.0
        self._mode: str | None = None
        self._motion: dict[str, Any] = {}
        self._twist = np.zeros(6)
        self._fault: str | None = None
        self._gripper_open = False
        self.contact_plane = None
        if contact_plane is not None:
            n = np.asarray(contact_plane[0], dtype=float)
            self.contact_plane = (n / np.linalg.norm(n), float(contact_plane[1]))
        self.contact_points = np.asarray(contact_points, dtype=float).reshape(-1, 3)
        self.stiffness = float(stiffness)
        self._T = self.kin.base_T(self.q, "tcp")
        self._sensor_T = np.linalg.inv(self._T) @ self.kin.base_T(self.q, "tof_sensor")

    # --- state ----------------------------------------------------------------------------------
    def joint_positions(self) -> np.ndarray:
        return self.q.copy()

    def tcp_pose(self) -> np.ndarray:
        return self._T.copy()

    def sensor_pose(self) -> np.ndarray:
        return self._T @ self._sensor_T

    def tcp_twist(self) -> np.ndarray:
        return self._twist.copy()

    def contact_vector(self) -> np.ndarray:
        """Force (N) the plane exerts on the tool, base frame (zero without contact)."""
        if self.contact_plane is None:
            return np.zeros(3)
        n, d = self.contact_plane
        pts = (self._T[:3, :3] @ self.contact_points.T).T + self._T[:3, 3]
        pen = np.clip(d - pts @ n, 0.0, None)
        return self.stiffness * float(pen.sum()) * n

    def contact_force(self) -> float:
        return float(np.linalg.norm(self.contact_vector()))

    def time(self) -> float:
        return self._t

    def fault(self) -> str | None:
        return self._fault

    def clear_fault(self) -> None:
        self._fault = None

    def protective_stop(self, why: str) -> None:
        """Halt at once and latch ``why`` (the gripper is not touched)."""
        self._mode, self._motion = None, {}
        self._twist[:] = 0.0
        self.qd[:] = 0.0
        self._fault = why

    def gripper(self, open: bool) -> None:
        self._gripper_open = bool(open)

    def gripper_is_open(self) -> bool:
        return self._gripper_open

    def is_moving(self) -> bool:
        return self._mode is not None

    # --- commands -------------------------------------------------------------------------------
    def _require_ok(self) -> None:
        if self._fault is not None:
            raise RobotFault(f"robot is faulted ({self._fault}); clear the fault first")

    def move_linear(self, pose: Any, speed: float = 0.05, accel: float = 0.2, asynchronous: bool = False) -> None:
        goal = check_pose(pose, "move_linear target")
        self._require_ok()
        lim = self.limits
        v, a = min(float(speed), lim.max_linear_speed), min(float(accel), lim.max_linear_accel)
        if not (v > 0 and a > 0):
            raise ValueError("speed and accel must be positive")
        start = self._T.copy()
        dp = goal[:3, 3] - start[:3, 3]
        rv = _rotvec(goal[:3, :3] @ start[:3, :3].T)
        # one profile in "path units": the leading of translation (m) and rotation (rad / angular limits)
        lin, ang = float(np.linalg.norm(dp)), float(np.linalg.norm(rv))
        scale = max(lin / v, ang / lim.max_angular_speed, 1e-12)
        prof = TrapezoidProfile(1.0, 1.0 / scale, a / max(lin, ang * a / lim.max_angular_accel, 1e-12))
        self._mode = "linear"
        self._motion = {"start": start, "dp": dp, "rv": rv, "prof": prof, "t0": self._t}
        if not asynchronous:
            self._run_until_idle(prof.duration + 1.0)

    def move_joint(self, q: Any, speed: float = 1.05, accel: float = 1.4, asynchronous: bool = False) -> None:
        goal = np.asarray(q, dtype=float)
        if goal.shape != (6,) or not np.all(np.isfinite(goal)):
            raise ValueError(f"move_joint target must be 6 finite joint angles (rad); got {q!r}")
        self._require_ok()
        lo, hi = np.asarray(self.limits.joint_lower), np.asarray(self.limits.joint_upper)
        if np.any(goal < lo) or np.any(goal > hi):
            raise RobotFault("move_joint target outside the joint limits")
        span = float(np.abs(goal - self.q).max())
        prof = TrapezoidProfile(1.0, float(speed) / max(span, 1e-12), float(accel) / max(span, 1e-12))
        self._mode = "joint"
        self._motion = {"start": self.q.copy(), "dq": goal - self.q, "prof": prof, "t0": self._t}
        if not asynchronous:
            self._run_until_idle(prof.duration + 1.0)

    def speed_linear(self, twist: Any, accel: float = 0.5, duration: float | None = None) -> None:
        v = check_twist(twist)
        self._require_ok()
        lim = self.limits
        clamp_twist(v, lim)
        if self._mode in ("linear", "joint"):
            self._twist[:] = 0.0
        self._mode = "speed"
        self._motion = {"target": v, "accel": min(float(accel), lim.max_linear_accel), "ref": self._T.copy()}
        if duration is not None:
            self.step(duration)
            self.stop(decel=accel)

    def stop(self, decel: float = 1.0, asynchronous: bool = False) -> None:
        if self._mode is None:
            return
        if self._mode != "speed":
            self._mode = "speed"
            self._motion = {"ref": self._T.copy()}
        self._motion.update(target=np.zeros(6), accel=float(decel), stopping=True)
        if not asynchronous:
            self._run_until_idle(float(np.abs(self._twist).max()) / float(decel) + 1.0)

    def step(self, dt: float) -> None:
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0; got {dt!r}")
        n = max(1, int(round(dt / self.period)))
        for _ in range(n):
            self._tick()

    def _run_until_idle(self, timeout: float) -> None:
        t_end = self._t + timeout
        while self._mode is not None:
            if self._t > t_end:
                self.protective_stop(f"motion did not finish within {timeout:.1f} s")
                raise RobotFault(self._fault)
            self._tick()
            if self._fault is not None:
                raise RobotFault(self._fault)

    # --- one controller cycle -----------------------------------------------------------------------
    def _reference(self, t: float) -> tuple[np.ndarray, np.ndarray] | None:
        mo = self._motion
        if self._mode == "linear":
            s, sd = mo["prof"].at(t - mo["t0"])
            T = np.eye(4)
            T[:3, 3] = mo["start"][:3, 3] + s * mo["dp"]
            T[:3, :3] = _rotm(s * mo["rv"]) @ mo["start"][:3, :3]
            if t - mo["t0"] >= mo["prof"].duration:
                self._mode, self._motion = None, {}
            return T, np.concatenate([sd * mo["dp"], sd * mo["rv"]])
        if self._mode == "speed":
            h = self.period
            diff = mo["target"] - self._twist
            step = mo["accel"] * h
            nd = max(np.linalg.norm(diff[:3]), np.linalg.norm(diff[3:]))
            tw = mo["target"].copy() if nd <= step else self._twist + diff * (step / nd)
            T = mo["ref"].copy()
            T[:3, 3] += tw[:3] * h
            T[:3, :3] = _rotm(tw[3:] * h) @ T[:3, :3]
            mo["ref"] = T
            if mo.get("stopping") and not np.any(tw):
                self._mode, self._motion = None, {}
            return T, tw
        return None

    def _tick(self) -> None:
        h = self.period
        self._t += h
        if self._mode == "joint":
            mo = self._motion
            s, sd = mo["prof"].at(self._t - mo["t0"])
            self.q = mo["start"] + s * mo["dq"]
            self.qd = sd * mo["dq"]
            if self._t - mo["t0"] >= mo["prof"].duration:
                self._mode, self._motion = None, {}
            T_new = self.kin.base_T(self.q, "tcp")
            self._twist = np.zeros(6) if self._mode is None else self._twist_between(self._T, T_new, h)
            self._T = T_new
        else:
            ref = self._reference(self._t)
            if ref is None:
                self._twist[:] = 0.0
                self.qd[:] = 0.0
            else:
                T_ref, v_ref = ref
                J = self.kin.jacobian(self.q, "tcp")
                e = np.concatenate([T_ref[:3, 3] - self._T[:3, 3], _rotvec(T_ref[:3, :3] @ self._T[:3, :3].T)])
                w = v_ref + _GAIN_PER_S * e if self._mode is not None else e / h
                qd = J.T @ np.linalg.solve(J @ J.T + _DLS * np.eye(6), w)
                scale = float(np.max(np.abs(qd) / np.asarray(self.limits.max_joint_speed)))
                if scale > 1.0:
                    self.protective_stop(f"joint speed limit: the path needs {scale:.1f}x the joint speed limit "
                                         "(singularity or workspace edge)")
                    return
                q_new = self.q + qd * h
                lo, hi = np.asarray(self.limits.joint_lower), np.asarray(self.limits.joint_upper)
                if np.any(q_new < lo) or np.any(q_new > hi):
                    self.protective_stop("joint limit reached")
                    return
                self.q, self.qd = q_new, qd
                self._T = self.kin.base_T(self.q, "tcp")
                self._twist = v_ref.copy()
        f = self.contact_force()
        if f > self.limits.max_contact_force:
            self.protective_stop(f"protective stop: contact force {f:.1f} N exceeds {self.limits.max_contact_force:.1f} N")

    @staticmethod
    def _twist_between(A: np.ndarray, B: np.ndarray, h: float) -> np.ndarray:
        return np.concatenate([(B[:3, 3] - A[:3, 3]) / h, _rotvec(B[:3, :3] @ A[:3, :3].T) / h])


__all__ = ["KinematicArm"]
