"""A faithful stand-in for ur_rtde: fake ``RTDEControlInterface``, ``RTDEReceiveInterface``, ``RTDEIOInterface``.

Concept: :class:`FakeUR` is the controller (a UR CB3 or e-Series box) the three fake interfaces talk to.
It moves an arm that obeys :class:`~place_safe.robot.interface.Robot` -- a
:class:`~place_safe.drivers.ur5.kinematic_arm.KinematicArm` by default, or the MuJoCo
:class:`~place_safe.sim.robot.SimRobot` -- and behaves like the controller where a driver can get it
wrong: commands return ``False`` once the control script has stopped, a protective stop halts the arm
and stops the script until it is unlocked, the watchdog stops the arm when the host stops kicking,
a dropped connection freezes the received state and makes commands raise ``RuntimeError``, a slow
controller stops advancing its timestamp. Faults are injected with :meth:`FakeUR.inject_protective_stop`,
:meth:`FakeUR.inject_emergency_stop`, :meth:`FakeUR.inject_disconnect` and :meth:`FakeUR.inject_slow`.

Pessimistic by default, as the hardware is:

* **Force noise and offset**: the TCP force reading carries white noise of
  :data:`FORCE_NOISE` per axis per cycle (CB3 3.6 N, the spread ``shared/docs/ur5-rtde.md`` gives for the
  motor-current estimate; e-Series 1 N) and a constant offset (a payload set a little wrong).
* **Watchdog**: once ``setWatchdog`` armed it, a host that does not kick it for longer than its period
  gets the arm stopped and the control script ended -- in every mode, at rest too (the control script
  shuts the control down, ur_rtde's ``setWatchdog`` docstring).
* **One motion thread**: a motion command (moveL, moveJ, speedL) sent while a stop is still running, or
  while a motion of another kind (or any move) runs, is the control script's "Another thread is already
  controlling the robot": the script stops, the command returns False, the error is in ``errors``.

The fake classes carry the installed ur-rtde's class names, method names, parameter names and defaults
(``tests/drivers/test_fake_rtde.py`` checks them against the pybind11 signatures of the real module);
:func:`modules` returns three module-like objects to hand to
:class:`~place_safe.drivers.ur5.rtde_robot.URRobot` so its real code path runs on the fake.

Time: the controller clock advances only when the host waits for a cycle (``waitPeriod``) or when a test
calls :meth:`FakeUR.advance` (the host stalling); nothing sleeps, so tests run fast.
"""

from __future__ import annotations

import datetime
import math
from types import SimpleNamespace
from typing import Any, Callable

import numpy as np

from place_safe.drivers.ur5.config import CONTROLLER_HZ
from place_safe.drivers.ur5.pose import pose_to_vector, vector_to_pose
from place_safe.exceptions import RobotFault
from place_safe.drivers.ur5.kinematic_arm import KinematicArm

#: UR robot and safety mode numbers (ur_rtde getRobotMode / getSafetyMode).
ROBOT_MODE_RUNNING = 7
SAFETY_NORMAL, SAFETY_PROTECTIVE_STOP, SAFETY_ROBOT_EMERGENCY_STOP = 1, 3, 7

#: N per axis per controller cycle: the standard deviation of the TCP force reading by controller.
FORCE_NOISE = {"cb3": 3.6, "e-series": 1.0}
#: N: the default constant offset of the TCP force reading (a payload set a little wrong).
FORCE_OFFSET = (1.5, -2.0, 6.0)
#: The control script's answer to a second motion thread.
THREAD_CONFLICT = "Another thread is already controlling the robot"

#: Fake controllers by host name, so ``FakeRTDEControlInterface("10.0.0.2")`` finds its controller.
_CONTROLLERS: dict[str, "FakeUR"] = {}


class FakeUR:
    """The fake controller (see module docstring).

    ``arm``: the Robot it moves (default a KinematicArm). ``controller``: ``cb3`` (125 Hz) or ``e-series``
    (500 Hz). ``arm_flange_T_tcp``: where ``arm.tcp_pose()`` sits on the flange (default the packaged
    TCP, 0.14 m along the tool axis). ``force_noise``: N, standard deviation of the TCP force reading per
    axis per cycle (default :data:`FORCE_NOISE` of the controller); ``force_offset``: N, a constant bias (default
    :data:`FORCE_OFFSET`). ``host``: name the fake interfaces find it by.
    """

    def __init__(self, arm: Any = None, *, controller: str = "cb3", host: str = "127.0.0.1",
                 arm_flange_T_tcp: Any = None, force_noise: float | None = None, force_offset: Any = FORCE_OFFSET,
                 seed: int = 0) -> None:
        if arm is None:
            arm = KinematicArm(period=1.0 / CONTROLLER_HZ[controller])
        self.arm = arm
        self.period = 1.0 / CONTROLLER_HZ[controller]
        self.host = host
        if arm_flange_T_tcp is None:
            arm_flange_T_tcp = np.eye(4)
            arm_flange_T_tcp[2, 3] = 0.14
        self.arm_flange_T_tcp = np.asarray(arm_flange_T_tcp, dtype=float)
        self.tcp_offset = np.eye(4)  # the controller's active TCP (setTcp); flange until set
        self.payload: tuple[float, list[float]] | None = None
        self.controller = controller
        self.force_noise = float(FORCE_NOISE[controller] if force_noise is None else force_noise)
        self.force_offset = np.asarray(force_offset, dtype=float)
        self._rng = np.random.default_rng(seed)
        self.time = float(arm.time())  # the controller clock is the arm's (simulation time for SimRobot)
        self.stamp = self.time  # what getTimestamp reports (lags when slow)
        self.connected = True
        self.reconnectable = True
        self.program_running = True
        self.safety_mode = SAFETY_NORMAL
        self.protective_reason: str | None = None
        self.watchdog_hz: float | None = None
        self.last_kick = 0.0
        self.async_progress = -1
        self.mode: str | None = None  # the motion thread: "move" (moveL/moveJ), "speed", "stop" or None
        self.errors: list[str] = []  # control-script errors (thread conflicts), in order
        self.watchdog_stops = 0  # times the watchdog stopped the script
        self.rejected: list[str] = []  # commands answered False (script stopped or robot stopped)
        self.outputs: dict[tuple[str, int], bool] = {}
        self.gripper_output: tuple[str, int, bool] | None = ("standard", 0, True)
        self.commands: list[tuple[float, str, tuple]] = []  # (time, name, args): every motion/IO command
        self._triggers: list[tuple[str, Callable[["FakeUR"], bool], Any]] = []
        self._slow_until = -1.0
        _CONTROLLERS[host] = self

    # --- fault injection --------------------------------------------------------------------------
    def inject_protective_stop(self, when: float | Callable[["FakeUR"], bool], reason: str = "injected") -> None:
        """Protective-stop at controller time ``when`` (s) or at the first cycle where ``when(fake)`` is true."""
        cond = when if callable(when) else (lambda f, t=float(when): f.time >= t)
        self._triggers.append(("pstop", cond, reason))

    def inject_emergency_stop(self, when: float | Callable[["FakeUR"], bool]) -> None:
        """Emergency-stop at ``when`` (as above): the arm halts, the script stops, until :meth:`release_emergency_stop`."""
        cond = when if callable(when) else (lambda f, t=float(when): f.time >= t)
        self._triggers.append(("estop", cond, None))

    def release_emergency_stop(self) -> None:
        self.unlock_protective_stop()

    def inject_disconnect(self, when: float | Callable[["FakeUR"], bool], reconnectable: bool = True) -> None:
        """Drop the connection at ``when`` (as above); ``reconnectable=False``: reconnect() keeps failing."""
        cond = when if callable(when) else (lambda f, t=float(when): f.time >= t)
        self._triggers.append(("drop", cond, reconnectable))

    def inject_slow(self, seconds: float) -> None:
        """From now on, for ``seconds``, the controller's published timestamp does not advance."""
        self._slow_until = self.time + float(seconds)

    def unlock_protective_stop(self) -> None:
        """What the operator does on the pendant (or the dashboard's ``unlock protective stop``)."""
        self.safety_mode = SAFETY_NORMAL
        self.protective_reason = None
        if hasattr(self.arm, "clear_fault"):
            self.arm.clear_fault()

    # --- controller behaviour ------------------------------------------------------------------
    def _protective_stop(self, reason: str) -> None:
        if self.safety_mode == SAFETY_PROTECTIVE_STOP:
            return
        self.safety_mode = SAFETY_PROTECTIVE_STOP
        self.protective_reason = reason
        self.program_running = False
        self.mode = None
        self.async_progress = -1
        if getattr(self.arm, "fault", lambda: None)() is None and hasattr(self.arm, "protective_stop"):
            self.arm.protective_stop(f"protective stop: {reason}")
        elif self.arm.is_moving():
            self._halt()

    def _halt(self) -> None:
        try:
            self.arm.stop(decel=10.0)
        except RobotFault:
            pass

    def advance(self, dt: float) -> None:
        """Let ``dt`` seconds pass on the controller (cycles of ``period``)."""
        for _ in range(max(1, int(round(dt / self.period)))):
            self._cycle()

    def _cycle(self) -> None:
        try:
            self.arm.step(self.period)
        except RobotFault:
            pass
        self.time = float(self.arm.time())
        if self.time >= self._slow_until:
            self.stamp = self.time
        if self.arm.fault() is not None and self.safety_mode == SAFETY_NORMAL:
            self._protective_stop(self.arm.fault())
        for trig in list(self._triggers):
            kind, cond, arg = trig
            if cond(self):
                self._triggers.remove(trig)
                if kind == "pstop":
                    self._protective_stop(arg)
                elif kind == "estop":
                    self._protective_stop("emergency stop")
                    self.safety_mode = SAFETY_ROBOT_EMERGENCY_STOP
                else:
                    self.connected, self.reconnectable = False, bool(arg)
        if (self.watchdog_hz and self.program_running
                and self.time - self.last_kick > 1.0 / self.watchdog_hz + 1e-9):
            if self.arm.is_moving():
                self._halt()
            self.mode = None
            self.program_running = False  # the control script stops on a watchdog timeout, at rest too
            self.watchdog_hz = None  # a new script starts without one
            self.watchdog_stops += 1
        if self.mode == "move" and not self.arm.is_moving():
            self.mode = None
            self.async_progress = -1 if self.async_progress != -1 else -2
        elif self.mode == "stop" and not self.arm.is_moving():
            self.mode = None

    def _conflict(self, name: str, kind: str) -> bool:
        """True (and the script stopped) if a ``kind`` motion ("move"/"speed") may not start now."""
        if self.mode is None or (self.mode == "speed" and kind == "speed"):
            return False
        self.errors.append(f"{name}: {THREAD_CONFLICT} (a {self.mode} thread is running)")
        self.program_running = False
        self.mode = None
        if self.arm.is_moving():
            self._halt()
        return True

    def _can_command(self, name: str, args: tuple) -> bool:
        if not self.connected:
            raise RuntimeError("RTDE control: not connected to the robot")
        self.commands.append((self.time, name, args))
        ok = self.program_running and self.safety_mode == SAFETY_NORMAL
        if not ok:
            self.rejected.append(name)
        return ok

    # --- frames ---------------------------------------------------------------------------------
    def base_T_flange(self) -> np.ndarray:
        return self.arm.tcp_pose() @ np.linalg.inv(self.arm_flange_T_tcp)

    def tcp_pose(self) -> np.ndarray:
        return self.base_T_flange() @ self.tcp_offset

    def to_arm_pose(self, tcp_pose: np.ndarray) -> np.ndarray:
        return tcp_pose @ np.linalg.inv(self.tcp_offset) @ self.arm_flange_T_tcp

    def to_arm_twist(self, xd: np.ndarray) -> np.ndarray:
        lever = self.arm.tcp_pose()[:3, 3] - self.tcp_pose()[:3, 3]
        out = np.array(xd, dtype=float)
        out[:3] += np.cross(out[3:], lever)
        return out

    def force(self) -> np.ndarray:
        f = np.zeros(6)
        vec = getattr(self.arm, "true_contact_vector", None) or getattr(self.arm, "contact_vector", None)
        f[:3] = vec() if vec is not None else np.array([0.0, 0.0, self.arm.contact_force()])
        f[:3] += self.force_offset
        if self.force_noise:
            f[:3] += self._rng.normal(0.0, self.force_noise, 3)
        return f

    def reachable(self, tcp_pose: np.ndarray) -> bool:
        """A pose the arm can reach: inside the UR5's 850 mm reach and above the base's own footprint."""
        p = self.to_arm_pose(tcp_pose)[:3, 3] - np.array([0.0, 0.0, 0.089159])
        return bool(np.linalg.norm(p) < 0.85 and np.linalg.norm(p[:2]) > 0.12)


def _timedelta(seconds: float) -> datetime.timedelta:
    return datetime.timedelta(seconds=seconds)


def _controller(hostname: str) -> FakeUR:
    fake = _CONTROLLERS.get(hostname)
    if fake is None:
        raise RuntimeError(f"fake ur_rtde: no robot at {hostname} (create a FakeUR(host={hostname!r}) first)")
    if not fake.connected and not fake.reconnectable:
        raise RuntimeError(f"fake ur_rtde: connection to {hostname} timed out")
    return fake


class _Connection:
    """What the three fake interfaces share: a connection to the fake controller at ``hostname`` that
    ``disconnect`` closes (this interface only) and ``reconnect`` reopens when the controller allows it."""

    def __init__(self, hostname: str) -> None:
        self._f = _controller(hostname)
        self._open = True

    def isConnected(self) -> bool:
        return self._open and self._f.connected

    def reconnect(self) -> bool:
        if not self._f.reconnectable:
            return False
        self._f.connected, self._open = True, True
        return True

    def disconnect(self) -> None:
        self._open = False


class RTDEControlInterface(_Connection):
    """Fake of ``rtde_control.RTDEControlInterface`` (names and defaults as in ur-rtde 1.6.5)."""

    def __init__(self, hostname: str, frequency: float = -1.0, flags: int = 1, ur_cap_port: int = 50002,
                 rt_priority: int = 0) -> None:
        super().__init__(hostname)
        self._f.program_running = self._f.safety_mode == SAFETY_NORMAL

    # connection
    def reconnect(self) -> bool:
        if not super().reconnect():
            return False
        self._f.program_running = self._f.safety_mode == SAFETY_NORMAL
        return True

    def isProgramRunning(self) -> bool:
        return self._f.connected and self._f.program_running

    def reuploadScript(self) -> bool:
        if not self._f.connected:
            raise RuntimeError("RTDE control: not connected to the robot")
        self._f.program_running = self._f.safety_mode == SAFETY_NORMAL
        self._f.watchdog_hz = None
        return self._f.program_running

    def stopScript(self) -> None:
        f = self._f
        f.program_running, f.watchdog_hz = False, None
        if f.arm.is_moving():
            f._halt()
        f.mode = None

    # pacing and watchdog
    def initPeriod(self) -> datetime.timedelta:
        return _timedelta(self._f.time)

    def waitPeriod(self, arg0: datetime.timedelta) -> None:
        self._f._cycle()

    def getStepTime(self) -> float:
        return self._f.period

    def setWatchdog(self, min_frequency: float = 10.0) -> bool:
        if not self._f._can_command("setWatchdog", (min_frequency,)):
            return False
        self._f.watchdog_hz, self._f.last_kick = float(min_frequency), self._f.time
        return True

    def kickWatchdog(self) -> bool:
        if not self._f.connected:
            raise RuntimeError("RTDE control: not connected to the robot")
        self._f.last_kick = self._f.time
        return self._f.program_running

    # setup
    def setTcp(self, arg0: list[float]) -> bool:
        if not self._f._can_command("setTcp", (list(arg0),)):
            return False
        self._f.tcp_offset = vector_to_pose(arg0)
        return True

    def getTCPOffset(self) -> list[float]:
        return pose_to_vector(self._f.tcp_offset)

    def setPayload(self, arg0: float, arg1: list[float]) -> bool:
        if not self._f._can_command("setPayload", (arg0, list(arg1))):
            return False
        self._f.payload = (float(arg0), list(arg1))
        return True

    def zeroFtSensor(self) -> bool:
        return self._f._can_command("zeroFtSensor", ())

    # checks
    def isPoseWithinSafetyLimits(self, arg0: list[float]) -> bool:
        return self._f.reachable(vector_to_pose(arg0))

    def isJointsWithinSafetyLimits(self, arg0: list[float]) -> bool:
        q = np.asarray(arg0, dtype=float)
        return bool(q.shape == (6,) and np.all(np.abs(q) <= 2 * math.pi) and abs(q[2]) <= math.pi)

    def getForwardKinematics(self, q: list[float] = [], tcp_offset: list[float] = []) -> list[float]:  # noqa: B006
        f = self._f
        if len(q) == 0:
            T = f.base_T_flange()
        else:
            T = f.arm.kin.base_T_flange(np.asarray(q, dtype=float))
        return pose_to_vector(T @ (vector_to_pose(tcp_offset) if len(tcp_offset) else f.tcp_offset))

    def isSteady(self) -> bool:
        return not self._f.arm.is_moving()

    def getAsyncOperationProgress(self) -> int:
        return self._f.async_progress

    # motion
    def moveL(self, pose: list[float], speed: float = 0.25, acceleration: float = 1.2,
              asynchronous: bool = False) -> bool:
        f = self._f
        if not f._can_command("moveL", (list(pose), speed, acceleration, asynchronous)):
            return False
        if f._conflict("moveL", "move"):
            return False
        target = vector_to_pose(pose)
        if not f.reachable(target):
            return False
        f.arm.move_linear(f.to_arm_pose(target), speed, acceleration, asynchronous=True)
        return self._started(asynchronous)

    def moveJ(self, q: list[float], speed: float = 1.05, acceleration: float = 1.4, asynchronous: bool = False) -> bool:
        f = self._f
        if not f._can_command("moveJ", (list(q), speed, acceleration, asynchronous)):
            return False
        if f._conflict("moveJ", "move") or not self.isJointsWithinSafetyLimits(list(q)):
            return False
        f.arm.move_joint(np.asarray(q, dtype=float), speed, acceleration, asynchronous=True)
        return self._started(asynchronous)

    def _started(self, asynchronous: bool) -> bool:
        f = self._f
        f.mode, f.async_progress = "move", 0
        if asynchronous:
            return True
        while f.mode == "move" and f.connected and f.program_running:
            f._cycle()
        return f.safety_mode == SAFETY_NORMAL and f.connected

    def speedL(self, xd: list[float], acceleration: float = 0.25, time: float = 0.0) -> bool:
        f = self._f
        if not f._can_command("speedL", (list(xd), acceleration, time)):
            return False
        if f._conflict("speedL", "speed"):
            return False
        f.arm.speed_linear(f.to_arm_twist(np.asarray(xd, dtype=float)), accel=acceleration)
        f.mode = "speed"
        if time > 0:
            f.advance(time)
        return True

    def speedStop(self, a: float = 10.0) -> bool:
        f = self._f
        if not f._can_command("speedStop", (a,)):
            return False
        if f.mode == "speed":
            f.arm.stop(decel=a, asynchronous=True)
            f.mode = "stop" if f.arm.is_moving() else None  # the stop runs until the arm is at rest
        return True

    def stopL(self, a: float = 10.0, asynchronous: bool = False) -> None:
        f = self._f
        if f._can_command("stopL", (a, asynchronous)) and f.arm.is_moving():
            f.arm.stop(decel=a, asynchronous=True)
            f.mode = "stop"
            if not asynchronous:
                while f.arm.is_moving() and f.connected:
                    f._cycle()

    def stopJ(self, a: float = 2.0, asynchronous: bool = False) -> None:
        self.stopL(a, asynchronous)

    def triggerProtectiveStop(self) -> bool:
        self._f._protective_stop("triggered by the host")
        return True


class RTDEReceiveInterface(_Connection):
    """Fake of ``rtde_receive.RTDEReceiveInterface``: the controller's state (frozen while disconnected)."""

    def __init__(self, hostname: str, frequency: float = -1.0, variables: list[str] = [],  # noqa: B006
                 verbose: bool = False, use_upper_range_registers: bool = False, rt_priority: int = 0) -> None:
        super().__init__(hostname)
        self._last: dict[str, Any] = {}

    def _get(self, key: str, fn: Callable[[], Any]) -> Any:
        if self._open and self._f.connected:
            self._last[key] = fn()
        return self._last.get(key, fn())

    def initPeriod(self) -> datetime.timedelta:
        return _timedelta(self._f.time)

    def waitPeriod(self, arg0: datetime.timedelta) -> None:
        self._f._cycle()

    def getTimestamp(self) -> float:
        return self._get("t", lambda: self._f.stamp)

    def getActualQ(self) -> list[float]:
        return self._get("q", lambda: [float(v) for v in self._f.arm.joint_positions()])

    def getActualTCPPose(self) -> list[float]:
        return self._get("pose", lambda: pose_to_vector(self._f.tcp_pose()))

    def getActualTCPSpeed(self) -> list[float]:
        return self._get("speed", lambda: [float(v) for v in self._f.arm.tcp_twist()])

    def getActualTCPForce(self) -> list[float]:
        return self._get("force", lambda: [float(v) for v in self._f.force()])

    def getRobotMode(self) -> int:
        return self._get("mode", lambda: ROBOT_MODE_RUNNING)

    def getSafetyMode(self) -> int:
        return self._get("safety", lambda: self._f.safety_mode)

    def getSafetyStatusBits(self) -> int:
        return self._get("bits", lambda: 1 if self._f.safety_mode == SAFETY_NORMAL else (1 << 2) | (1 << 10))

    def isProtectiveStopped(self) -> bool:
        return self._get("pstop", lambda: self._f.safety_mode == SAFETY_PROTECTIVE_STOP)

    def isEmergencyStopped(self) -> bool:
        return self._get("estop", lambda: self._f.safety_mode == SAFETY_ROBOT_EMERGENCY_STOP)

    def getActualDigitalOutputBits(self) -> int:
        return sum(1 << i for (kind, i), v in self._f.outputs.items() if kind == "standard" and v)


class RTDEIOInterface(_Connection):
    """Fake of ``rtde_io.RTDEIOInterface``: digital outputs (one of them may drive the arm's gripper)."""

    def __init__(self, hostname: str, verbose: bool = False, use_upper_range_registers: bool = False) -> None:
        super().__init__(hostname)

    def _set(self, kind: str, arg0: int, arg1: bool) -> bool:
        f = self._f
        if not f.connected:
            raise RuntimeError("RTDE IO: not connected to the robot")
        f.commands.append((f.time, f"set{kind.capitalize()}DigitalOut", (arg0, arg1)))
        f.outputs[(kind, int(arg0))] = bool(arg1)
        if f.gripper_output is not None and f.gripper_output[:2] == (kind, int(arg0)):
            f.arm.gripper(open=bool(arg1) == f.gripper_output[2])
        return True

    def setStandardDigitalOut(self, arg0: int, arg1: bool) -> bool:
        return self._set("standard", arg0, arg1)

    def setToolDigitalOut(self, arg0: int, arg1: bool) -> bool:
        return self._set("tool", arg0, arg1)


def modules() -> SimpleNamespace:
    """The three fake modules as URRobot expects them (``.rtde_control``, ``.rtde_receive``, ``.rtde_io``)."""
    return SimpleNamespace(rtde_control=SimpleNamespace(RTDEControlInterface=RTDEControlInterface),
                           rtde_receive=SimpleNamespace(RTDEReceiveInterface=RTDEReceiveInterface),
                           rtde_io=SimpleNamespace(RTDEIOInterface=RTDEIOInterface))


#: (fake class, real module name, real class name) for the signature check.
FAKES = ((RTDEControlInterface, "rtde_control", "RTDEControlInterface"),
         (RTDEReceiveInterface, "rtde_receive", "RTDEReceiveInterface"),
         (RTDEIOInterface, "rtde_io", "RTDEIOInterface"))

__all__ = ["FakeUR", "RTDEControlInterface", "RTDEReceiveInterface", "RTDEIOInterface", "modules", "FAKES"]
