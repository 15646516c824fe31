"""Motion of the simulated UR5 as the UR controller makes it: joint position servos (gravity-compensated arm,
PD with velocity feed-forward through the position actuators) under a Cartesian loop that follows a reference
TCP trajectory by damped-least-squares differential IK on MuJoCo site Jacobians, closed on the commanded
joints; straight-line moves are planned (IK along the line within the joint limits) before they start.

Modes: ``None`` (holding), ``"linear"`` (moveL along a trapezoidal profile), ``"joint"`` (moveJ), ``"speed"``
(speedL; a stop is a speed move to zero twist). SI units: m, rad, s; poses and twists in the robot base frame.
"""

from __future__ import annotations

import math
from typing import Any, Callable, NoReturn

import mujoco
import numpy as np

from place_safe.exceptions import RobotFault
from place_safe.robot.interface import RobotLimits, TrapezoidProfile
from place_safe.sim.arm_model import ArmModel, exp_rot, log_rot
from place_safe.sim.robot_model import ARM_JOINTS

# Control constants (units in the names).
_CART_GAIN_PER_S = 15.0  # Cartesian error feedback (1/s), below the ~50 rad/s servo bandwidth
_DLS_DAMPING = 1e-3  # damped least squares lambda (m), only matters near singularities
_IK_TOL_M = 1e-5  # planning IK position tolerance
_IK_TOL_RAD = 1e-4  # planning IK orientation tolerance
_DLS_EYE = _DLS_DAMPING**2 * np.eye(6)
_PLAN_STEP_M = 0.005  # path sampling for reachability checks
_PLAN_STEP_RAD = 0.05
_SETTLE_TOL_M = 2e-4  # end of move: position error
_SETTLE_TOL_RAD = 2e-3
SETTLE_MAX_S = 1.0  # the longest a move settles after its profile ends
_SETTLE_TOL_JOINT_RAD = 2e-4
_JOINT_TRACKING_FAULT_RAD = 0.1


def outside_limits(q: np.ndarray, limits: RobotLimits) -> tuple[int, float, float] | None:
    """(joint index, lower, upper) of the first joint of ``q`` outside ``limits``, or None."""
    lo, hi = np.asarray(limits.joint_lower), np.asarray(limits.joint_upper)
    bad = np.flatnonzero((q < lo) | (q > hi))
    if not bad.size:
        return None
    j = int(bad[0])
    return j, float(lo[j]), float(hi[j])


class ArmMotion:
    """The controller's motion state and its control tick. ``limits()`` gives the robot's current limits;
    ``fault(message)`` latches a fault and raises (it never returns)."""

    def __init__(self, arm: ArmModel, ticks_per_control: int, limits: Callable[[], RobotLimits],
                 fault: Callable[[str], NoReturn]) -> None:
        self.arm = arm
        self.ticks_per_control = ticks_per_control
        self._limits, self._fault = limits, fault
        self.tick_left = 0
        self.mode: str | None = None
        self.motion: dict[str, Any] = {}
        self.ref_twist = np.zeros(6)
        self.q_cmd = np.zeros(6)
        self.qd_cmd = np.zeros(6)

    def time(self) -> float:
        return float(self.arm.data.time)

    # servo command -------------------------------------------------------------------------------
    def apply_ctrl(self) -> None:
        # PD with velocity feed-forward through the position actuator:
        # kp (q_cmd + kv/kp qd_cmd - q) - kv qd = kp (q_cmd - q) + kv (qd_cmd - qd)
        self.arm.data.ctrl[self.arm.act] = self.q_cmd + self.arm.kv_over_kp * self.qd_cmd

    def hold(self, q: np.ndarray) -> None:
        """End any motion and servo at ``q`` at rest."""
        self.q_cmd = q.copy()
        self.qd_cmd[:] = 0.0
        self.mode, self.motion = None, {}
        self.ref_twist[:] = 0.0
        self.apply_ctrl()

    def finish(self) -> None:
        self.arm.data.qfrc_applied[self.arm.vadr] = 0.0
        self.mode, self.motion = None, {}
        self.ref_twist[:] = 0.0
        self.qd_cmd[:] = 0.0
        self.apply_ctrl()

    def set_feedforward(self, qd_new: np.ndarray, dt: float) -> None:
        """Inertial feed-forward torque M(q) qdd for the change of joint velocity over one control tick
        (what the UR controller adds to its servo loop); without it the servos lag on accelerating and
        overshoot the commanded speed."""
        m, d, vadr = self.arm.model, self.arm.data, self.arm.vadr
        qdd = (qd_new - self.qd_cmd) / dt
        vec = np.zeros(m.nv)
        vec[vadr] = qdd
        res = np.zeros(m.nv)
        mujoco.mj_mulM(m, d, res, vec)
        d.qfrc_applied[vadr] = res[vadr]

    # planning: reachability of a straight line ------------------------------------------------------
    def ik_point(self, q: np.ndarray, target: np.ndarray, iters: int = 50) -> tuple[np.ndarray, float, float]:
        """DLS IK on the scratch data from ``q`` to base_T_tcp ``target``; returns (q, pos err, rot err)."""
        arm = self.arm
        m, d = arm.model, arm.scratch
        d.qpos[:] = arm.data.qpos
        q = q.copy()
        max_step = 0.2  # rad per iteration
        ep = er = math.inf
        for _ in range(iters):
            d.qpos[arm.qadr] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            T = arm.base_T_site(arm.tcp, d)
            e = np.concatenate([target[:3, 3] - T[:3, 3], log_rot(target[:3, :3] @ T[:3, :3].T)])
            ep, er = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
            if ep < _IK_TOL_M and er < _IK_TOL_RAD:
                break
            J = arm.jac_base(d)
            dq = J.T @ np.linalg.solve(J @ J.T + _DLS_EYE, e)
            s = np.abs(dq).max()
            if s > max_step:
                dq *= max_step / s
            q = q + dq
        return q, ep, er

    def plan_line(self, start: np.ndarray, goal: np.ndarray) -> None:
        """Check a straight TCP line is followable: IK converges along it within joint limits (RobotFault)."""
        dp = goal[:3, 3] - start[:3, 3]
        rv = log_rot(goal[:3, :3] @ start[:3, :3].T)
        n = max(1, int(math.ceil(max(np.linalg.norm(dp) / _PLAN_STEP_M, np.linalg.norm(rv) / _PLAN_STEP_RAD))))
        q = self.arm.data.qpos[self.arm.qadr].copy()
        for k in range(1, n + 1):
            s = k / n
            T = np.eye(4)
            T[:3, 3] = start[:3, 3] + s * dp
            T[:3, :3] = exp_rot(s * rv) @ start[:3, :3]
            q_new, ep, er = self.ik_point(q, T)
            if ep > 1e-4 or er > 1e-3:
                raise RobotFault(
                    f"target pose unreachable by a straight line: IK fails at {100 * s:.0f}% of the path "
                    f"(position error {1000 * ep:.1f} mm, orientation error {math.degrees(er):.2f} deg) at "
                    f"TCP position {np.round(T[:3, 3], 4).tolist()} m in the base frame")
            if (out := outside_limits(q_new, self._limits())) is not None:
                j, lo, hi = out
                raise RobotFault(f"target pose needs joint {ARM_JOINTS[j]} at {q_new[j]:.3f} rad, outside "
                                 f"[{lo:.3f}, {hi:.3f}] rad")
            if np.abs(q_new - q).max() > 0.5:
                raise RobotFault("target pose unreachable by a straight line: the path crosses a singularity "
                                 f"(joint jump of {np.abs(q_new - q).max():.2f} rad at {100 * s:.0f}% of the path)")
            q = q_new

    # starting a motion (the caller has checked the arguments and stopped a motion that must end first) -------
    def start_linear(self, goal: np.ndarray, speed: float, accel: float) -> float:
        """Plan and start a moveL to ``goal`` at ``speed``/``accel`` (already within the limits); returns its
        profile's duration (s)."""
        lim = self._limits()
        start = self.reference_pose()
        self.plan_line(start, goal)
        dp = goal[:3, 3] - start[:3, 3]
        rv = log_rot(goal[:3, :3] @ start[:3, :3].T)
        L, A = float(np.linalg.norm(dp)), float(np.linalg.norm(rv))
        # normalised path parameter s in [0, 1]; both the linear and the angular part obey the limits
        v_s = min(speed / L if L > 0 else math.inf,
                  min(speed, lim.max_angular_speed) / A if A > 0 else math.inf)
        a_s = min(accel / L if L > 0 else math.inf,
                  min(accel, lim.max_angular_accel) / A if A > 0 else math.inf)
        # already there: an empty profile (the move only settles)
        prof = TrapezoidProfile(1.0, v_s, a_s) if math.isfinite(v_s) else TrapezoidProfile(0.0, 1.0, 1.0)
        self.mode = "linear"
        self.motion = {"start": start, "goal": goal, "dp": dp, "rv": rv, "profile": prof,
                       "t0": self.time(), "settle": 0.0}
        self.tick_left = 0
        return prof.duration

    def start_joint(self, goal: np.ndarray, speed: float, accel: float) -> float:
        """Start a moveJ from the commanded joints to ``goal``; returns its profile's duration (s)."""
        start = self.q_cmd.copy()
        dq = goal - start
        vmax = np.minimum(float(speed), np.asarray(self._limits().max_joint_speed))
        span = np.abs(dq)
        moving = span > 0
        v_s = float(np.min(vmax[moving] / span[moving])) if moving.any() else math.inf
        a_s = float(np.min(float(accel) / span[moving])) if moving.any() else math.inf
        prof = TrapezoidProfile(1.0, v_s, a_s) if math.isfinite(v_s) else TrapezoidProfile(0.0, 1.0, 1.0)
        self.mode = "joint"
        self.motion = {"start": start, "dq": dq, "goal": goal, "profile": prof, "t0": self.time(),
                       "settle": 0.0}
        self.tick_left = 0
        return prof.duration

    def start_speed(self, twist: np.ndarray, accel: float) -> None:
        """Start a speedL toward ``twist`` (already clamped), ramping at ``accel``."""
        ref = self.reference_pose()
        self.mode = "speed"
        self.motion = {"target": twist, "accel": accel, "ref": ref, "t_last": self.time()}
        self.tick_left = 0

    def start_stop(self, decel: float) -> float:
        """Start decelerating to rest at ``decel`` (a joint move continues from its joint velocity, decelerating
        in Cartesian space); returns the longest it may take (s)."""
        if self.mode == "joint":
            sd = self.arm.at_joints(self.q_cmd)
            self.ref_twist = self.arm.jac_base(sd) @ self.qd_cmd
            ref = self.arm.base_T_site(self.arm.tcp, sd)
        else:
            ref = self.reference_pose()
        self.mode = "speed"
        self.motion = {"target": np.zeros(6), "accel": float(decel), "ref": ref, "stopping": True,
                       "t_last": self.time()}
        self.tick_left = 0
        return np.abs(self.ref_twist).max() / decel + 2.0

    # the reference ------------------------------------------------------------------------------------
    def reference_pose(self) -> np.ndarray:
        """Where the Cartesian reference is now (continuing a motion smoothly), else the actual TCP."""
        if self.mode == "linear":
            return self.linear_ref(self.time())[0]
        if self.mode == "speed":
            return self.speed_ref(self.time())
        if self.mode == "joint":
            raise RobotFault("a joint move is in progress; stop() it before a Cartesian command")
        return self.arm.base_T_site(self.arm.tcp)

    def speed_ref(self, t: float) -> np.ndarray:
        """Reference pose in speed mode: last tick's reference moved on by the reference twist."""
        mo = self.motion
        el = t - mo["t_last"]
        T = mo["ref"].copy()
        T[:3, 3] += self.ref_twist[:3] * el
        T[:3, :3] = exp_rot(self.ref_twist[3:] * el) @ T[:3, :3]
        return T

    def linear_ref(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        mo = self.motion
        s, sd = mo["profile"].at(t - mo["t0"])
        T = np.eye(4)
        T[:3, 3] = mo["start"][:3, 3] + s * mo["dp"]
        T[:3, :3] = exp_rot(s * mo["rv"]) @ mo["start"][:3, :3]
        return T, np.concatenate([sd * mo["dp"], sd * mo["rv"]])

    # the control loop ------------------------------------------------------------------------------------
    def step(self, h: float) -> None:
        """One physics step of ``h`` s: a control tick every ``ticks_per_control`` steps, in between the joint
        command advances along its velocity."""
        if self.mode is None:
            return
        self.tick_left -= 1
        if self.tick_left <= 0:
            self.tick_left = self.ticks_per_control
            self.control(h, h * self.ticks_per_control)
        else:
            self.q_cmd = self.q_cmd + self.qd_cmd * h
            self.apply_ctrl()

    def control(self, h: float, dt: float) -> None:
        """One Cartesian control tick (every ``dt`` s; physics steps are ``h`` s): update the reference
        and the joint velocity command that the next ``dt / h`` physics steps follow."""
        if self.mode is None:
            return
        arm = self.arm
        limits = self._limits()
        t = self.time()
        mo = self.motion
        if self.mode == "joint":
            self.control_joint(t, h, dt)
            return
        if self.mode == "linear":
            # pose at the tick, velocity averaged over the coming period (the joint command integrates it)
            ref = self.linear_ref(t)[0]
            vref = self.linear_ref(t + dt / 2)[1]
            if t - mo["t0"] >= mo["profile"].duration:
                mo["settle"] += dt
        else:
            ref = self.speed_ref(t)
            mo["ref"], mo["t_last"] = ref, t
            # ramp the reference twist toward the target at the commanded acceleration
            diff = mo["target"] - self.ref_twist
            step = mo["accel"] * dt
            nd = max(np.linalg.norm(diff[:3]), np.linalg.norm(diff[3:]))
            vref = mo["target"].copy() if nd <= step else self.ref_twist + diff * (step / nd)
        self.ref_twist = vref
        # actual TCP vs reference: only for fault detection and the end-of-move check
        T = arm.base_T_site(arm.tcp)
        ep = float(np.linalg.norm(ref[:3, 3] - T[:3, 3]))
        er = float(np.linalg.norm(log_rot(ref[:3, :3] @ T[:3, :3].T)))
        if ep > limits.max_tracking_error:
            self._fault(f"TCP cannot follow the commanded path: {1000 * ep:.1f} mm off "
                        f"(limit {1000 * limits.max_tracking_error:.0f} mm; singularity, workspace "
                        "edge or blocked arm)")
        # closed-loop IK on the commanded joints (the servos track q_cmd; closing the Cartesian loop on
        # the measured pose would integrate the servo lag and overshoot the speed limit)
        sd = arm.at_joints(self.q_cmd)
        Tc = arm.base_T_site(arm.tcp, sd)
        e = np.concatenate([ref[:3, 3] - Tc[:3, 3], log_rot(ref[:3, :3] @ Tc[:3, :3].T)])
        J = arm.jac_base(sd)
        w = vref + _CART_GAIN_PER_S * e
        qd = J.T @ np.linalg.solve(J @ J.T + _DLS_EYE, w)
        scale = np.max(np.abs(qd) / np.asarray(limits.max_joint_speed))
        if scale > 1.0:
            qd /= scale
        q_new = self.q_cmd + qd * h
        if (out := outside_limits(q_new, limits)) is not None:
            j, lo, hi = out
            self._fault(f"joint limit: {ARM_JOINTS[j]} would reach {q_new[j]:.4f} rad, limits "
                        f"[{lo:.4f}, {hi:.4f}] rad")
        self.set_feedforward(qd, dt)
        self.q_cmd, self.qd_cmd = q_new, qd
        self.apply_ctrl()
        # end of motion
        if self.mode == "linear":
            if mo["settle"] > 0 and ((ep < _SETTLE_TOL_M and er < _SETTLE_TOL_RAD) or mo["settle"] > SETTLE_MAX_S):
                self.finish()
        elif mo.get("stopping") and not np.any(self.ref_twist):
            self.finish()

    def control_joint(self, t: float, h: float, dt: float) -> None:
        mo = self.motion
        s, sd = mo["profile"].at(t - mo["t0"])
        q_ref = mo["start"] + s * mo["dq"]
        err = float(np.abs(q_ref - self.arm.data.qpos[self.arm.qadr]).max())
        if err > _JOINT_TRACKING_FAULT_RAD:
            self._fault(f"joints cannot follow the commanded motion: {err:.3f} rad off "
                        f"(limit {_JOINT_TRACKING_FAULT_RAD} rad; blocked arm)")
        self.q_cmd, self.qd_cmd = q_ref, sd * mo["dq"]
        self.apply_ctrl()
        if t - mo["t0"] >= mo["profile"].duration:
            mo["settle"] += dt
            if err < _SETTLE_TOL_JOINT_RAD or mo["settle"] > SETTLE_MAX_S:
                self.finish()


__all__ = ["ArmMotion", "outside_limits", "SETTLE_MAX_S"]
