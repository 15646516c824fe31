"""The simulated UR5: :class:`place_safe.robot.interface.Robot` on MuJoCo physics.

Concept: :class:`SimRobot` drives the arm of a MuJoCo model (the packaged ``robots/ur5/ur5.xml`` or a
scene that contains it) like the UR controller does: joint position servos (gravity-compensated arm,
PD with velocity feed-forward through the position actuators) under a Cartesian loop that follows a
reference TCP trajectory by damped-least-squares differential IK on MuJoCo site Jacobians
(``mujoco.mj_jacSite``), closed on the measured TCP pose. Physics is stepped in real MuJoCo at the model
timestep; step callbacks (``add_step_callback``) let a simulated sensor advance in lockstep.

Conventions
-----------
* Poses/twists in the robot base frame = the frame of the ``base`` body (scene builders may move the
  base in the world; this class converts). TCP = site ``tcp``, sensor = site ``tof_sensor``.
* The held cup is welded to the flange by the equality ``cup_grasp`` while held; ``gripper(open=True)``
  deactivates the weld and opens the fingers, so the cup is free (it falls or stands on a surface).
* Contact force = norm of the net contact force from the environment (anything that is not robot, cup
  or liquid) on the gripper bodies and the held cup. Above ``limits.max_contact_force`` (or any robot
  link touching the environment that hard) the robot protective-stops: motion halts, servos hold the
  current position, the gripper stays closed, the fault is latched and RobotFault raised.
* The force the placement sees is a UR controller's, not MuJoCo's: every control period (8 ms) the true
  net force plus a constant offset plus white noise (``controller`` ``cb3``: 3.6 N per axis, the CB3's
  motor-current estimate; ``e-series``: 1 N) feeds a
  :class:`~place_safe.robot.contact_detector.ContactDetector` zeroed at rest at construction (and by
  :meth:`SimRobot.zero_force`); :meth:`SimRobot.contact_force` is the detector's output (0.0 without a
  confirmed contact). :meth:`SimRobot.true_contact_force` / ``true_contact_vector`` are the physics, for
  judges and stand-ins; ``true_force_peak`` is its largest value since construction.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from place_safe.exceptions import RobotFault
from place_safe.robot.contact_detector import ContactDetector, DetectorSettings
from place_safe.robot.interface import Robot, RobotLimits, TrapezoidProfile, check_pose, check_twist, clamp_twist
from place_safe.robot.description import ur5_config

from place_safe.sim.robot_model import ARM_JOINTS, FINGERS, load_robot_model, robot_spec  # noqa: F401
from place_safe.drivers.ur5.config import MotionConfig
from place_safe.drivers.ur5.fake_rtde import FORCE_NOISE, FORCE_OFFSET

StepCallback = Callable[[mujoco.MjModel, mujoco.MjData, float], None]

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
_SETTLE_MAX_S = 1.0
_SETTLE_TOL_JOINT_RAD = 2e-4
_JOINT_TRACKING_FAULT_RAD = 0.1


def _log_rot(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a rotation matrix (MuJoCo's C helpers: fast per step)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    v = np.empty(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return v


def _exp_rot(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (rad)."""
    angle = math.sqrt(float(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]))
    if angle < 1e-15:
        return np.eye(3)
    q = np.empty(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(w, dtype=np.float64) / angle, angle)
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, q)
    return R.reshape(3, 3)


class SimRobot(Robot):
    """UR5 in MuJoCo behind the :class:`Robot` interface.

    Parameters
    ----------
    model, data:
        A MuJoCo model containing the robot (joint/site/body names as in ``robots/ur5/ur5.xml``,
        optionally with a common ``prefix``) and its data. ``None``: load the bare robot.
    limits:
        Motion/safety limits; default :class:`RobotLimits()`.
    emergency_decel:
        m/s^2: a stop asked harder than ``limits.max_linear_accel`` (an obstacle, a fault) decelerates at most
        this hard, as the ur_rtde driver does (default: the robot file's ``motion.emergency_decel``, 2.0).
    q_init:
        Initial joint angles (6,), default the ``home`` of ``robots/ur5/config.json`` (gripper down).
        The arm is placed there at rest and, if ``hold_cup``, the cup and liquid are put in the gripper.
    hold_cup:
        Start with the cup grasped (weld active). If the model has no cup this is ignored.
    prefix:
        Name prefix of the robot's elements in ``model`` (if the scene builder attached it with one).
    control_period:
        Period (s) of the Cartesian control loop (125 Hz like the UR CB3 controller); physics and
        safety checks run at every model timestep, the joint command is interpolated in between.
    """

    def __init__(self, model: mujoco.MjModel | None = None, data: mujoco.MjData | None = None, *,
                 limits: RobotLimits | None = None, q_init: Any = None, hold_cup: bool = True,
                 prefix: str = "", control_period: float = 0.008, controller: str = "cb3",
                 force_noise: float | None = None, force_offset: Any = None, force_seed: int = 0,
                 detector: DetectorSettings | None = None, emergency_decel: float | None = None) -> None:
        if model is None:
            model, data = load_robot_model()
        elif data is None:
            data = mujoco.MjData(model)
        self.model, self.data = model, data
        self.limits = limits if limits is not None else RobotLimits()
        # the hardest stop, as the ur_rtde driver gives it (a stop asked harder than max_linear_accel is an
        # emergency stop at most at the robot file's motion.emergency_decel): never kinder than the real arm
        self.emergency_decel = float(MotionConfig().emergency_decel if emergency_decel is None else emergency_decel)
        m = model
        p = prefix

        def _id(kind: mujoco.mjtObj, name: str) -> int:
            i = mujoco.mj_name2id(m, kind, p + name)
            if i < 0:
                raise ValueError(f"model has no {kind.name.lower()[5:]} named {p + name!r}; "
                                 "expected the robot of robots/ur5/ur5.xml")
            return i

        jids = [_id(mujoco.mjtObj.mjOBJ_JOINT, j) for j in ARM_JOINTS]
        self._qadr = np.array([m.jnt_qposadr[j] for j in jids])
        self._vadr = np.array([m.jnt_dofadr[j] for j in jids])
        self._act = np.array([_id(mujoco.mjtObj.mjOBJ_ACTUATOR, j) for j in ARM_JOINTS])
        # position actuators: gain kp, bias (0, -kp, -kv)
        kp = m.actuator_gainprm[self._act, 0]
        if np.any(kp <= 0) or np.any(m.actuator_biasprm[self._act, 1] >= 0):
            raise ValueError("arm actuators must be MuJoCo position servos (kp > 0)")
        self._kv_over_kp = -m.actuator_biasprm[self._act, 2] / kp
        self._finger_act = np.array([_id(mujoco.mjtObj.mjOBJ_ACTUATOR, f) for f in FINGERS])
        self._finger_range = m.actuator_ctrlrange[self._finger_act].copy()
        self._tcp = _id(mujoco.mjtObj.mjOBJ_SITE, "tcp")
        self._sensor = _id(mujoco.mjtObj.mjOBJ_SITE, "tof_sensor")
        self._flange_site = _id(mujoco.mjtObj.mjOBJ_SITE, "flange")
        self._base = _id(mujoco.mjtObj.mjOBJ_BODY, "base")
        self._flange = _id(mujoco.mjtObj.mjOBJ_BODY, "flange")
        self._grip_bodies = {self._flange, _id(mujoco.mjtObj.mjOBJ_BODY, "finger_left"),
                             _id(mujoco.mjtObj.mjOBJ_BODY, "finger_right")}
        # geom classes: 0 environment, 1 robot arm, 2 gripper, 3 cup, 4 liquid
        robot_bodies = np.flatnonzero(m.body_rootid == self._base)
        self._cup = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, p + "cup")
        self._weld = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, p + "cup_grasp")
        self._liquid = [b for b in range(m.nbody) if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
                        and mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b).startswith(p + "liquid_")]
        body_class = np.zeros(m.nbody, dtype=np.int8)
        body_class[robot_bodies] = 1
        body_class[list(self._grip_bodies)] = 2
        if self._cup >= 0:
            body_class[self._cup] = 3
        body_class[self._liquid] = 4
        self._geom_class = body_class[m.geom_bodyid]
        if self._cup >= 0 and self._weld >= 0:
            rp = m.eq_data[self._weld]
            self._flange_T_cup = np.eye(4)
            self._flange_T_cup[:3, 3] = rp[3:6]
            qw, qx, qy, qz = rp[6:10]
            self._flange_T_cup[:3, :3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
            # liquid positions in the cup frame as laid out by the model (at qpos0, not the current state)
            ref = mujoco.MjData(m)
            mujoco.mj_kinematics(m, ref)
            cTw = np.linalg.inv(self._world_T_body(self._cup, ref))
            self._liquid_in_cup = [cTw @ np.append(ref.xpos[b], 1.0) for b in self._liquid]
            self._weld_relpose0 = m.eq_data[self._weld, 3:10].copy()
        else:
            self._flange_T_cup = None
            self._liquid_in_cup = []
        if not (control_period > 0 and math.isfinite(control_period)):
            raise ValueError(f"control_period must be a positive number of seconds; got {control_period!r}")
        self._ticks_per_control = max(1, int(round(control_period / m.opt.timestep)))
        self._tick_left = 0
        self._scratch = mujoco.MjData(m)
        cup_cfg = ur5_config()["cup"]
        self._cup_inner_radius = cup_cfg["radius"] - cup_cfg["wall_thickness"]
        self._cup_height = cup_cfg["height"]
        self._callbacks: list[StepCallback] = []
        self._fault: str | None = None
        self._force_grace = 0.0
        self._mode: str | None = None
        self._motion: dict[str, Any] = {}
        self._ref_twist = np.zeros(6)
        self._q_cmd = np.zeros(6)
        self._qd_cmd = np.zeros(6)
        self._last_force = 0.0
        self._gripper_open = False

        self.force_noise = float(FORCE_NOISE[controller] if force_noise is None else force_noise)
        self.force_offset = np.asarray(FORCE_OFFSET if force_offset is None else force_offset, dtype=float)
        self._force_rng = np.random.default_rng(force_seed)
        self.detector = ContactDetector(detector if detector is not None else DetectorSettings.for_controller(
            controller, period=control_period))
        self._sense_ticks = self._ticks_per_control
        self._sense_left = self._sense_ticks
        self.true_force_peak = 0.0
        if q_init is None:
            q_init = ur5_config()["arm"]["home"]
        self.set_joint_positions(q_init, hold_cup=hold_cup)
        self.zero_force()

    # ------------------------------------------------------------------------------------------
    # setup helpers
    # ------------------------------------------------------------------------------------------
    @classmethod
    def load(cls, **kwargs: Any) -> "SimRobot":
        """A SimRobot on the bare packaged robot model."""
        return cls(None, None, **kwargs)

    def set_joint_positions(self, q: Any, hold_cup: bool = True) -> None:
        """Teleport the arm to ``q`` at rest (servos hold it); put the cup in the gripper if ``hold_cup``."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (6,) or not np.all(np.isfinite(q)):
            raise ValueError(f"joint angles must be 6 finite radians; got {q.tolist()}")
        self._check_joint_limits(q, "initial configuration")
        m, d = self.model, self.data
        d.qpos[self._qadr] = q
        d.qvel[self._vadr] = 0.0
        self._q_cmd = q.copy()
        self._qd_cmd[:] = 0.0
        self._mode, self._motion = None, {}
        self._ref_twist[:] = 0.0
        self._apply_ctrl()
        mujoco.mj_forward(m, d)
        if hold_cup and self._flange_T_cup is not None:
            self.regrasp_cup()
        elif not hold_cup:
            self.gripper(open=True)

    def reset(self, q: Any = None, hold_cup: bool = True) -> None:
        """Reset the whole simulation (mj_resetData), clear any fault and start at rest at ``q``
        (default: home) holding the cup."""
        mujoco.mj_resetData(self.model, self.data)
        self._fault, self._force_grace = None, 0.0
        self.set_joint_positions(ur5_config()["arm"]["home"] if q is None else q, hold_cup=hold_cup)

    def regrasp_cup(self) -> None:
        """Put the cup (and its liquid) into the closed gripper at the nominal grasp and weld it."""
        if self._flange_T_cup is None:
            raise RobotFault("this model has no cup with a 'cup_grasp' weld to grasp")
        m, d = self.model, self.data
        m.eq_data[self._weld, 3:10] = self._weld_relpose0  # undo a re-grasp at another relative pose
        wTc = self._world_T_body(self._flange) @ self._flange_T_cup
        self._set_free_body(self._cup, wTc)
        for b, pc in zip(self._liquid, self._liquid_in_cup):
            T = np.eye(4)
            T[:, 3] = wTc @ pc
            self._set_free_body(b, T)
        d.eq_active[self._weld] = 1
        d.ctrl[self._finger_act] = self._finger_range[:, 0]
        fj = [m.actuator_trnid[a, 0] for a in self._finger_act]
        d.qpos[[m.jnt_qposadr[j] for j in fj]] = self._finger_range[:, 0]
        self._gripper_open = False
        mujoco.mj_forward(m, d)

    def _set_free_body(self, body: int, wT: np.ndarray) -> None:
        m, d = self.model, self.data
        j = m.body_jntadr[body]
        if j < 0 or m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError(f"body {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body)} is not free")
        a, v = m.jnt_qposadr[j], m.jnt_dofadr[j]
        x, y, z, w = Rotation.from_matrix(wT[:3, :3]).as_quat()
        d.qpos[a:a + 7] = [*wT[:3, 3], w, x, y, z]
        d.qvel[v:v + 6] = 0.0

    def add_step_callback(self, fn: StepCallback) -> None:
        """Call ``fn(model, data, t)`` after every physics step (e.g. a simulated sensor)."""
        self._callbacks.append(fn)

    def remove_step_callback(self, fn: StepCallback) -> None:
        self._callbacks.remove(fn)

    # ------------------------------------------------------------------------------------------
    # frames
    # ------------------------------------------------------------------------------------------
    def _world_T_body(self, b: int, data: mujoco.MjData | None = None) -> np.ndarray:
        d = self.data if data is None else data
        T = np.eye(4)
        T[:3, :3] = d.xmat[b].reshape(3, 3)
        T[:3, 3] = d.xpos[b]
        return T

    def _world_T_site(self, s: int, data: mujoco.MjData | None = None) -> np.ndarray:
        d = self.data if data is None else data
        T = np.eye(4)
        T[:3, :3] = d.site_xmat[s].reshape(3, 3)
        T[:3, 3] = d.site_xpos[s]
        return T

    def world_T_base(self) -> np.ndarray:
        """Pose of the robot base in the MuJoCo world."""
        return self._world_T_body(self._base)

    def _base_T_site(self, s: int, data: mujoco.MjData | None = None) -> np.ndarray:
        wb = self._world_T_body(self._base, data)
        ws = self._world_T_site(s, data)
        T = np.eye(4)
        T[:3, :3] = wb[:3, :3].T @ ws[:3, :3]
        T[:3, 3] = wb[:3, :3].T @ (ws[:3, 3] - wb[:3, 3])
        return T

    def _jac_base(self, data: mujoco.MjData) -> np.ndarray:
        """6x6 TCP Jacobian (linear; angular) in the base frame for the arm dofs."""
        jp = np.zeros((3, self.model.nv))
        jr = np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, data, jp, jr, self._tcp)
        Rb = data.xmat[self._base].reshape(3, 3)
        return np.vstack([Rb.T @ jp[:, self._vadr], Rb.T @ jr[:, self._vadr]])

    # ------------------------------------------------------------------------------------------
    # Robot interface: state
    # ------------------------------------------------------------------------------------------
    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self._qadr].copy()

    def joint_velocities(self) -> np.ndarray:
        return self.data.qvel[self._vadr].copy()

    def tcp_pose(self) -> np.ndarray:
        return self._base_T_site(self._tcp)

    def sensor_pose(self) -> np.ndarray:
        return self._base_T_site(self._sensor)

    def flange_pose(self) -> np.ndarray:
        return self._base_T_site(self._flange_site)

    def cup_pose(self) -> np.ndarray:
        """base_T_cup of the cup body (held or not)."""
        if self._cup < 0:
            raise RobotFault("this model has no cup")
        wb = self._world_T_body(self._base)
        return np.linalg.inv(wb) @ self._world_T_body(self._cup)

    def tcp_twist(self) -> np.ndarray:
        return self._jac_base(self.data) @ self.data.qvel[self._vadr]

    def time(self) -> float:
        return float(self.data.time)

    def liquid_spilled(self) -> int:
        """Number of liquid spheres no longer inside the cup (centre outside the cup's inner cylinder)."""
        if self._cup < 0 or not self._liquid:
            return 0
        cTw = np.linalg.inv(self._world_T_body(self._cup))
        p = (cTw[:3, :3] @ self.data.xpos[self._liquid].T).T + cTw[:3, 3]
        inner = self._cup_inner_radius
        inside = (np.hypot(p[:, 0], p[:, 1]) < inner) & (p[:, 2] > 0.0) & (p[:, 2] < self._cup_height)
        return int(np.count_nonzero(~inside))

    def holding(self) -> bool:
        """True while the cup weld is active."""
        return self._weld >= 0 and bool(self.data.eq_active[self._weld])

    def _contact_forces(self) -> tuple[np.ndarray, float]:
        """(net force on gripper + held cup from the environment (3,), max single-contact force on any
        robot part)."""
        d = self.data
        n = d.ncon
        if n == 0:
            return np.zeros(3), 0.0
        g = d.contact.geom[:n]
        c1, c2 = self._geom_class[g[:, 0]], self._geom_class[g[:, 1]]
        held = self.holding()
        ours = (c1 == 1) | (c1 == 2) | ((c1 == 3) & held)
        ours2 = (c2 == 1) | (c2 == 2) | ((c2 == 3) & held)
        env1, env2 = c1 == 0, c2 == 0
        sel = np.flatnonzero((ours & env2) | (ours2 & env1))
        net = np.zeros(3)
        worst = 0.0
        f6 = np.zeros(6)
        for i in sel:
            mujoco.mj_contactForce(self.model, d, int(i), f6)
            fw = d.contact.frame[i].reshape(3, 3).T @ f6[:3]  # force of geom1 on geom2, world frame
            on_ours = fw if ours2[i] else -fw
            worst = max(worst, float(np.linalg.norm(fw)))
            if (c2[i] if ours2[i] else c1[i]) >= 2:
                net += on_ours
        return net, worst

    def true_contact_vector(self) -> np.ndarray:
        """N: the net force of the environment on the gripper and the held cup (physics, base frame)."""
        R = self.world_T_base()[:3, :3]
        return R.T @ self._contact_forces()[0]

    def true_contact_force(self) -> float:
        """N: magnitude of :meth:`true_contact_vector` (physics)."""
        return float(np.linalg.norm(self._contact_forces()[0]))

    def force_reading(self) -> np.ndarray:
        """One TCP force reading as the controller gives it (N, base frame): truth + offset + noise."""
        f = self.true_contact_vector() + self.force_offset
        if self.force_noise:
            f = f + self._force_rng.normal(0.0, self.force_noise, 3)
        return f

    def zero_force(self, samples: int = 50) -> np.ndarray:
        """Take the rest reading (``samples`` readings at the current state) for the contact detector."""
        offset, _ = self.detector.zero([self.force_reading() for _ in range(max(2, int(samples)))])
        return offset

    def _sense(self) -> None:
        """One controller cycle of the force estimate into the contact detector (approach: the tool axis)."""
        self.detector.update(self.force_reading(), self.tcp_pose()[:3, 2])

    def contact_force(self) -> float:
        """N: the contact detector's output on the noisy force reading (0.0 without a confirmed contact)."""
        return self.detector.contact_force()

    # ------------------------------------------------------------------------------------------
    # faults
    # ------------------------------------------------------------------------------------------
    def fault(self) -> str | None:
        return self._fault

    def clear_fault(self) -> None:
        """Acknowledge a latched fault. The contact-force stop re-arms once the force has dropped
        below the threshold (so the arm can be moved away from what it pressed on)."""
        if self._fault is not None:
            self._force_grace = max(self.limits.max_contact_force, self._last_force) + 5.0
        self._fault = None

    def _raise_fault(self, msg: str) -> None:
        """Latch a fault: halt (hold the current position), keep the gripper as it is, raise."""
        self._fault = msg
        self.data.qfrc_applied[self._vadr] = 0.0
        self._mode, self._motion = None, {}
        self._ref_twist[:] = 0.0
        self._q_cmd = self.data.qpos[self._qadr].copy()
        self._qd_cmd[:] = 0.0
        self._apply_ctrl()
        raise RobotFault(msg)

    def _require_ok(self) -> None:
        if self._fault is not None:
            raise RobotFault(f"robot is faulted ({self._fault}); call clear_fault() before commanding motion")

    def _check_joint_limits(self, q: np.ndarray, what: str) -> None:
        lo, hi = np.asarray(self.limits.joint_lower), np.asarray(self.limits.joint_upper)
        bad = np.flatnonzero((q < lo) | (q > hi))
        if bad.size:
            j = int(bad[0])
            raise RobotFault(f"{what}: joint {ARM_JOINTS[j]} at {q[j]:.4f} rad is outside its limits "
                             f"[{lo[j]:.4f}, {hi[j]:.4f}] rad")

    # ------------------------------------------------------------------------------------------
    # planning: reachability of a straight line
    # ------------------------------------------------------------------------------------------
    def _ik_point(self, q: np.ndarray, target: np.ndarray, iters: int = 50) -> tuple[np.ndarray, float, float]:
        """DLS IK on the scratch data from ``q`` to base_T_tcp ``target``; returns (q, pos err, rot err)."""
        m, d = self.model, self._scratch
        d.qpos[:] = self.data.qpos
        q = q.copy()
        max_step = 0.2  # rad per iteration
        ep = er = math.inf
        for _ in range(iters):
            d.qpos[self._qadr] = q
            mujoco.mj_kinematics(m, d)
            mujoco.mj_comPos(m, d)
            T = self._base_T_site(self._tcp, d)
            e = np.concatenate([target[:3, 3] - T[:3, 3], _log_rot(target[:3, :3] @ T[:3, :3].T)])
            ep, er = float(np.linalg.norm(e[:3])), float(np.linalg.norm(e[3:]))
            if ep < _IK_TOL_M and er < _IK_TOL_RAD:
                break
            J = self._jac_base(d)
            dq = J.T @ np.linalg.solve(J @ J.T + _DLS_EYE, e)
            s = np.abs(dq).max()
            if s > max_step:
                dq *= max_step / s
            q = q + dq
        return q, ep, er

    def _plan_line(self, start: np.ndarray, goal: np.ndarray) -> None:
        """Check a straight TCP line is followable: IK converges along it within joint limits."""
        dp = goal[:3, 3] - start[:3, 3]
        rv = _log_rot(goal[:3, :3] @ start[:3, :3].T)
        n = max(1, int(math.ceil(max(np.linalg.norm(dp) / _PLAN_STEP_M, np.linalg.norm(rv) / _PLAN_STEP_RAD))))
        q = self.data.qpos[self._qadr].copy()
        lo, hi = np.asarray(self.limits.joint_lower), np.asarray(self.limits.joint_upper)
        for k in range(1, n + 1):
            s = k / n
            T = np.eye(4)
            T[:3, 3] = start[:3, 3] + s * dp
            T[:3, :3] = _exp_rot(s * rv) @ start[:3, :3]
            q_new, ep, er = self._ik_point(q, T)
            if ep > 1e-4 or er > 1e-3:
                raise RobotFault(
                    f"target pose unreachable by a straight line: IK fails at {100 * s:.0f}% of the path "
                    f"(position error {1000 * ep:.1f} mm, orientation error {math.degrees(er):.2f} deg) at "
                    f"TCP position {np.round(T[:3, 3], 4).tolist()} m in the base frame")
            if np.any(q_new < lo) or np.any(q_new > hi):
                j = int(np.flatnonzero((q_new < lo) | (q_new > hi))[0])
                raise RobotFault(f"target pose needs joint {ARM_JOINTS[j]} at {q_new[j]:.3f} rad, outside "
                                 f"[{lo[j]:.3f}, {hi[j]:.3f}] rad")
            if np.abs(q_new - q).max() > 0.5:
                raise RobotFault("target pose unreachable by a straight line: the path crosses a singularity "
                                 f"(joint jump of {np.abs(q_new - q).max():.2f} rad at {100 * s:.0f}% of the path)")
            q = q_new

    # ------------------------------------------------------------------------------------------
    # Robot interface: motion
    # ------------------------------------------------------------------------------------------
    def _check_speed(self, speed: float, accel: float) -> None:
        for name, v in (("speed", speed), ("accel", accel)):
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"{name} must be a positive finite number; got {v!r}")

    def move_linear(self, pose: Any, speed: float = 0.05, accel: float = 0.2,
                    asynchronous: bool = False) -> None:
        goal = check_pose(pose, "move_linear target")
        self._check_speed(speed, accel)
        self._require_ok()
        lim = self.limits
        speed = min(float(speed), lim.max_linear_speed)
        accel = min(float(accel), lim.max_linear_accel)
        if self._mode == "joint":
            self.stop(decel=accel)
        start = self._reference_pose()
        self._plan_line(start, goal)
        dp = goal[:3, 3] - start[:3, 3]
        rv = _log_rot(goal[:3, :3] @ start[:3, :3].T)
        L, A = float(np.linalg.norm(dp)), float(np.linalg.norm(rv))
        # normalised path parameter s in [0, 1]; both the linear and the angular part obey the limits
        v_s = min(speed / L if L > 0 else math.inf,
                  min(speed, lim.max_angular_speed) / A if A > 0 else math.inf)
        a_s = min(accel / L if L > 0 else math.inf,
                  min(accel, lim.max_angular_accel) / A if A > 0 else math.inf)
        # already there: an empty profile (the move only settles)
        prof = TrapezoidProfile(1.0, v_s, a_s) if math.isfinite(v_s) else TrapezoidProfile(0.0, 1.0, 1.0)
        self._mode = "linear"
        self._motion = {"start": start, "goal": goal, "dp": dp, "rv": rv, "profile": prof,
                        "t0": self.time(), "settle": 0.0}
        self._tick_left = 0
        if not asynchronous:
            self._run_until_idle(prof.duration + _SETTLE_MAX_S + 1.0)

    def move_joint(self, q: Any, speed: float = 1.05, accel: float = 1.4, asynchronous: bool = False) -> None:
        try:
            goal = np.asarray(q, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"move_joint target must be 6 joint angles (rad); got {q!r}") from exc
        if goal.shape != (6,) or not np.all(np.isfinite(goal)):
            raise ValueError(f"move_joint target must be 6 finite joint angles (rad); got {goal.tolist()}")
        self._check_speed(speed, accel)
        self._require_ok()
        self._check_joint_limits(goal, "move_joint target")
        if self._mode is not None:
            self.stop(decel=max(float(accel), 1.0))
        start = self._q_cmd.copy()
        dq = goal - start
        vmax = np.minimum(float(speed), np.asarray(self.limits.max_joint_speed))
        span = np.abs(dq)
        moving = span > 0
        v_s = float(np.min(vmax[moving] / span[moving])) if moving.any() else math.inf
        a_s = float(np.min(float(accel) / span[moving])) if moving.any() else math.inf
        prof = TrapezoidProfile(1.0, v_s, a_s) if math.isfinite(v_s) else TrapezoidProfile(0.0, 1.0, 1.0)
        self._mode = "joint"
        self._motion = {"start": start, "dq": dq, "goal": goal, "profile": prof, "t0": self.time(),
                        "settle": 0.0}
        self._tick_left = 0
        if not asynchronous:
            self._run_until_idle(prof.duration + _SETTLE_MAX_S + 1.0)

    def speed_linear(self, twist: Any, accel: float = 0.5, duration: float | None = None) -> None:
        v = check_twist(twist)
        self._check_speed(1.0, accel)
        if duration is not None and not (math.isfinite(duration) and duration >= 0):
            raise ValueError(f"duration must be None or a finite number of seconds >= 0; got {duration!r}")
        self._require_ok()
        lim = self.limits
        clamp_twist(v, lim)
        if self._mode == "joint":
            self.stop(decel=accel)
        ref = self._reference_pose()
        self._mode = "speed"
        self._motion = {"target": v, "accel": min(float(accel), lim.max_linear_accel), "ref": ref,
                        "t_last": self.time()}
        self._tick_left = 0
        if duration is not None:
            self._advance(duration)
            self.stop(decel=accel)

    def stop(self, decel: float = 1.0, asynchronous: bool = False) -> None:
        self._check_speed(1.0, decel)
        if self._mode is None:
            return
        if self._mode == "joint":  # continue from the current joint velocity, decelerating in Cartesian space
            sd = self._scratch
            sd.qpos[self._qadr] = self._q_cmd
            mujoco.mj_kinematics(self.model, sd)
            mujoco.mj_comPos(self.model, sd)
            self._ref_twist = self._jac_base(sd) @ self._qd_cmd
            self._mode, self._motion = "speed", {"ref": self._base_T_site(self._tcp, sd), "t_last": self.time()}
        ref = self._reference_pose()
        self._mode = "speed"
        lim = self.limits.max_linear_accel
        decel = float(decel) if decel <= lim else min(float(decel), self.emergency_decel)
        self._motion = {"target": np.zeros(6), "accel": decel, "ref": ref, "stopping": True,
                        "t_last": self.time()}
        self._tick_left = 0
        if not asynchronous:
            self._run_until_idle(np.abs(self._ref_twist).max() / decel + 2.0)

    def is_moving(self) -> bool:
        return self._mode is not None

    def step(self, dt: float) -> None:
        """Advance physics by ``dt`` seconds (rounded to whole timesteps, at least one)."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0; got {dt!r}")
        self._advance(dt)

    # ------------------------------------------------------------------------------------------
    # gripper
    # ------------------------------------------------------------------------------------------
    def gripper(self, open: bool) -> None:
        d = self.data
        if open:
            if self._weld >= 0:
                d.eq_active[self._weld] = 0
            d.ctrl[self._finger_act] = self._finger_range[:, 1]
            self._gripper_open = True
        else:
            d.ctrl[self._finger_act] = self._finger_range[:, 0]
            self._gripper_open = False
            if self._flange_T_cup is not None and not self.holding():
                # grasp the cup again if it sits where the fingers close on it (within 5 mm / 5 deg)
                fTc = np.linalg.inv(self._world_T_body(self._flange)) @ self._world_T_body(self._cup)
                E = np.linalg.inv(self._flange_T_cup) @ fTc
                if np.linalg.norm(E[:3, 3]) < 0.005 and np.linalg.norm(_log_rot(E[:3, :3])) < math.radians(5):
                    x, y, z, w = Rotation.from_matrix(fTc[:3, :3]).as_quat()
                    self.model.eq_data[self._weld, 3:10] = [*fTc[:3, 3], w, x, y, z]
                    d.eq_active[self._weld] = 1

    def gripper_is_open(self) -> bool:
        return self._gripper_open

    # ------------------------------------------------------------------------------------------
    # control loop
    # ------------------------------------------------------------------------------------------
    def _reference_pose(self) -> np.ndarray:
        """Where the Cartesian reference is now (continuing a motion smoothly), else the actual TCP."""
        if self._mode == "linear":
            return self._linear_ref(self.time())[0]
        if self._mode == "speed":
            return self._speed_ref(self.time())
        if self._mode == "joint":
            raise RobotFault("a joint move is in progress; stop() it before a Cartesian command")
        return self.tcp_pose()

    def _speed_ref(self, t: float) -> np.ndarray:
        """Reference pose in speed mode: last tick's reference moved on by the reference twist."""
        mo = self._motion
        el = t - mo["t_last"]
        T = mo["ref"].copy()
        T[:3, 3] += self._ref_twist[:3] * el
        T[:3, :3] = _exp_rot(self._ref_twist[3:] * el) @ T[:3, :3]
        return T

    def _linear_ref(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        mo = self._motion
        s, sd = mo["profile"].at(t - mo["t0"])
        T = np.eye(4)
        T[:3, 3] = mo["start"][:3, 3] + s * mo["dp"]
        T[:3, :3] = _exp_rot(s * mo["rv"]) @ mo["start"][:3, :3]
        return T, np.concatenate([sd * mo["dp"], sd * mo["rv"]])

    def _set_feedforward(self, qd_new: np.ndarray, dt: float) -> None:
        """Inertial feed-forward torque M(q) qdd for the change of joint velocity over one control tick
        (what the UR controller adds to its servo loop); without it the servos lag on accelerating and
        overshoot the commanded speed."""
        qdd = (qd_new - self._qd_cmd) / dt
        vec = np.zeros(self.model.nv)
        vec[self._vadr] = qdd
        res = np.zeros(self.model.nv)
        mujoco.mj_mulM(self.model, self.data, res, vec)
        self.data.qfrc_applied[self._vadr] = res[self._vadr]

    def _apply_ctrl(self) -> None:
        # PD with velocity feed-forward through the position actuator:
        # kp (q_cmd + kv/kp qd_cmd - q) - kv qd = kp (q_cmd - q) + kv (qd_cmd - qd)
        self.data.ctrl[self._act] = self._q_cmd + self._kv_over_kp * self._qd_cmd

    def _control(self, h: float, dt: float) -> None:
        """One Cartesian control tick (every ``dt`` s; physics steps are ``h`` s): update the reference
        and the joint velocity command that the next ``dt / h`` physics steps follow."""
        if self._mode is None:
            return
        t = self.time()
        mo = self._motion
        if self._mode == "joint":
            self._control_joint(t, h, dt)
            return
        if self._mode == "linear":
            # pose at the tick, velocity averaged over the coming period (the joint command integrates it)
            ref = self._linear_ref(t)[0]
            vref = self._linear_ref(t + dt / 2)[1]
            if t - mo["t0"] >= mo["profile"].duration:
                mo["settle"] += dt
        else:
            ref = self._speed_ref(t)
            mo["ref"], mo["t_last"] = ref, t
            # ramp the reference twist toward the target at the commanded acceleration
            diff = mo["target"] - self._ref_twist
            step = mo["accel"] * dt
            nd = max(np.linalg.norm(diff[:3]), np.linalg.norm(diff[3:]))
            vref = mo["target"].copy() if nd <= step else self._ref_twist + diff * (step / nd)
        self._ref_twist = vref
        # actual TCP vs reference: only for fault detection and the end-of-move check
        T = self.tcp_pose()
        ep = float(np.linalg.norm(ref[:3, 3] - T[:3, 3]))
        er = float(np.linalg.norm(_log_rot(ref[:3, :3] @ T[:3, :3].T)))
        if ep > self.limits.max_tracking_error:
            self._raise_fault(f"TCP cannot follow the commanded path: {1000 * ep:.1f} mm off "
                              f"(limit {1000 * self.limits.max_tracking_error:.0f} mm; singularity, workspace "
                              "edge or blocked arm)")
        # closed-loop IK on the commanded joints (the servos track q_cmd; closing the Cartesian loop on
        # the measured pose would integrate the servo lag and overshoot the speed limit)
        sd = self._scratch
        sd.qpos[self._qadr] = self._q_cmd
        mujoco.mj_kinematics(self.model, sd)
        mujoco.mj_comPos(self.model, sd)
        Tc = self._base_T_site(self._tcp, sd)
        e = np.concatenate([ref[:3, 3] - Tc[:3, 3], _log_rot(ref[:3, :3] @ Tc[:3, :3].T)])
        J = self._jac_base(sd)
        w = vref + _CART_GAIN_PER_S * e
        qd = J.T @ np.linalg.solve(J @ J.T + _DLS_EYE, w)
        scale = np.max(np.abs(qd) / np.asarray(self.limits.max_joint_speed))
        if scale > 1.0:
            qd /= scale
        q_new = self._q_cmd + qd * h
        self._check_limits_running(q_new)
        self._set_feedforward(qd, dt)
        self._q_cmd, self._qd_cmd = q_new, qd
        self._apply_ctrl()
        # end of motion
        if self._mode == "linear":
            if mo["settle"] > 0 and ((ep < _SETTLE_TOL_M and er < _SETTLE_TOL_RAD) or mo["settle"] > _SETTLE_MAX_S):
                self._finish()
        elif mo.get("stopping") and not np.any(self._ref_twist):
            self._finish()

    def _control_joint(self, t: float, h: float, dt: float) -> None:
        mo = self._motion
        s, sd = mo["profile"].at(t - mo["t0"])
        q_ref = mo["start"] + s * mo["dq"]
        err = float(np.abs(q_ref - self.joint_positions()).max())
        if err > _JOINT_TRACKING_FAULT_RAD:
            self._raise_fault(f"joints cannot follow the commanded motion: {err:.3f} rad off "
                              f"(limit {_JOINT_TRACKING_FAULT_RAD} rad; blocked arm)")
        self._q_cmd, self._qd_cmd = q_ref, sd * mo["dq"]
        self._apply_ctrl()
        if t - mo["t0"] >= mo["profile"].duration:
            mo["settle"] += dt
            if err < _SETTLE_TOL_JOINT_RAD or mo["settle"] > _SETTLE_MAX_S:
                self._finish()

    def _finish(self) -> None:
        self.data.qfrc_applied[self._vadr] = 0.0
        self._mode, self._motion = None, {}
        self._ref_twist[:] = 0.0
        self._qd_cmd[:] = 0.0
        self._apply_ctrl()

    def _check_limits_running(self, q: np.ndarray) -> None:
        lo, hi = np.asarray(self.limits.joint_lower), np.asarray(self.limits.joint_upper)
        bad = np.flatnonzero((q < lo) | (q > hi))
        if bad.size:
            j = int(bad[0])
            self._raise_fault(f"joint limit: {ARM_JOINTS[j]} would reach {q[j]:.4f} rad, limits "
                              f"[{lo[j]:.4f}, {hi[j]:.4f}] rad")

    def _safety(self) -> None:
        net, worst = self._contact_forces()
        f = float(np.linalg.norm(net))
        self._last_force = max(f, worst)
        self.true_force_peak = max(self.true_force_peak, f)
        thr = self.limits.max_contact_force
        if self._force_grace > 0:
            if self._last_force < thr:
                self._force_grace = 0.0
            else:
                thr = max(thr, self._force_grace)
        if f > thr or worst > thr:
            self._raise_fault(f"protective stop: contact force {max(f, worst):.1f} N exceeds {thr:.1f} N "
                              "(collision or pressing too hard); holding position and object")
        if not np.all(np.isfinite(self.data.qpos)):
            self._fault = "simulation diverged (NaN state)"
            raise RobotFault(self._fault)

    def _advance(self, duration: float) -> None:
        m, d = self.model, self.data
        h = m.opt.timestep
        n = max(1, int(round(duration / h)))
        for _ in range(n):
            if self._mode is not None:
                self._tick_left -= 1
                if self._tick_left <= 0:
                    self._tick_left = self._ticks_per_control
                    self._control(h, h * self._ticks_per_control)
                else:  # between control ticks: advance the joint command along its velocity
                    self._q_cmd = self._q_cmd + self._qd_cmd * h
                    self._apply_ctrl()
            mujoco.mj_step(m, d)
            for cb in self._callbacks:
                cb(m, d, float(d.time))
            if self._fault is None:
                self._safety()
            self._sense_left -= 1
            if self._sense_left <= 0:
                self._sense_left = self._sense_ticks
                self._sense()

    def _run_until_idle(self, timeout: float) -> None:
        h = self.model.opt.timestep
        t_end = self.time() + timeout
        while self._mode is not None:
            if self.time() > t_end:
                self._raise_fault(f"motion did not finish within {timeout:.1f} s")
            self._advance(h)


__all__ = ["SimRobot", "load_robot_model", "robot_spec", "ARM_JOINTS", "FINGERS", "StepCallback"]
