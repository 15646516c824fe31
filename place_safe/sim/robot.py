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
  link touching the environment that hard) the robot protective-stops: the fault is latched, a moving
  arm brakes to rest at ``emergency_decel`` as the ur_rtde driver does (then the servos hold it), the
  gripper stays closed and RobotFault is raised. Every fault (tracking, joint limit, timeout, an injected
  protective stop) stops so.
* The force the placement sees is a UR controller's, not MuJoCo's: every control period (8 ms) the true
  net force plus a constant offset plus white noise (``controller`` ``cb3``: 3.6 N per axis, the CB3's
  motor-current estimate; ``e-series``: 1 N) feeds a
  :class:`~place_safe.robot.contact_detector.ContactDetector` zeroed at rest at construction (and by
  :meth:`SimRobot.zero_force`); :meth:`SimRobot.contact_force` is the detector's output (0.0 without a
  confirmed contact). :meth:`SimRobot.true_contact_force` / ``true_contact_vector`` are the physics, for
  judges and stand-ins; ``true_force_peak`` is its largest value since construction.

The concerns live in their own modules and SimRobot composes them: :mod:`~place_safe.sim.arm_model` (the
robot's elements in the model and its frames), :mod:`~place_safe.sim.arm_motion` (servos, the Cartesian loop
and straight-line planning), :mod:`~place_safe.sim.payload` (gripper, cup and liquid) and
:mod:`~place_safe.sim.force_sensing` (contact physics, the controller's force estimate, the protective
stop's test). SimRobot itself keeps the fault latch and the physics step loop.
"""

from __future__ import annotations

import math
from typing import Any, Callable

import mujoco
import numpy as np

from place_safe.exceptions import RobotFault
from place_safe.robot.contact_detector import DetectorSettings
from place_safe.robot.interface import Robot, RobotLimits, check_pose, check_twist, clamp_twist, stop_decel
from place_safe.robot.description import ur5_config

from place_safe.sim.arm_model import ArmModel
from place_safe.sim.arm_motion import SETTLE_MAX_S, ArmMotion, outside_limits
from place_safe.sim.force_sensing import ForceSensing
from place_safe.sim.payload import HeldCup
from place_safe.sim.robot_model import ARM_JOINTS, FINGERS, load_robot_model, robot_spec  # noqa: F401
from place_safe.drivers.ur5.config import MotionConfig, URConfig, packaged_config


def sim_limits(robot: URConfig | None = None) -> RobotLimits:
    """The simulated arm's limits: the Cartesian speed, acceleration and contact limits of the robot file ``robot``
    (default the packaged ``robots/ur5/sim.toml``: one definition, the descent is planned from what the simulated arm
    does), the joint ranges of :class:`RobotLimits`. The real arm's ``real.toml`` allows 0.1 m/s and 0.5 m/s^2."""
    lim = (robot if robot is not None else URConfig.load(packaged_config("sim"))).limits
    return RobotLimits(max_linear_speed=lim.max_linear_speed, max_linear_accel=lim.max_linear_accel,
                       max_angular_speed=lim.max_angular_speed, max_angular_accel=lim.max_angular_accel,
                       max_contact_force=lim.max_contact_force)

StepCallback = Callable[[mujoco.MjModel, mujoco.MjData, float], None]


class SimRobot(Robot):
    """UR5 in MuJoCo behind the :class:`Robot` interface.

    Parameters
    ----------
    model, data:
        A MuJoCo model containing the robot (joint/site/body names as in ``robots/ur5/ur5.xml``,
        optionally with a common ``prefix``) and its data. ``None``: load the bare robot.
    limits:
        Motion/safety limits; default :func:`sim_limits` (``robots/ur5/sim.toml``).
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
        self.limits = limits if limits is not None else sim_limits()
        # the hardest stop, as the ur_rtde driver gives it (a stop asked harder than max_linear_accel is an
        # emergency stop at most at the robot file's motion.emergency_decel): never kinder than the real arm
        self.emergency_decel = float(MotionConfig().emergency_decel if emergency_decel is None else emergency_decel)
        self.arm = ArmModel(model, data, prefix)
        self.payload = HeldCup(self.arm)
        if not (control_period > 0 and math.isfinite(control_period)):
            raise ValueError(f"control_period must be a positive number of seconds; got {control_period!r}")
        ticks = max(1, int(round(control_period / model.opt.timestep)))
        self.motion = ArmMotion(self.arm, ticks, limits=lambda: self.limits, fault=self._raise_fault)
        self.forces = ForceSensing(self.arm, self.payload, controller=controller, control_period=control_period,
                                   sense_ticks=ticks, force_noise=force_noise, force_offset=force_offset,
                                   force_seed=force_seed, detector=detector)
        self._callbacks: list[StepCallback] = []
        self._fault: str | None = None
        # the fault's stop: started (pending) inside the step loop, finished by the outermost loop
        self._loop_depth, self._brake_pending, self._braking, self._brake_limit = 0, False, False, 0.0
        #: faults raised while a fault's stop was braking (recorded only; the first fault stays latched)
        self.faults_while_stopping: list[str] = []
        if q_init is None:
            q_init = ur5_config()["arm"]["home"]
        self.set_joint_positions(q_init, hold_cup=hold_cup)
        self.zero_force()

    # the force sensing's settings and record, as attributes of the robot
    @property
    def detector(self):
        """The :class:`~place_safe.robot.contact_detector.ContactDetector` on the controller's force estimate."""
        return self.forces.detector

    @property
    def force_noise(self) -> float:
        return self.forces.force_noise

    @property
    def force_offset(self) -> np.ndarray:
        return self.forces.force_offset

    @property
    def true_force_peak(self) -> float:
        """N: the largest net contact force (physics) since construction."""
        return self.forces.true_force_peak

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
        d = self.data
        d.qpos[self.arm.qadr] = q
        d.qvel[self.arm.vadr] = 0.0
        self.motion.hold(q)
        mujoco.mj_forward(self.model, d)
        if hold_cup and self.payload.flange_T_cup is not None:
            self.regrasp_cup()
        elif not hold_cup:
            self.gripper(open=True)

    def reset(self, q: Any = None, hold_cup: bool = True) -> None:
        """Reset the whole simulation (mj_resetData), clear any fault and start at rest at ``q``
        (default: home) holding the cup."""
        mujoco.mj_resetData(self.model, self.data)
        self._fault, self.forces.grace = None, 0.0
        self._brake_pending, self.faults_while_stopping = False, []
        self.set_joint_positions(ur5_config()["arm"]["home"] if q is None else q, hold_cup=hold_cup)

    def regrasp_cup(self) -> None:
        """Put the cup (and its liquid) into the closed gripper at the nominal grasp and weld it."""
        self.payload.regrasp()

    def add_step_callback(self, fn: StepCallback) -> None:
        """Call ``fn(model, data, t)`` after every physics step (e.g. a simulated sensor)."""
        self._callbacks.append(fn)

    def remove_step_callback(self, fn: StepCallback) -> None:
        self._callbacks.remove(fn)

    # ------------------------------------------------------------------------------------------
    # Robot interface: state
    # ------------------------------------------------------------------------------------------
    def world_T_base(self) -> np.ndarray:
        """Pose of the robot base in the MuJoCo world."""
        return self.arm.world_T_base()

    def joint_positions(self) -> np.ndarray:
        return self.data.qpos[self.arm.qadr].copy()

    def joint_velocities(self) -> np.ndarray:
        return self.data.qvel[self.arm.vadr].copy()

    def tcp_pose(self) -> np.ndarray:
        return self.arm.base_T_site(self.arm.tcp)

    def sensor_pose(self) -> np.ndarray:
        return self.arm.base_T_site(self.arm.sensor)

    def flange_pose(self) -> np.ndarray:
        return self.arm.base_T_site(self.arm.flange_site)

    def cup_pose(self) -> np.ndarray:
        """base_T_cup of the cup body (held or not)."""
        return self.payload.cup_pose()

    def tcp_twist(self) -> np.ndarray:
        return self.arm.jac_base(self.data) @ self.data.qvel[self.arm.vadr]

    def time(self) -> float:
        return float(self.data.time)

    def liquid_spilled(self) -> int:
        """Number of liquid spheres no longer inside the cup (centre outside the cup's inner cylinder)."""
        return self.payload.liquid_spilled()

    def holding(self) -> bool:
        """True while the cup weld is active."""
        return self.payload.holding()

    def true_contact_vector(self) -> np.ndarray:
        """N: the net force of the environment on the gripper and the held cup (physics, base frame)."""
        return self.forces.true_contact_vector()

    def true_contact_force(self) -> float:
        """N: magnitude of :meth:`true_contact_vector` (physics)."""
        return float(np.linalg.norm(self.forces.contact_forces()[0]))

    def force_reading(self) -> np.ndarray:
        """One TCP force reading as the controller gives it (N, base frame): truth + offset + noise."""
        return self.forces.force_reading()

    def zero_force(self, samples: int = 50) -> np.ndarray:
        """Take the rest reading (``samples`` readings at the current state) for the contact detector."""
        return self.forces.zero(samples)

    def contact_force(self) -> float:
        """N: the contact detector's output on the noisy force reading (0.0 without a confirmed contact)."""
        return self.forces.detector.contact_force()

    def contact_latency(self) -> float:
        """s: the contact detector's 10 N touch latency at the noise measured when it was last zeroed."""
        return self.forces.detector.touch_latency()

    # ------------------------------------------------------------------------------------------
    # faults
    # ------------------------------------------------------------------------------------------
    def fault(self) -> str | None:
        return self._fault

    def clear_fault(self) -> None:
        """Acknowledge a latched fault. The contact-force stop re-arms once the force has dropped
        below the threshold (so the arm can be moved away from what it pressed on)."""
        if self._fault is not None:
            self.forces.rearm(self.limits.max_contact_force)
        self._fault = None

    def _raise_fault(self, msg: str) -> None:
        """Latch a fault, stop the arm as the real driver does and raise RobotFault; the gripper stays as it is.

        A moving arm brakes to rest at ``emergency_decel`` (the Cartesian stop :meth:`stop` uses: the ur_rtde
        driver stops a faulted arm at ``motion.emergency_decel``; holding at once would stop the cup kinder than
        the real arm). A fault raised inside the step loop (the Cartesian loop's faults, the contact-force stop,
        a step callback's injected protective stop) only latches and starts that stop: the outermost step loop
        finishes the braking once the exception has left the loop and its callbacks, so nothing runs
        re-entrantly. A fault raised during the braking is only recorded (``faults_while_stopping``) and is not
        re-entered; if it comes from the Cartesian loop (tracking, joint limit) the arm holds where it is."""
        if self._braking:  # a fault during the fault's stop: record it; the braking loop decides
            self.faults_while_stopping.append(msg)
            raise RobotFault(msg)
        self._fault = msg
        self.data.qfrc_applied[self.arm.vadr] = 0.0
        if self.motion.mode is not None and np.all(np.isfinite(self.data.qpos)) \
                and np.all(np.isfinite(self.data.qvel)):
            self._brake_limit = self.motion.start_stop(self.emergency_decel)
            self._brake_pending = True
            if self._loop_depth == 0:  # called from outside the step loop: brake now
                self._brake_after_fault()
        else:
            self.motion.hold(self.data.qpos[self.arm.qadr])
        raise RobotFault(msg)

    def _brake_after_fault(self) -> None:
        """Step physics (motion, callbacks, force record) until the fault's stop is at rest or its time limit
        has passed; then hold. Faults raised meanwhile are recorded, not re-entered."""
        self._brake_pending, self._braking = False, True
        m, d = self.model, self.data
        h = m.opt.timestep
        t_end = self.time() + self._brake_limit
        try:
            while self.motion.mode is not None and self.time() <= t_end:
                try:
                    self._step_once(m, d, h)
                except RobotFault:  # the Cartesian loop faulted while stopping (recorded): hold here
                    break
                if not (np.all(np.isfinite(d.qpos)) and np.all(np.isfinite(d.qvel))):
                    break
                if (why := self.forces.overload(self.limits.max_contact_force)) is not None:
                    self.faults_while_stopping.append(why)  # recorded (and its peak kept); the stop goes on
                self.forces.tick()
        finally:
            self._braking = False
            if self.motion.mode is not None:
                q = d.qpos[self.arm.qadr]
                self.motion.hold(q if np.all(np.isfinite(q)) else self.motion.q_cmd)
            d.qfrc_applied[self.arm.vadr] = 0.0

    def _require_ok(self) -> None:
        if self._fault is not None:
            raise RobotFault(f"robot is faulted ({self._fault}); call clear_fault() before commanding motion")

    def _check_joint_limits(self, q: np.ndarray, what: str) -> None:
        if (out := outside_limits(q, self.limits)) is not None:
            j, lo, hi = out
            raise RobotFault(f"{what}: joint {ARM_JOINTS[j]} at {q[j]:.4f} rad is outside its limits "
                             f"[{lo:.4f}, {hi:.4f}] rad")

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
        if self.motion.mode == "joint":
            self.stop(decel=accel)
        duration = self.motion.start_linear(goal, speed, accel)
        if not asynchronous:
            self._run_until_idle(duration + SETTLE_MAX_S + 1.0)

    def move_joint(self, q: Any, speed: float = 1.05, accel: float = 1.4, asynchronous: bool = False) -> None:
        try:
            goal = np.asarray(q, dtype=np.float64)
        except (TypeError, ValueError, OverflowError) as exc:
            raise ValueError(f"move_joint target must be 6 joint angles (rad); got {q!r}") from exc
        if goal.shape != (6,) or not np.all(np.isfinite(goal)):
            raise ValueError(f"move_joint target must be 6 finite joint angles (rad); got {goal.tolist()}")
        self._check_speed(speed, accel)
        self._require_ok()
        self._check_joint_limits(goal, "move_joint target")
        if self.motion.mode is not None:
            self.stop(decel=max(float(accel), 1.0))
        duration = self.motion.start_joint(goal, speed, accel)
        if not asynchronous:
            self._run_until_idle(duration + SETTLE_MAX_S + 1.0)

    def speed_linear(self, twist: Any, accel: float = 0.5, duration: float | None = None) -> None:
        v = check_twist(twist)
        self._check_speed(1.0, accel)
        if duration is not None and not (math.isfinite(duration) and duration >= 0):
            raise ValueError(f"duration must be None or a finite number of seconds >= 0; got {duration!r}")
        self._require_ok()
        lim = self.limits
        clamp_twist(v, lim)
        if self.motion.mode == "joint":
            self.stop(decel=accel)
        self.motion.start_speed(v, min(float(accel), lim.max_linear_accel))
        if duration is not None:
            self._advance(duration)
            self.stop(decel=accel)

    def stop(self, decel: float = 1.0, asynchronous: bool = False) -> None:
        self._check_speed(1.0, decel)
        if self.motion.mode is None:
            return
        longest = self.motion.start_stop(stop_decel(decel, self.limits.max_linear_accel, self.emergency_decel))
        if not asynchronous:
            self._run_until_idle(longest)

    def is_moving(self) -> bool:
        return self.motion.mode is not None

    def step(self, dt: float) -> None:
        """Advance physics by ``dt`` seconds (rounded to whole timesteps, at least one)."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0; got {dt!r}")
        self._advance(dt)

    # ------------------------------------------------------------------------------------------
    # gripper
    # ------------------------------------------------------------------------------------------
    def gripper(self, open: bool) -> None:
        self.payload.set_open(open)

    def gripper_is_open(self) -> bool:
        return self.payload.is_open

    # ------------------------------------------------------------------------------------------
    # the step loop: control, physics, sensors, safety
    # ------------------------------------------------------------------------------------------
    def _safety(self) -> None:
        if (why := self.forces.overload(self.limits.max_contact_force)) is not None:
            self._raise_fault(why)
        if not np.all(np.isfinite(self.data.qpos)):
            self._fault = "simulation diverged (NaN state)"
            raise RobotFault(self._fault)

    def _step_once(self, m: mujoco.MjModel, d: mujoco.MjData, h: float) -> None:
        self.motion.step(h)
        mujoco.mj_step(m, d)
        for cb in self._callbacks:
            cb(m, d, float(d.time))

    def _advance(self, duration: float) -> None:
        m, d = self.model, self.data
        h = m.opt.timestep
        n = max(1, int(round(duration / h)))
        self._loop_depth += 1
        try:
            for _ in range(n):
                self._step_once(m, d, h)
                if self._fault is None:
                    self._safety()
                self.forces.tick()
        finally:
            self._loop_depth -= 1
            if self._loop_depth == 0 and self._brake_pending:  # a fault in the loop: its stop, then its raise
                self._brake_after_fault()

    def _run_until_idle(self, timeout: float) -> None:
        h = self.model.opt.timestep
        t_end = self.time() + timeout
        while self.motion.mode is not None:
            if self.time() > t_end:
                self._raise_fault(f"motion did not finish within {timeout:.1f} s")
            self._advance(h)


__all__ = ["SimRobot", "sim_limits", "load_robot_model", "robot_spec", "ARM_JOINTS", "FINGERS", "StepCallback"]
