"""The real UR5 over ur_rtde: :class:`URRobot` implements :class:`~place_safe.robot.interface.Robot`.

Concept: three ur_rtde interfaces -- ``RTDEControlInterface`` (moveL, moveJ, speedL, speedStop, stopL,
watchdog, pacing with ``initPeriod``/``waitPeriod`` at the controller's rate), ``RTDEReceiveInterface``
(actual q, TCP pose, speed and force, robot and safety mode, protective stop, controller timestamp) and
``RTDEIOInterface`` (a gripper on a digital output; a Robotiq gripper talks to its URCap socket instead)
-- behind the narrow robot interface the placement code drives. The interfaces are injectable (or the
modules that make them), so the same code runs on :mod:`place_safe.drivers.ur5.fake_rtde` in CI.

Safety, in the order it is applied:

* Our own limits before every command (:class:`~place_safe.drivers.ur5.config.LimitsConfig`): speed and
  acceleration (clamped), the TCP workspace box, the deepest z a descent may reach and a keep-out below
  the sensed surface (:meth:`URRobot.set_surface`): a moveL target -- or, for speedL, the point where the
  arm would come to rest if it stopped now plus one watchdog period of travel -- outside them is refused
  before anything moves (``RobotFault``, not latched; a running speedL is stopped first).
* Every controller cycle (``step``, and the waits inside blocking commands): the watchdog is kicked;
  protective stop, emergency stop, a safety mode other than normal/reduced, a robot not running, a
  stopped control script, a lost connection, a stale controller timestamp, our force limit or a limit
  crossed during speedL -> the arm is stopped (where it can still be commanded) and a
  :class:`~place_safe.exceptions.RobotFault` is latched. The gripper is never opened on a fault and
  ``gripper(open=True)`` is refused while faulted.
* ``clear_fault`` reconnects after a lost connection (``reconnect_attempts`` tries) and restarts the control
  script, but refuses while the controller is still protective-stopped (unlock it on the pendant).
* ``dry_run``: only ``RTDEReceiveInterface`` is opened; every command prints the planned motion and returns
  without moving (the robot's state is read live, nothing is commanded).

Contact: every controller cycle the TCP force estimate goes through a
:class:`~place_safe.robot.contact_detector.ContactDetector` (the force along the tool axis, averaged over a
few cycles, against a threshold set from the noise measured at rest by :meth:`URRobot.zero_force`, with a
persistence test); :meth:`URRobot.contact_force` is its output (0.0 without confirmed contact). The
settings come from the robot file's ``[contact]`` section or the controller's defaults (CB3 / e-Series).

Threads on the controller: the ur_rtde control script runs one motion thread at a time; starting a motion
while a stop or another motion still runs is answered "Another thread is already controlling the robot"
and stops the script. So a motion command after an asynchronous stop first waits (servicing the watchdog)
until the arm is at rest, and a motion of the other kind is stopped with its own stop (``speedStop`` for
speedL, ``stopL`` for moveL/moveJ) and waited for. Every stop decelerates at most at
``limits.max_linear_accel``, or at ``motion.emergency_decel`` for a stop asked harder (obstacle, fault).

Watchdog: armed (``setWatchdog``) with the first motion command -- before it the arm is at rest by design
(connecting, opening the sensor, loading an estimator) -- and kicked every cycle of every wait from then on:
``step``, blocking moves, stops, the gripper's settle and its socket replies (the gripper gets
:meth:`URRobot.service` as its wait). :meth:`URRobot.disconnect` stops any motion, waits for rest and stops
the control script, so the watchdog never fires on the way out.

After a lost connection, :meth:`URRobot.reconnect` reads the controller's state (safety mode, protective
and emergency stop, robot mode, control script) before anything else and says what it found.

ur_rtde prints its own lines (e.g. "connect: Connection refused") from C++ to the terminal; the driver
captures file descriptors 1 and 2 while it connects and sends those lines to the ``place_safe.drivers.ur5``
log, so the user reads one error line.

Conventions: :mod:`place_safe.robot.interface` (4x4 base-frame poses, SI units). The controller's TCP is
set to the configuration's ``flange_T_tcp`` at connect, so ``getActualTCPPose`` is our TCP.
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import sys
import tempfile
import threading
import time as _time
from typing import Any, Callable, Iterator

import numpy as np

from place_safe.drivers.ur5.config import URConfig
from place_safe.drivers.ur5.gripper import Gripper, make_gripper
from place_safe.drivers.ur5.pose import pose_to_vector, vector_to_pose
from place_safe.exceptions import RobotFault
from place_safe.robot.contact_detector import ContactDetector
from place_safe.robot.interface import Robot, RobotLimits, check_pose, check_twist, clamp_twist, stop_decel
from place_safe.robot.kinematics import Kinematics

log = logging.getLogger("place_safe.drivers.ur5")

#: UR safety modes that allow motion (1 normal, 2 reduced) and names of the others (UR documentation).
_SAFE_MODES = (1, 2)
_SAFETY_NAMES = {3: "protective stop", 4: "recovery mode", 5: "safeguard stop", 6: "system emergency stop",
                 7: "robot emergency stop", 8: "safety violation", 9: "safety fault",
                 10: "joint ID validation", 11: "undefined safety mode", 12: "automatic-mode safeguard stop",
                 13: "three-position enabling stop"}
_ROBOT_RUNNING = 7
_ROBOT_MODES = {-1: "no controller", 0: "disconnected", 1: "confirm safety", 2: "booting", 3: "power off",
                4: "power on", 5: "idle", 6: "backdrive", 8: "updating firmware"}
#: m/s and cycles: a TCP slower than this for this many cycles in a row is at rest (besides isSteady).
_REST_SPEED, _REST_CYCLES = 1e-4, 5
_FORCE_BASELINE_SAMPLES = 50  # cycles at rest for the force offset and its spread (0.4 s on a CB3)


@contextlib.contextmanager
def captured_output(what: str) -> Iterator[None]:
    """Send what C/C++ code prints to file descriptors 1 and 2 meanwhile to the log (``what: line``) instead of
    the terminal (ur_rtde's own "connect: Connection refused" before our one-line error)."""
    try:
        sys.stdout.flush()
        sys.stderr.flush()
        saved = (os.dup(1), os.dup(2))
    except (OSError, ValueError, AttributeError):  # no real descriptors (embedded): leave them alone
        yield
        return
    tmp = tempfile.TemporaryFile()
    try:
        os.dup2(tmp.fileno(), 1)
        os.dup2(tmp.fileno(), 2)
        yield
    finally:
        try:
            import ctypes

            ctypes.CDLL(None).fflush(None)  # C stdio buffers (std::cout is synced with them)
        except Exception:  # noqa: BLE001 - best effort
            pass
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
        tmp.seek(0)
        text = tmp.read().decode("utf-8", "replace")
        tmp.close()
        for line in text.splitlines():
            if line.strip():
                log.info("%s: %s", what, line.strip())


def _import_modules() -> Any:
    """The installed ur_rtde modules (the ``[hw]`` extra)."""
    from types import SimpleNamespace

    try:
        import rtde_control
        import rtde_io
        import rtde_receive
    except ImportError as exc:
        raise RobotFault(f"ur_rtde is not installed ({exc}); pip install 'place-safe[hw]'") from None
    return SimpleNamespace(rtde_control=rtde_control, rtde_receive=rtde_receive, rtde_io=rtde_io)


def _with_timeout(fn: Callable[[], Any], timeout: float, what: str) -> Any:
    """Run a blocking connect call with a deadline (ur_rtde's constructors can hang on a dead host)."""
    box: dict[str, Any] = {}

    def run() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread
            box["error"] = exc

    th = threading.Thread(target=run, name=f"connect {what}", daemon=True)
    with captured_output(what):
        th.start()
        th.join(timeout)
    if th.is_alive():
        raise RobotFault(f"{what}: no answer within {timeout:g} s (is the robot on and reachable?)")
    if "error" in box:
        raise RobotFault(f"{what}: {str(box['error']).splitlines()[0] if str(box['error']) else box['error']!r} "
                         "(cannot connect: check the robot file's [connection] host, the network, and that the "
                         "pendant is in Remote Control)")
    return box["value"]


class URRobot(Robot):
    """A UR5 on ur_rtde (see the module docstring).

    Parameters
    ----------
    config:
        The robot file (:class:`URConfig`, e.g. ``URConfig.load("robots/ur5/real.toml")``).
    control, receive, io:
        Already-made interfaces (tests, or a caller that manages connections); else made at :meth:`connect`
        from ``modules`` (default: the installed ur_rtde).
    gripper:
        A :class:`~place_safe.drivers.ur5.gripper.Gripper`; default from ``config.gripper``.
    dry_run:
        Receive-only: print planned motions, command nothing.
    out:
        Where dry-run plans and notes are printed (default stderr).
    """

    def __init__(self, config: URConfig, *, control: Any = None, receive: Any = None, io: Any = None,
                 gripper: Gripper | None = None, modules: Any = None, dry_run: bool = False,
                 out: Callable[[str], None] | None = None, kinematics: Any = None) -> None:
        self.config = config
        lim = config.limits
        self.limits = RobotLimits(max_linear_speed=lim.max_linear_speed, max_linear_accel=lim.max_linear_accel,
                                  max_angular_speed=lim.max_angular_speed, max_angular_accel=lim.max_angular_accel,
                                  max_contact_force=lim.max_contact_force)
        self.tool = config.tool.frames()
        self.dry_run = bool(dry_run)
        self._modules = modules
        self._control, self._receive, self._io = control, receive, io
        self._gripper = gripper
        self._out = out or (lambda s: print(s, file=sys.stderr, flush=True))
        self._kin = kinematics
        self.period = 1.0 / config.connection.frequency
        self._fault: str | None = None
        self._lost = False
        self._mode: str | None = None  # "move", "speed" or None
        self._twist = np.zeros(6)
        self._accel = 0.5
        self._surface: tuple[np.ndarray, float] | None = None
        self.detector = ContactDetector(config.contact.settings(config.connection.controller))
        self._watchdog_armed = False
        self.last_state: str | None = None  # what reconnect() found on the controller
        self._stamp = (math.nan, 0)  # last controller timestamp, cycles it has not changed
        self._connected = False
        self.planned: list[str] = []  # dry-run plans, in order

    # ------------------------------------------------------------------------------------------
    # lifecycle
    # ------------------------------------------------------------------------------------------
    def connect(self) -> "URRobot":
        """Open the interfaces (with timeouts), set TCP, payload and watchdog, zero the force reading."""
        if self._connected:
            return self
        c = self.config.connection
        mods = None
        if self._receive is None or (not self.dry_run and (self._control is None or self._io is None)):
            mods = self._modules if self._modules is not None else _import_modules()
        host, freq, tmo = c.host, c.frequency, c.connect_timeout_s
        if self._receive is None:
            self._receive = _with_timeout(lambda: mods.rtde_receive.RTDEReceiveInterface(host, freq), tmo,
                                          f"RTDE receive at {host}")
        if not self.dry_run:
            if self._control is None:
                self._control = _with_timeout(lambda: mods.rtde_control.RTDEControlInterface(host, freq), tmo,
                                              f"RTDE control at {host}")
            if self._io is None and self.config.gripper.kind == "digital":
                self._io = _with_timeout(lambda: mods.rtde_io.RTDEIOInterface(host), tmo, f"RTDE IO at {host}")
            tool = self.config.tool
            self._ok(self._control.setTcp(pose_to_vector(self.tool.flange_T_tcp)), "setTcp")
            self._ok(self._control.setPayload(tool.payload_kg, list(tool.payload_cog)), "setPayload")
        if self._gripper is None:
            self._gripper = make_gripper(self.config.gripper, host, self._io)
        if not self.dry_run:
            self._gripper.bind_wait(self.service)
            if hasattr(self._gripper, "connect"):  # a socket gripper connects (and activates) before any motion
                self._gripper.connect()
        self._connected = True
        self._check_state()
        self.zero_force()
        return self

    def disconnect(self) -> None:
        """Stop any motion and wait for rest, stop the control script (so the watchdog cannot fire), close the
        gripper socket and every interface. Idempotent; never raises."""
        if self._control is not None and not self._lost and not self.dry_run and self._connected:
            try:
                if self._mode is not None and self._mode != "stopping":
                    self._stop_motion(self._decel(self._accel))
                if self._mode is not None:
                    self._wait_rest(2.0 + 1.0 / self._decel(self._accel), "stop before disconnecting")
            except Exception:  # noqa: BLE001 - best effort on the way out
                pass
            try:
                self._control.stopScript()
            except Exception:  # noqa: BLE001
                pass
            self._watchdog_armed = False
        for closer in (getattr(self._gripper, "close_connection", None),
                       getattr(self._control, "disconnect", None), getattr(self._receive, "disconnect", None),
                       getattr(self._io, "disconnect", None)):
            if closer is not None:
                try:
                    closer()
                except Exception:  # noqa: BLE001
                    pass
        self._connected = False

    def is_connected(self) -> bool:
        return self._connected and not self._lost

    def __enter__(self) -> "URRobot":
        return self.connect()

    def reconnect(self) -> None:
        """Reconnect every interface (``reconnect_attempts`` tries, ``reconnect_backoff_s`` apart)."""
        c = self.config.connection
        for attempt in range(c.reconnect_attempts + 1):
            ok = True
            for iface in (self._receive, self._control, self._io):
                if iface is not None and not iface.isConnected():
                    try:
                        ok = bool(_with_timeout(iface.reconnect, c.connect_timeout_s, "reconnect")) and ok
                    except RobotFault:
                        ok = False
            if ok:
                self._lost = False
                self._stamp = (math.nan, 0)
                self.last_state = self.describe_state()
                self._out(f"reconnected to the robot at {c.host}: {self.last_state}")
                return
            if attempt < c.reconnect_attempts and c.reconnect_backoff_s:
                _time.sleep(c.reconnect_backoff_s)
        raise RobotFault(f"cannot reconnect to the robot at {c.host} after {c.reconnect_attempts + 1} tries")

    def describe_state(self) -> str:
        """The controller's state in words: safety mode, emergency / protective stop, robot mode, control
        script (read first after a reconnect, before any command)."""
        r = self._receive
        parts = []
        try:
            safety = int(r.getSafetyMode())
            parts.append("safety mode " + ("normal" if safety == 1 else "reduced" if safety == 2
                                           else _SAFETY_NAMES.get(safety, str(safety))))
            if r.isEmergencyStopped():
                parts.append("EMERGENCY STOPPED")
            if r.isProtectiveStopped():
                parts.append("PROTECTIVE STOP (unlock it on the teach pendant)")
            mode = int(r.getRobotMode())
            parts.append("robot running" if mode == _ROBOT_RUNNING else
                         f"robot {_ROBOT_MODES.get(mode, f'mode {mode}')}")
            if self._control is not None:
                parts.append("control script running" if self._control.isProgramRunning()
                             else "control script stopped")
        except Exception as exc:  # noqa: BLE001 - the state could not be read: say so
            parts.append(f"state unreadable ({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})")
        return ", ".join(parts)

    # ------------------------------------------------------------------------------------------
    # faults
    # ------------------------------------------------------------------------------------------
    def fault(self) -> str | None:
        return self._fault

    def _latch(self, why: str) -> RobotFault:
        """Stop the arm (if it can still be commanded), latch ``why`` and return the error to raise."""
        if self._fault is None:
            self._fault = why
            if self._control is not None and not self._lost and self._mode is not None:
                try:
                    self._stop_motion(self.config.motion.emergency_decel)
                except Exception:  # noqa: BLE001 - the fault is what matters
                    pass
            self._mode = None
        return RobotFault(self._fault)

    def clear_fault(self) -> None:
        if self._fault is None:
            return
        if self._lost:
            self.reconnect()
        r = self._receive
        if r.isProtectiveStopped() or r.getSafetyMode() not in _SAFE_MODES:
            raise RobotFault("the controller is still stopped (" + self._safety_name()
                             + "): unlock it on the teach pendant, then clear the fault")
        if self._control is not None and not self._control.isProgramRunning():
            if not self._control.reuploadScript():
                raise RobotFault("cannot restart the ur_rtde control script on the controller")
            self._watchdog_armed = False  # a new script: armed again with the next motion
        self._fault = None
        self._mode = None

    def _safety_name(self) -> str:
        m = int(self._receive.getSafetyMode())
        return _SAFETY_NAMES.get(m, f"safety mode {m}")

    def _require_ok(self) -> None:
        if not self._connected:
            raise RobotFault("robot is not connected: call connect() (or use it as a context manager)")
        if self._fault is not None:
            raise RobotFault(f"robot is faulted ({self._fault}); clear the fault first")
        self._check_state()

    def _ok(self, result: Any, what: str) -> None:
        """A command's boolean answer: False means the controller refused it -> find out why, latch."""
        if result is False:
            self._check_state()
            raise self._latch(f"the controller refused {what} (control script not running or robot stopped)")

    def _check_state(self) -> None:
        """Latch a fault for anything that makes the robot unsafe to command (see the module docstring)."""
        if self._fault is not None:
            return
        r = self._receive
        c = self.config.connection
        for name, iface in (("receive", r), ("control", self._control), ("IO", self._io)):
            if iface is not None and not iface.isConnected():
                self._lost = True
                raise self._latch(f"lost the RTDE {name} connection to {c.host}")
        if r.isEmergencyStopped():
            raise self._latch("emergency stop")
        if r.isProtectiveStopped() or r.getSafetyMode() not in _SAFE_MODES:
            raise self._latch(f"{self._safety_name()} on the controller")
        mode = int(r.getRobotMode())
        if mode != _ROBOT_RUNNING:
            raise self._latch(f"robot is not running ({_ROBOT_MODES.get(mode, f'mode {mode}')})")
        if self._control is not None and not self._control.isProgramRunning():
            raise self._latch("the ur_rtde control script stopped on the controller (watchdog timeout or "
                              "a script error)")
        stamp = float(r.getTimestamp())
        last, n = self._stamp
        n = n + 1 if stamp == last else 0
        self._stamp = (stamp, n)
        if n > c.stale_cycles:
            self._lost = True
            raise self._latch(f"controller timestamp stuck at {stamp:.3f} s for {n} cycles (controller or link stalled)")
        f = float(np.linalg.norm(self.detector.filtered))
        if f > self.limits.max_contact_force:
            raise self._latch(f"contact force {f:.1f} N exceeds our limit {self.limits.max_contact_force:.1f} N")

    # ------------------------------------------------------------------------------------------
    # state
    # ------------------------------------------------------------------------------------------
    def _vec(self, values: Any, n: int, what: str) -> np.ndarray:
        v = np.asarray(values, dtype=float)
        if v.shape != (n,) or not np.all(np.isfinite(v)):
            raise self._latch(f"the controller sent an invalid {what}: {values!r}")
        return v

    def joint_positions(self) -> np.ndarray:
        return self._vec(self._receive.getActualQ(), 6, "joint vector")

    def tcp_pose(self) -> np.ndarray:
        if self.dry_run:  # the controller's TCP is not ours to set: flange from our kinematics
            if self._kin is None:
                self._kin = Kinematics()
            return self._kin.base_T_flange(self.joint_positions()) @ self.tool.flange_T_tcp
        return vector_to_pose(self._vec(self._receive.getActualTCPPose(), 6, "TCP pose"))

    def sensor_pose(self) -> np.ndarray:
        return self.tcp_pose() @ self.tool.tcp_T_sensor

    def cup_pose(self) -> np.ndarray:
        return self.tcp_pose() @ self.tool.tcp_T_cup

    def tcp_twist(self) -> np.ndarray:
        return self._vec(self._receive.getActualTCPSpeed(), 6, "TCP speed")

    def _raw_force(self) -> np.ndarray:
        return self._vec(self._receive.getActualTCPForce(), 6, "TCP force")[:3]

    def force_vector(self) -> np.ndarray:
        """One raw TCP force sample (N, base frame) minus the reading at rest taken by :meth:`zero_force`."""
        return self._raw_force() - self.detector.offset

    def contact_force(self) -> float:
        """N: the contact detector's output -- the averaged force against the tool axis once contact is
        confirmed, else 0.0 (see :mod:`place_safe.robot.contact_detector`)."""
        return self.detector.contact_force()

    def contact_latency(self) -> float | None:
        """s: the contact detector's 10 N touch latency (95th percentile) at the noise :meth:`zero_force` measured
        (where it raised the threshold beyond the robot file's ``[contact] noise_std``); None before the first
        zeroing (``connect`` zeroes)."""
        return self.detector.touch_latency() if self.detector.rest_samples else None

    def zero_force(self, samples: int = _FORCE_BASELINE_SAMPLES) -> np.ndarray:
        """Sample the TCP force over ``samples`` cycles at rest: the mean is subtracted from now on (payload and
        sensor offset; the CB3's estimate is off by several newtons otherwise), the per-axis spread sets the
        contact detector's threshold (never below the configured noise). Returns the mean."""
        acc = []
        for _ in range(max(2, int(samples))):
            acc.append(self._raw_force())
            self._wait_cycle(detect=False)
        offset, spread = self.detector.zero(acc)
        log.info("force at rest: offset %s N, spread %s N per axis; contact threshold %.1f N",
                 np.round(offset, 2).tolist(), np.round(spread, 2).tolist(), self.detector.threshold)
        return offset

    @property
    def force_noise(self) -> np.ndarray:
        """N per axis: the spread of the TCP force measured at rest by :meth:`zero_force`."""
        return self.detector.rest_std.copy()

    def time(self) -> float:
        return float(self._receive.getTimestamp())

    def is_moving(self) -> bool:
        if self.dry_run or self._mode is None:
            return False
        if self._mode == "move" and self._control.getAsyncOperationProgress() < 0 and self._control.isSteady():
            self._mode = None
        elif self._mode == "stopping" and self._control.isSteady():
            self._mode = None
        return self._mode is not None

    # ------------------------------------------------------------------------------------------
    # limits
    # ------------------------------------------------------------------------------------------
    def set_surface(self, plane: Any | None) -> None:
        """Keep-out below a sensed surface: ``(n, d)`` in the base frame (``n . x = d``, n up) or None."""
        if plane is None:
            self._surface = None
            return
        n, d = np.asarray(plane[0], dtype=float), float(plane[1])
        if n.shape != (3,) or not np.all(np.isfinite(n)) or not math.isfinite(d) or np.linalg.norm(n) == 0:
            raise ValueError(f"surface must be (normal (3,), offset) finite; got {plane!r}")
        k = np.linalg.norm(n)
        self._surface = (n / k, d / k)

    def check_tcp_position(self, p: np.ndarray, what: str, descent: bool = False) -> str | None:
        """Why TCP position ``p`` (base frame) breaks our limits, or None."""
        lim = self.config.limits
        lo, hi = np.asarray(lim.workspace_min), np.asarray(lim.workspace_max)
        if np.any(p < lo) or np.any(p > hi):
            return (f"{what} {np.round(p, 3).tolist()} m is outside the workspace box "
                    f"{list(lim.workspace_min)}..{list(lim.workspace_max)} m")
        if descent and p[2] < lim.min_descent_z:
            return f"{what} z {p[2]:.3f} m is below the deepest allowed descent {lim.min_descent_z:.3f} m"
        if self._surface is not None:
            n, d = self._surface
            cup = p + (self.tcp_pose()[:3, :3] @ self.tool.tcp_T_cup[:3, 3])
            depth = d - float(n @ cup)
            if depth > lim.surface_keepout:
                return (f"{what} would put the cup bottom {1000 * depth:.1f} mm below the sensed surface "
                        f"(keep-out {1000 * lim.surface_keepout:.1f} mm)")
        return None

    def _refuse(self, why: str) -> RobotFault:
        if self._mode == "speed" and not self.dry_run:
            self._stop_motion(self.config.motion.emergency_decel)
        return RobotFault(why)

    def _decel(self, requested: float) -> float:
        """The deceleration a stop asked at ``requested`` m/s^2 gets: as asked up to ``max_linear_accel``; a
        harder one is an emergency stop, at most ``motion.emergency_decel``."""
        return stop_decel(requested, self.config.limits.max_linear_accel, self.config.motion.emergency_decel)

    def _arm_watchdog(self) -> None:
        if not self._watchdog_armed:
            self._ok(self._control.setWatchdog(self.config.watchdog_hz), "setWatchdog")
            self._watchdog_armed = True

    def _before_motion(self, kind: str, accel: float) -> None:
        """Make way for a motion of ``kind`` ("move" or "speed"): the controller runs one motion thread at a
        time, so a running stop is waited for and a running motion of the other kind (or a move) is stopped
        with its own stop and waited for. Arms the watchdog."""
        self._arm_watchdog()
        if self._mode is None or (self._mode == "speed" and kind == "speed"):
            return
        if self._mode != "stopping":
            self._stop_motion(self._decel(accel))
        self._wait_rest(2.0 + 1.0 / self._decel(accel), "the stop before the next motion")

    def _check_rate(self, value: float, limit: float, what: str) -> float:
        if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
            raise ValueError(f"{what} must be a positive finite number; got {value!r}")
        return min(float(value), limit)

    # ------------------------------------------------------------------------------------------
    # motion
    # ------------------------------------------------------------------------------------------
    def move_linear(self, pose: Any, speed: float = 0.05, accel: float = 0.2, asynchronous: bool = False) -> None:
        goal = check_pose(pose, "move_linear target")
        v = self._check_rate(speed, self.limits.max_linear_speed, "speed")
        a = self._check_rate(accel, self.limits.max_linear_accel, "accel")
        self._require_ok()
        start = self.tcp_pose()
        why = self.check_tcp_position(goal[:3, 3], "moveL target", descent=goal[2, 3] < start[2, 3])
        if why:
            raise self._refuse(why)
        vec = pose_to_vector(goal)
        if self.dry_run:
            self._plan(f"moveL {np.round(vec, 4).tolist()} speed {v:g} m/s accel {a:g} m/s^2 "
                       f"({1000 * np.linalg.norm(goal[:3, 3] - start[:3, 3]):.1f} mm)")
            return
        if not self._control.isPoseWithinSafetyLimits(vec):
            raise self._refuse(f"moveL target {np.round(vec, 4).tolist()} is outside the controller's safety limits "
                               "or unreachable")
        self._before_motion("move", a)
        self._ok(self._control.moveL(vec, v, a, True), "moveL")
        self._mode, self._accel = "move", a
        if not asynchronous:
            dist = float(np.linalg.norm(goal[:3, 3] - start[:3, 3]))
            self._wait_idle(dist / v + 2 * v / a + 2.0, "moveL")

    def move_joint(self, q: Any, speed: float = 1.05, accel: float = 1.4, asynchronous: bool = False) -> None:
        goal = np.asarray(q, dtype=float)
        if goal.shape != (6,) or not np.all(np.isfinite(goal)):
            raise ValueError(f"move_joint target must be 6 finite joint angles (rad); got {q!r}")
        lim = self.config.limits
        v = self._check_rate(speed, lim.max_joint_speed, "speed")
        a = self._check_rate(accel, lim.max_joint_accel, "accel")
        self._require_ok()
        lo, hi = np.asarray(self.limits.joint_lower), np.asarray(self.limits.joint_upper)
        if np.any(goal < lo) or np.any(goal > hi):
            raise self._refuse(f"moveJ target {np.round(goal, 4).tolist()} is outside the joint limits")
        if self._kin is None:
            self._kin = Kinematics()
        T = self._kin.base_T_flange(goal) @ self.tool.flange_T_tcp
        why = self.check_tcp_position(T[:3, 3], "moveJ target", descent=T[2, 3] < self.tcp_pose()[2, 3])
        if why:
            raise self._refuse(why)
        if self.dry_run:
            self._plan(f"moveJ {np.round(goal, 4).tolist()} speed {v:g} rad/s accel {a:g} rad/s^2")
            return
        self._before_motion("move", self.limits.max_linear_accel)
        self._ok(self._control.moveJ([float(x) for x in goal], v, a, True), "moveJ")
        self._mode, self._accel = "move", a
        if not asynchronous:
            span = float(np.abs(goal - self.joint_positions()).max())
            self._wait_idle(span / v + 2 * v / a + 2.0, "moveJ")

    def _stop_point(self, twist: np.ndarray, accel: float) -> np.ndarray:
        """Where the TCP comes to rest if it runs at ``twist`` for one watchdog period and then brakes."""
        v = twist[:3]
        s = float(np.linalg.norm(v))
        p = self.tcp_pose()[:3, 3]
        if s == 0:
            return p
        return p + v * (1.0 / self.config.watchdog_hz + self.period) + v / s * (s * s / (2 * accel))

    def speed_linear(self, twist: Any, accel: float = 0.5, duration: float | None = None) -> None:
        v = check_twist(twist)
        a = self._check_rate(accel, self.limits.max_linear_accel, "accel")
        if duration is not None and not (math.isfinite(duration) and duration >= 0):
            raise ValueError(f"duration must be None or a finite number of seconds >= 0; got {duration!r}")
        lim = self.limits
        clamp_twist(v, lim)
        self._require_ok()
        why = self.check_tcp_position(self._stop_point(v, a), "speedL stopping point", descent=v[2] < 0)
        if why:
            raise self._refuse(why)
        if self.dry_run:
            self._plan(f"speedL {np.round(v, 4).tolist()} accel {a:g}" + (f" for {duration:g} s" if duration else ""))
            return
        self._before_motion("speed", a)
        self._ok(self._control.speedL([float(x) for x in v], a, 0.0), "speedL")
        self._mode, self._twist, self._accel = "speed", v, a
        if duration is not None:
            self.step(duration)
            self.stop(decel=a)

    def stop(self, decel: float = 1.0, asynchronous: bool = False) -> None:
        """Decelerate to rest at ``decel`` m/s^2 -- at most ``limits.max_linear_accel``, or for a harder request
        an emergency stop at most at ``motion.emergency_decel``. A stop already running is not sent again."""
        d = self._decel(self._check_rate(decel, 50.0, "decel"))
        if self.dry_run:
            self._plan(f"stop decel {d:g}")
            return
        if self._mode is None or self._fault is not None:
            return
        speed = float(np.linalg.norm(self._twist[:3]))
        if self._mode != "stopping":
            self._stop_motion(d)
        if not asynchronous:
            self._wait_rest(speed / d + 1.0, "stop")

    def _stop_motion(self, decel: float) -> None:
        """The stop for the running mode: ``speedStop`` ends speedL, ``stopL`` an asynchronous moveL/moveJ."""
        c = self._control
        d = min(float(decel), self.config.motion.emergency_decel)
        if self._mode == "speed":
            c.speedStop(d)
        elif self._mode == "move":
            c.stopL(d, True)
        self._mode = "stopping"
        self._twist = np.zeros(6)

    def _wait_rest(self, timeout: float, what: str) -> None:
        """Service the connection until the arm is at rest (isSteady) after a stop."""
        if self._mode is None:
            return
        self._mode = "stopping"
        self._wait_idle(timeout, what, steady=True)

    def service(self, dt: float) -> None:
        """Let ``dt`` s pass with the arm at rest by design (the gripper's settle, a dwell): every controller
        cycle the watchdog is kicked, the force read and the state checked (faults latch)."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0; got {dt!r}")
        for _ in range(max(1, int(math.ceil(dt / self.period)))):
            self._wait_cycle()
            if self._fault is None:
                self._check_state()

    def _wait_idle(self, timeout: float, what: str, steady: bool = False) -> None:
        t_end = self.time() + timeout
        n_max = int(math.ceil(timeout / self.period)) + 10
        still = 0  # cycles in a row with the TCP at rest by its measured speed
        for _ in range(n_max):
            self._wait_cycle()
            self._check_state()
            if steady or self._mode == "stopping":
                # at rest: the controller says so, or the measured TCP speed has been ~0 for REST_CYCLES cycles
                # (a controller whose isSteady stays False outside position mode still ends the wait)
                still = still + 1 if float(np.linalg.norm(self.tcp_twist()[:3])) < _REST_SPEED else 0
                done = self._control.isSteady() or still >= _REST_CYCLES
            else:
                done = self._control.getAsyncOperationProgress() < 0 and self._control.isSteady()
            if done:
                self._mode = None
                return
            if self.time() > t_end:
                break
        raise self._latch(f"{what} did not finish within {timeout:.1f} s")

    def step(self, dt: float) -> None:
        """Service the connection for ``dt`` seconds: one ``initPeriod``/``waitPeriod`` cycle per controller
        period, kicking the watchdog and checking the state (and our limits during speedL) every cycle."""
        if not (math.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be a finite number of seconds >= 0; got {dt!r}")
        if not self._connected:
            raise RobotFault("robot is not connected: call connect() first")
        for _ in range(max(1, int(round(dt / self.period)))):
            self._wait_cycle()
            if self._fault is not None:
                continue
            self._check_state()
            if self._mode == "speed":
                why = self.check_tcp_position(self._stop_point(self._twist, self._accel), "speedL stopping point",
                                              descent=self._twist[2] < 0)
                if why:
                    raise self._latch(why)

    def _wait_cycle(self, detect: bool = True) -> None:
        """One controller cycle: kick the watchdog, wait for the period, feed the contact detector."""
        iface = self._control if self._control is not None else self._receive
        try:
            t0 = iface.initPeriod()
            if self._control is not None and not self._lost:
                self._control.kickWatchdog()
            iface.waitPeriod(t0)
        except RuntimeError as exc:
            self._lost = True
            raise self._latch(f"lost the connection to the controller ({exc})") from None
        if detect and not self._lost:
            try:
                force = self._receive.getActualTCPForce()
                pose = self._receive.getActualTCPPose()
                axis = vector_to_pose(pose)[:3, 2]  # the tool axis: the direction the cup moves down along
            except Exception:  # noqa: BLE001 - a bad reading is a fault, found by _check_state / _vec
                return
            self.detector.update(np.asarray(force, dtype=float)[:3], axis)

    # ------------------------------------------------------------------------------------------
    # gripper
    # ------------------------------------------------------------------------------------------
    def gripper(self, open: bool) -> None:
        if open and self._fault is not None:
            raise RobotFault(f"refusing to open the gripper: robot is faulted ({self._fault})")
        if self.dry_run:
            self._plan(self._gripper.describe(open) if self._gripper is not None else f"gripper open={open}")
            return
        self._require_ok()
        if open:
            self._gripper.open()
        else:
            self._gripper.close()

    def _plan(self, text: str) -> None:
        self.planned.append(text)
        self._out(f"[dry run] {text}")


__all__ = ["URRobot"]
