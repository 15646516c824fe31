"""The placement loop: frame source -> estimator -> fusion -> decision -> robot, once per control tick.

Concept: :class:`PlacementLoop` is the one road from the sensor to the gripper, the same object on the
real UR5 (ur-rtde robot, TMF8820 over I2C), in MuJoCo (``SimRobot`` + ``SimToF``) and in scenario runs.
The caller chooses the robot, the frame source, the estimator and the tool frames; the loop owns:

* the **newest-estimate buffer** (:class:`EstimatePipeline`): for a real source a reader thread
  reads frames and estimates their planes off the control thread, keeping only the newest result, so a
  125 Hz tick never blocks on I/O or on the solver; a source driven by the robot's clock (the
  simulated sensor, ``clock_domain == "robot"``) is polled once per tick instead -- on a helper thread
  waited for at most :data:`READ_BOUND` seconds, so a source that blocks is a dead sensor, not a hung
  loop -- and estimated inline;
* the **clock map** (:class:`ClockMap`): frame stamps are on the source's clock (host
  ``time.monotonic`` for hardware); the loop converts them to the robot's clock before anything
  compares them with robot time;
* the **pose at the measurement time** (:class:`PoseHistory`): the TCP pose recorded every tick,
  interpolated at the frame's stamp, times the configured ``tcp_T_sensor`` (a frame is read ~0.1 s
  after it was measured: 8 mm of travel at approach speed);
* **frame gating**: frames whose stamp is not finite, lies in the future, is older than
  ``max_frame_age`` or is not later than the newest one already used (duplicates, out-of-order) are
  dropped with a reason, so a frozen or replaying sensor cannot count as fresh evidence;
* **command dispatch** (speedL / stopL / open gripper) and a failed command becoming a fault;
* the **transition and frame logs** and the :class:`LoopResult`;
* the **failure policy**: any exception class from the robot, the source or the estimator ends in a safe
  stop with the reason; an interrupt on the control thread (Ctrl-C) is re-raised after it (see
  :class:`PlacementLoop`).

Timing: ``tick()`` lets one control period pass (``robot.step(period)``: physics in simulation, the
controller's ``waitPeriod`` on the real arm), then reads the newest estimate, updates the fusion, runs
one :meth:`~place_safe.placement.machine.PlacementMachine.step` and dispatches its command.
Conventions: SI units, base-frame 4x4 poses (see :mod:`place_safe.robot.interface`).
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from place_safe.exceptions import RobotFault, SensorTimeout
from place_safe.fusion.plane_filter import PlaneFilter
from place_safe.fusion.surface_map import MIN_INLIERS, SurfaceMap
from place_safe.placement.machine import CommandKind, PlacementConfig, PlacementMachine, RobotState
from place_safe.robot.tool import ToolFrames

log = logging.getLogger("place_safe.placement.loop")

#: s, control period (125 Hz, the UR CB3 controller's rate).
CONTROL_PERIOD = 0.008
#: Control ticks of pose history kept for stamp lookup (2 s at 125 Hz; frames are ~0.1 s old).
POSE_HISTORY = 250
#: Clock-offset samples kept by :class:`ClockMap`.
CLOCK_SAMPLES = 64
#: Zones still on the known surface from which a frame gives the surface's height (with the remembered
#: slope) when clutter or a step covers the others.
MIN_ON_KNOWN = 3
#: rad: the slope uncertainty of such a height-only estimate (it measures no slope).
KNOWN_SLOPE_STD = math.radians(5.0)
#: m: the least height uncertainty per zone of such an estimate.
KNOWN_HEIGHT_STD = 0.0005
#: s (host clock): the longest a read of a robot-clock source may take before the loop goes on without it
#: (a simulated sensor answers in milliseconds; one that blocks is a dead sensor, not a reason to hang).
READ_BOUND = 2.0
#: Exceptions that are a request to stop the program (Ctrl-C, ``sys.exit``): on the control thread the loop
#: makes its safe stop and then re-raises them; raised by a source or an estimator on a reader thread they
#: are that part's failure like any other.
INTERRUPTS = (KeyboardInterrupt, SystemExit)


def describe_exception(exc: BaseException) -> str:
    """``Type: first line of the message`` of any exception, even one whose ``str`` raises."""
    try:
        text = str(exc).strip()
    except BaseException:  # noqa: BLE001 - a broken __str__ must not break the report of it
        text = ""
    name = type(exc).__name__
    return f"{name}: {text.splitlines()[0]}" if text else name


def _is_interrupt_here(exc: BaseException) -> bool:
    """An interrupt raised on the main thread (a real Ctrl-C or exit request), to be re-raised after a safe stop."""
    return isinstance(exc, INTERRUPTS) and threading.current_thread() is threading.main_thread()


# ---------------------------------------------------------------------------------------------
# clocks and poses
# ---------------------------------------------------------------------------------------------
class ClockMap:
    """Maps stamps on a source's clock to the robot's clock.

    ``domain == "robot"``: the source stamps on the robot's clock already (simulation): identity.
    ``domain == "monotonic"``: the source stamps with the host's ``time.monotonic()``. Each tick the
    loop observes ``(robot.time(), host_now)``; the robot's time is the stamp of its newest state
    packet, so ``robot - host`` is low by up to one packet period and the offset is the largest of the
    recent samples. Until the first observation the map is undefined and returns NaN.
    """

    def __init__(self, domain: str = "monotonic", samples: int = CLOCK_SAMPLES) -> None:
        if domain not in ("robot", "monotonic"):
            raise ValueError(f"clock domain must be 'robot' or 'monotonic', got {domain!r}")
        self.domain = domain
        self._offsets: deque[float] = deque(maxlen=samples)

    def observe(self, robot_time: float, host_time: float) -> None:
        off = float(robot_time) - float(host_time)
        if math.isfinite(off):
            self._offsets.append(off)

    @property
    def offset(self) -> float:
        if self.domain == "robot":
            return 0.0
        return max(self._offsets) if self._offsets else math.nan

    def to_robot(self, stamp: Any) -> float:
        """The robot-clock time of a source stamp (NaN if it cannot be converted)."""
        try:
            s = float(stamp)
        except (TypeError, ValueError):
            return math.nan
        return s + self.offset


class PoseHistory:
    """Poses recorded at increasing times; :meth:`at` interpolates (linear position, slerp rotation).

    A sample at a time not later than the newest one replaces it (a frozen clock keeps one entry).
    """

    def __init__(self, maxlen: int = POSE_HISTORY, tolerance: float = CONTROL_PERIOD / 2) -> None:
        self._t: deque[float] = deque(maxlen=maxlen)
        self._T: deque[np.ndarray] = deque(maxlen=maxlen)
        self.tolerance = tolerance

    def add(self, t: float, T: Any) -> None:
        try:
            T = np.asarray(T, dtype=float)
            t = float(t)
        except (TypeError, ValueError):
            return
        if not (math.isfinite(t) and T.shape == (4, 4) and np.all(np.isfinite(T))):
            return
        while self._t and t <= self._t[-1]:
            self._t.pop()
            self._T.pop()
        self._t.append(float(t))
        self._T.append(T.copy())

    def at(self, t: float) -> np.ndarray | None:
        """Pose at ``t``; None if ``t`` is not finite or outside the recorded span (by more than
        ``tolerance``)."""
        if not self._t or not math.isfinite(t):
            return None
        ts = np.fromiter(self._t, float)
        if t < ts[0] - self.tolerance or t > ts[-1] + self.tolerance:
            return None
        i = int(np.searchsorted(ts, t))
        if i <= 0:
            return self._T[0].copy()
        if i >= len(ts):
            return self._T[-1].copy()
        from scipy.spatial.transform import Rotation, Slerp

        t0, t1 = ts[i - 1], ts[i]
        A, B = self._T[i - 1], self._T[i]
        s = (t - t0) / (t1 - t0)
        T = np.eye(4)
        T[:3, 3] = (1 - s) * A[:3, 3] + s * B[:3, 3]
        T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]])))([s]).as_matrix()[0]
        return T


#: The fault the machine sees when ``robot.fault()`` itself fails.
_NO_ANSWER = "robot does not answer"


def clock_domain_of(source: Any) -> str:
    """A source's ``clock_domain`` ("robot" or "monotonic", the default when it has none); any other value
    (or an attribute that raises) is an :class:`~place_safe.exceptions.ArgumentTypeError`."""
    from place_safe.exceptions import ArgumentTypeError

    try:
        domain = getattr(source, "clock_domain", "monotonic")
    except BaseException as exc:  # noqa: BLE001 - a property that raises is a broken source
        if isinstance(exc, INTERRUPTS):
            raise
        raise ArgumentTypeError(f"source.clock_domain raised {describe_exception(exc)}") from None
    if domain not in ("robot", "monotonic"):
        raise ArgumentTypeError(f"source.clock_domain must be 'robot' or 'monotonic', got {domain!r}")
    return domain


# ---------------------------------------------------------------------------------------------
# newest-estimate buffer
# ---------------------------------------------------------------------------------------------
@dataclass
class Measurement:
    """One frame and its plane estimate, with when it arrived (host monotonic seconds)."""

    frame: Any
    estimate: Any
    arrived: float


class EstimatePipeline:
    """Reads frames from a source and estimates their planes; :meth:`take` returns the newest result.

    ``threaded=True`` (default for sources whose ``clock_domain`` is not ``"robot"``): a daemon
    thread loops ``source.read(timeout)`` + ``estimator.estimate``; results that were never taken are
    counted in ``overwritten``. ``threaded=False``: :meth:`take` polls ``source.read(0)`` and estimates
    inline (sources that advance with the robot's clock). The poll runs on a helper thread and is waited
    for at most ``read_bound`` seconds (host clock): a source that blocks in ``read`` is a dead sensor
    (``error`` says so, later takes return None at once until the read comes back), never a hung loop.
    Source errors other than a timeout -- any exception class, ``BaseException`` subclasses included --
    are kept in ``error`` (the loop refuses on a dead sensor); the thread keeps trying with a back-off.
    """

    def __init__(self, source: Any, estimator: Any, threaded: bool | None = None, read_timeout: float = 0.1,
                 clock: Callable[[], float] = time.monotonic, read_bound: float = READ_BOUND) -> None:
        self.source, self.estimator = source, estimator
        self.threaded = (clock_domain_of(source) != "robot") if threaded is None else bool(threaded)
        self.read_timeout = read_timeout
        self.read_bound = float(read_bound)
        self.clock = clock
        self.blocked = 0  # robot-clock reads that did not return within read_bound
        self._worker: threading.Thread | None = None
        self._request = threading.Event()
        self._done = threading.Event()
        self._pending = False
        self._waiting_out = False
        self._polled: tuple[bool, Any] | None = None
        self.frames = 0
        self.overwritten = 0
        self.timeouts = 0
        self.errors = 0
        self.error: str | None = None
        self._latest: Measurement | None = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._ended = False

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> "EstimatePipeline":
        if self.threaded and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="place-safe-sensor", daemon=True)
            self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._request.set()  # wakes the robot-clock helper so it can end
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._worker is not None:
            self._worker.join(timeout=0.05 if self._pending else 1.0)  # a blocked read is left behind (daemon)
            self._worker = None

    # -- work ----------------------------------------------------------------------------------
    def _poll(self, timeout: float) -> tuple[bool, Any]:
        """``(True, frame)`` or ``(False, None)`` after a timeout, the end or an error of ``source.read``.

        Never raises: every exception class is the source's failure (``error``) -- except an interrupt on
        the main thread (Ctrl-C), which is re-raised for the loop's safe stop."""
        try:
            return True, self.source.read(timeout)
        except SensorTimeout:
            self.timeouts += 1
        except StopIteration:
            self._ended = True
        except BaseException as exc:  # a dead bus, a driver bug, a BaseException subclass: refuse, not crash
            if _is_interrupt_here(exc):
                raise
            self.errors += 1
            self.error = describe_exception(exc)
        return False, None

    def _estimate(self, frame: Any) -> Measurement:
        self.frames += 1
        try:
            est = self.estimator.estimate(frame)
        except BaseException as exc:  # estimators never raise for bad data; a bug must not stop the loop
            if _is_interrupt_here(exc):
                raise
            from place_safe.recovery.estimator import PlaneEstimate

            est = PlaneEstimate(None, reason=f"estimator failed: {describe_exception(exc)}")
        self.error = None
        return Measurement(frame, est, self.clock())

    def _read_one(self, timeout: float) -> Measurement | None:
        ok, frame = self._poll(timeout)
        return self._estimate(frame) if ok else None

    # -- robot-clock sources: one read at a time on a helper thread, waited for at most read_bound --------
    def _serve(self) -> None:
        while True:
            self._request.wait()
            self._request.clear()
            if self._stop.is_set():
                return
            self._polled = self._poll(0.0)
            self._done.set()

    def _bounded_read(self) -> Measurement | None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._serve, name="place-safe-sensor-poll", daemon=True)
            self._worker.start()
        if not self._pending:
            self._done.clear()
            self._pending = True
            self._request.set()
        if not self._done.wait(0.0 if self._waiting_out else self.read_bound):
            if not self._waiting_out:
                self._waiting_out = True
                self.blocked += 1
                self.errors += 1
                self.error = (f"source did not return from read() within {self.read_bound:g} s "
                              "(blocked: treated as a dead sensor)")
            return None
        self._pending = self._waiting_out = False
        (ok, frame), self._polled = self._polled or (False, None), None
        return self._estimate(frame) if ok else None

    def _run(self) -> None:
        backoff = 0.01
        while not self._stop.is_set() and not self._ended:
            m = self._read_one(self.read_timeout)
            if m is None:
                if self.error is not None:
                    self._stop.wait(backoff)
                    backoff = min(backoff * 2, 0.5)
                continue
            backoff = 0.01
            with self._lock:
                if self._latest is not None:
                    self.overwritten += 1
                self._latest = m

    def take(self) -> Measurement | None:
        """The newest measurement not taken before, or None (never blocks)."""
        if not self.threaded:
            return None if (self._ended or self._stop.is_set()) else self._bounded_read()
        with self._lock:
            m, self._latest = self._latest, None
        return m


# ---------------------------------------------------------------------------------------------
# the loop
# ---------------------------------------------------------------------------------------------
@dataclass
class LoopResult:
    """What one placement did, from the loop's point of view (SI units)."""

    outcome: str  # "released", "refused" or "timeout"
    reason: str  # the deciding transition's reason (or why it timed out)
    final_phase: str
    robot_seconds: float  # robot-clock time from start to finish
    ticks: int
    frames: int  # measurements taken from the pipeline
    frames_used: int  # measurements that passed the gating and reached the fusion
    planes: int  # planes the fusion accepted
    dropped: dict[str, int] = field(default_factory=dict)  # frames not used, by reason
    contact_force_peak: float = 0.0
    transitions: list[dict] = field(default_factory=list)
    frame_log: list[dict] = field(default_factory=list)
    budget: dict[str, float] = field(default_factory=dict)  # s spent on each part (PlacementMachine.budget)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


def within_robot_limits(config: PlacementConfig, robot: Any) -> PlacementConfig:
    """``config`` with its speeds and accelerations capped at the robot's ``limits`` (``max_linear_speed``,
    ``max_linear_accel``), so that the descent profile is planned with the braking the arm really has
    (a driver would clip a faster command and the arm would then stop later than planned). A robot
    without readable limits leaves the config as it is."""
    import dataclasses

    try:
        lim = getattr(robot, "limits", None)
        v = getattr(lim, "max_linear_speed", None)
        a = getattr(lim, "max_linear_accel", None)
    except Exception:  # a robot whose limits cannot be read: its driver clips what it must
        v = a = None
    ok = (lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0)
    changes: dict[str, float] = {}
    if ok(v):
        for name in ("approach_speed", "descend_speed", "survey_speed", "retreat_speed", "near_surface_speed"):
            if getattr(config, name) > v:
                changes[name] = float(v)
    if ok(a):
        for name in ("accel", "lateral_accel"):
            if getattr(config, name) > a:
                changes[name] = float(a)
    return dataclasses.replace(config, **changes) if changes else config


class PlacementLoop:
    """One placement: ``PlacementLoop(robot, source, estimator, tool, config).run()`` (see module doc).

    Parameters
    ----------
    robot: a :class:`~place_safe.robot.interface.Robot` (connected by the caller or by ``run``).
    source: a :class:`~place_safe.io.source.FrameSource`; its ``clock_domain`` says how stamps are read.
    estimator: a plane estimator (``estimate(frame) -> PlaneEstimate``).
    tool: tool frames (default: ``robot.tool``, i.e. the robot's configuration).
    config: placement thresholds and speeds.
    period: control period in seconds (default 8 ms).
    max_frame_age: s; frames measured longer ago than this (robot clock) are dropped as stale.
    log_frames: keep a per-frame log in the result.
    read_bound: s (host clock) a robot-clock source's ``read`` may take before it counts as dead.

    Arguments of the wrong kind (``config="x"``, a robot without ``step``) raise
    :class:`~place_safe.exceptions.ArgumentTypeError` saying what was expected.

    Failure policy: :meth:`tick` and :meth:`run` never block on the source (see :class:`EstimatePipeline`)
    and never raise for what the robot, the source or the estimator do: any exception class ends in a
    safe stop (``stopL``, the cup held, the machine aborted) with the reason in the result. The one
    exception is an interrupt on the control thread (``KeyboardInterrupt``: Ctrl-C; ``SystemExit``):
    the loop makes the same safe stop, records the reason ("interrupted: ...") and then re-raises it,
    so the program ends as the user asked; :meth:`result` still tells what happened.
    """

    def __init__(self, robot: Any, source: Any, estimator: Any, tool: ToolFrames | None = None,
                 config: PlacementConfig | None = None, *, period: float = CONTROL_PERIOD,
                 max_frame_age: float = 0.5, log_frames: bool = True, plane_filter: PlaneFilter | None = None,
                 pipeline: EstimatePipeline | None = None, host_clock: Callable[[], float] = time.monotonic,
                 surface_map: SurfaceMap | None = None, read_bound: float = READ_BOUND) -> None:
        _check_arguments(robot, source, estimator, tool, config, period=period, max_frame_age=max_frame_age,
                         read_bound=read_bound, plane_filter=plane_filter, pipeline=pipeline,
                         surface_map=surface_map, host_clock=host_clock)
        self.robot, self.source, self.estimator = robot, source, estimator
        self.tool = tool if tool is not None else robot.tool
        self.config = within_robot_limits(config if config is not None else PlacementConfig(), robot)
        self.period = float(period)
        self.max_frame_age = float(max_frame_age)
        self.log_frames = log_frames
        self.host_clock = host_clock
        self.filter = plane_filter if plane_filter is not None else PlaneFilter(
            window=max(7, int(max(self.config.check_frames, self.config.max_check_frames)) + 2))
        if self.filter.window < self.config.check_frames:
            raise ValueError(f"the plane filter's window ({self.filter.window}) cannot hold check_frames "
                             f"({self.config.check_frames}) planes: nothing could ever be released")
        self.machine = PlacementMachine(self.config, period=self.period)
        if surface_map is None:
            from place_safe.fusion.surface_map import CONSENSUS_RELATIVE
            from place_safe.recovery.points import PeakParams

            params = peak_params_of(estimator)
            # built-in constants put zone points a centimetre off: only calibrated ones get the tight tolerance
            calibrated = params != PeakParams.default_peak()
            surface_map = SurfaceMap(params, cup_radius=self.config.cup_radius, margin=self.config.footprint_margin,
                                     tolerance=self.config.footprint_tolerance,
                                     min_frames=max(int(self.config.footprint_frames), 1),
                                     relative=CONSENSUS_RELATIVE if calibrated else 0.0)
        self.surface = surface_map
        self._landing_T_cup: np.ndarray | None = None
        self._footprint_key: tuple | None = None
        self._footprint = None
        self.multi_surface = 0  # frames that saw more than one surface
        self.pipeline = pipeline if pipeline is not None else EstimatePipeline(source, estimator, clock=host_clock,
                                                                               read_bound=read_bound)
        self.clock = ClockMap(clock_domain_of(source))
        self.history = PoseHistory(tolerance=self.period / 2)
        self._tcp_T_sensor = self.tool.tcp_T_sensor
        self._tcp_T_cup = self.tool.tcp_T_cup
        self.frame_log: list[dict] = []
        self.dropped: dict[str, int] = {}
        self.frames = 0
        self.frames_used = 0
        self.ticks = 0
        self.force_peak = 0.0
        self._last_stamp = -math.inf
        self._last_arrival: float | None = None  # robot time of the newest measurement's arrival
        self._note: str | None = None
        self._cmd_error: str | None = None
        self._t_start: float | None = None
        self._started = False

    # -- helpers -------------------------------------------------------------------------------
    def _drop(self, reason: str) -> None:
        key = reason.split(":")[0]
        self.dropped[key] = self.dropped.get(key, 0) + 1
        self._note = reason

    def _robot_now(self) -> float:
        try:
            t = float(self.robot.time())
        except BaseException as exc:  # a robot that cannot tell its time is faulted: the machine aborts on NaN
            if _is_interrupt_here(exc):
                raise
            return math.nan
        return t

    def _safe(self, fn: Callable[[], Any], default: Any) -> Any:
        try:
            return fn()
        except BaseException as exc:  # any exception class; only an interrupt on this thread goes on
            if _is_interrupt_here(exc):
                raise
            return default

    def _use(self, m: Measurement, now: float) -> None:
        """Gate one measurement and offer it to the fusion."""
        frame, est = m.frame, m.estimate
        self.frames += 1
        self._last_arrival = now
        stamp = self.clock.to_robot(getattr(frame, "timestamp", None))
        accepted = False
        if not math.isfinite(stamp):
            self._drop("unstamped: frame has no usable timestamp")
        elif stamp > now + self.period:
            self._drop(f"future: frame stamped {stamp - now:.3f} s after the robot's clock")
        elif now - stamp > self.max_frame_age:
            self._drop(f"stale: frame measured {now - stamp:.3f} s ago (> {self.max_frame_age:.2f} s)")
        elif stamp <= self._last_stamp:
            self._drop("repeated: frame not newer than the last one used (duplicate or out of order)")
        else:
            pose = self.history.at(stamp)
            if pose is None:
                self._drop("no pose: no robot pose recorded at the frame's measurement time")
            else:
                self._last_stamp = stamp
                self.frames_used += 1
                base_T_sensor = pose @ self._tcp_T_sensor
                est, why = self._surfaces(frame, est, base_T_sensor, stamp)
                if est is None:
                    self._drop(why)
                else:
                    accepted = self.filter.update(est, base_T_sensor, stamp)
                    self._note = (why if accepted else self.filter.last_reject_reason)
        if self.log_frames:
            plane = getattr(est, "plane", None)
            entry = {"t": now, "stamp": stamp, "accepted": accepted,
                     "ms": float(getattr(est, "seconds", math.nan)) * 1e3,
                     "plane": plane.to_dict() if plane is not None else None,
                     "truth": frame.truth.to_dict() if getattr(frame, "truth", None) is not None else None}
            if not accepted:
                entry["reason"] = self._note
            self.frame_log.append(entry)

    def _surfaces(self, frame: Any, est: Any, base_T_sensor: np.ndarray, stamp: float) -> tuple[Any, str | None]:
        """Record the frame in the surface map; a frame that saw more than one surface gets the plane of the
        zones that agree (a majority), or is dropped. Returns (estimate or None, note)."""
        try:
            fs = self.surface.add(frame, base_T_sensor, stamp)
        except Exception as exc:  # the map is evidence, not control: a bug there must not stop the loop
            return est, f"surface map failed: {describe_exception(exc)}"
        if fs is None:
            return est, None
        # zones off the known surface while most still lie on it: clutter or a step coming into view
        # beside the footprint. A frame's own consensus can miss it -- a tilted plane through every zone
        # absorbs a box on one side -- so the zones are held against the fused surface too.
        known = self.filter.fused() if self.surface.relative > 0 else None  # zone points good to ~1 mm only
        if known is not None:  # when the peak mapping is calibrated (see SurfaceMap.consensus_tolerance)
            try:
                on = self.surface.on_plane(fs, known.normal_base, known.offset_base)
            except Exception:  # evidence, not control (see above): without it the frame goes on as it is
                on = np.zeros(len(fs.valid), dtype=bool)
            off = fs.valid & ~on
            n_on = int(on.sum())
            what = (f"zone(s) {', '.join(str(z + 1) for z in np.flatnonzero(off))} off the known surface"
                    + (f" ({fs.describe()})" if fs.multi_surface else ""))
            if off.any() and n_on >= MIN_INLIERS:
                self.multi_surface += 1
                return self._zone_plane(fs, on, base_T_sensor), f"{what}: plane from the {n_on} zones still on it"
            if off.any() and n_on >= MIN_ON_KNOWN and known.source == "memory":
                # too few zones for a slope of their own: the remembered slope, their height
                self.multi_surface += 1
                return self._known_plane(fs, on, known, base_T_sensor), (
                    f"{what}: the known surface's slope, its height from the {n_on} zones still on it")
        if not fs.multi_surface:
            return est, None
        self.multi_surface += 1
        off = fs.valid & ~fs.inliers
        if not off.any():
            return est, f"more than one surface in view: {fs.describe()}"
        if int(fs.inliers.sum()) < MIN_INLIERS:
            return None, (f"multi-surface: more than one surface in view and no {MIN_INLIERS} zones agree "
                          f"(edge, step or clutter): {fs.describe()}")
        return (self._zone_plane(fs, fs.inliers, base_T_sensor),
                f"more than one surface in view, plane from the {int(fs.inliers.sum())} zones that agree: {fs.describe()}")

    @staticmethod
    def _known_plane(fs: Any, zones: np.ndarray, known: Any, base_T_sensor: np.ndarray) -> Any:
        """An estimate (sensor frame) with the known surface's normal and the height the calibrated peak
        points of ``zones`` give it (their median). It measures no slope: its normal carries
        :data:`KNOWN_SLOPE_STD` so the fusion's slope stays with the frames that measured one."""
        from place_safe.geometry import Plane
        from place_safe.recovery.estimator import PlaneEstimate

        T = np.asarray(base_T_sensor, dtype=float)
        n_b = np.asarray(known.normal_base, dtype=float)
        heights = fs.points_base[np.asarray(zones, dtype=bool)] @ n_b
        d_b = float(np.median(heights))
        n_s = -(T[:3, :3].T @ n_b)  # towards the surface, as the sensor frame's planes are (n_z > 0)
        d_s = float(n_b @ T[:3, 3]) - d_b
        if not (n_s[2] > 0 and d_s > 0):
            return PlaneEstimate(None, reason="the known surface is not in front of the sensor")
        spread = float(np.std(heights)) if heights.size > 1 else 0.0
        var_d = max(spread, KNOWN_HEIGHT_STD) ** 2 / heights.size
        cov = np.diag([KNOWN_SLOPE_STD ** 2, KNOWN_SLOPE_STD ** 2, var_d])
        return PlaneEstimate(Plane(n_s, d_s), residual=spread, covariance=cov, method_used="peak-known-slope")

    @staticmethod
    def _zone_plane(fs: Any, zones: np.ndarray, base_T_sensor: np.ndarray) -> Any:
        """The plane (sensor frame) fitted to the calibrated peak points of ``zones`` of a recorded frame,
        as an estimate with its covariance ("peak-consensus"); None-plane estimate when the fit fails."""
        from place_safe.geometry import Plane
        from place_safe.recovery.estimator import PlaneEstimate
        from place_safe.recovery.points import fit_planes, plane_covariance

        T = np.asarray(base_T_sensor, dtype=float)
        pts = np.nan_to_num((fs.points_base - T[:3, 3]) @ T[:3, :3])
        n, d, rms, ok = fit_planes(pts[None], np.asarray(zones, dtype=bool)[None])
        if not ok[0]:
            return PlaneEstimate(None, reason="no plane through the zones that agree")
        plane = Plane(n[0], float(d[0]))
        cov = plane_covariance(pts, zones, plane)
        return PlaneEstimate(plane, residual=float(rms[0]), covariance=cov, method_used="peak-consensus")

    def _footprint_verdict(self, fused: Any, tcp: Any) -> Any:
        """The surface map's verdict on the landing footprint (None without a fused plane)."""
        if fused is None or self._landing_T_cup is None:
            return None
        try:
            key = (fused.stamp, fused.count, len(self.surface.frames))
            if key != self._footprint_key:
                self._footprint = self.surface.footprint(fused.normal_base, fused.offset_base, self._landing_T_cup)
                self._footprint_key = key
            return self.surface.sight(self._footprint, fused.normal_base, fused.offset_base, self._landing_T_cup,
                                      np.asarray(tcp, dtype=float) @ self._tcp_T_sensor)
        except Exception as exc:
            from place_safe.fusion.surface_map import FootprintVerdict

            return FootprintVerdict(problem=f"surface map failed: {describe_exception(exc)}")

    def _dispatch(self, cmd: Any) -> None:
        try:
            if cmd.kind == CommandKind.SPEED:
                self.robot.speed_linear(np.asarray(cmd.twist), accel=cmd.accel)
            elif cmd.kind == CommandKind.STOP:
                self.robot.stop(decel=cmd.accel, asynchronous=True)
            elif cmd.kind == CommandKind.OPEN_GRIPPER:
                self.robot.gripper(open=True)
        except BaseException as exc:  # any failure of a command is a fault: stop, hold the cup, say why
            if _is_interrupt_here(exc):
                raise
            self._cmd_error = f"command {cmd.kind.value} failed: {describe_exception(exc)}"
            if cmd.kind == CommandKind.OPEN_GRIPPER:
                self.machine.gripper_failed(self._robot_now(), self._cmd_error)
            self._stop_robot()

    def _stop_robot(self) -> None:
        try:
            self.robot.stop(decel=self.config.accel, asynchronous=True)
        except BaseException as exc:  # noqa: BLE001 - the stop is best effort; an interrupt still goes on
            if _is_interrupt_here(exc):
                raise

    # -- the tick ------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the sensor pipeline and record the first pose (``run`` calls it)."""
        if self._started:
            return
        self._started = True
        self.pipeline.start()
        now = self._robot_now()
        self._t_start = now
        tcp = self._safe(self.robot.tcp_pose, np.full((4, 4), np.nan))
        self.history.add(now, tcp)
        try:
            landing = np.asarray(tcp, dtype=float) @ self._tcp_T_cup
            self._landing_T_cup = landing if np.all(np.isfinite(landing)) else None
        except Exception:
            self._landing_T_cup = None
        self.clock.observe(now, self.host_clock())

    def tick(self) -> Any:
        """One control period: advance, sense, fuse, decide, command. Returns the machine's command.

        Never raises: anything unexpected (a robot or estimator returning garbage or raising any exception
        class, a bug) stops the robot and ends the placement holding the cup, with the reason. An interrupt
        on the control thread (``KeyboardInterrupt``, ``SystemExit``) gets the same safe stop and is then
        re-raised (see the class docstring)."""
        try:
            return self._tick()
        except BaseException as exc:
            interrupt = isinstance(exc, INTERRUPTS)
            why = f"{'interrupted' if interrupt else 'internal error'}: {describe_exception(exc)}"
            try:
                self._stop_robot()
            finally:
                try:
                    cmd = self.machine.abort(self._robot_now(), why)
                except BaseException:  # noqa: BLE001 - the robot is stopped; the record is best effort
                    cmd = None
            if interrupt:
                raise
            return cmd

    def _tick(self) -> Any:
        if not self._started:
            self.start()
        self.ticks += 1
        try:
            self.robot.step(self.period)
        except RobotFault:
            pass  # latched; the machine sees robot.fault() below
        except BaseException as exc:
            if _is_interrupt_here(exc):
                raise
            self._cmd_error = f"robot step failed: {describe_exception(exc)}"
            self._stop_robot()  # our own failure, not the controller's stop: the arm may still move
        now = self._robot_now()
        tcp = self._safe(self.robot.tcp_pose, np.full((4, 4), np.nan))
        self.history.add(now, tcp)
        self.clock.observe(now, self.host_clock())
        force = self._safe(self.robot.contact_force, math.nan)
        if isinstance(force, (int, float)) and math.isfinite(force):
            self.force_peak = max(self.force_peak, float(force))
        m = self.pipeline.take()
        if m is not None:
            self._use(m, now)
        note = self._note
        if self.pipeline.error is not None:
            note = f"sensor error: {self.pipeline.error}"
        fault = self._safe(self.robot.fault, _NO_ANSWER) or self._cmd_error
        if fault is _NO_ANSWER:
            self._stop_robot()  # a robot that cannot report its state may still move: stop it ourselves
        try:
            cup = np.asarray(tcp, dtype=float) @ self._tcp_T_cup
        except Exception:
            cup = np.full((4, 4), np.nan)
        state = RobotState(now, tcp, cup, force, fault, self._last_arrival)
        fused = self.filter.fused(now) if math.isfinite(now) else None
        cmd = self.machine.step(state, fused, note, self._footprint_verdict(fused, tcp))
        self._dispatch(cmd)
        return cmd

    @property
    def finished(self) -> bool:
        return self.machine.finished

    def run(self, timeout: float = 60.0) -> LoopResult:
        """Tick until the machine finishes or ``timeout`` seconds of robot time pass (then the robot is
        stopped holding the cup and the outcome is "timeout"). Stops the sensor pipeline at the end."""
        if isinstance(timeout, bool) or not isinstance(timeout, (int, float)) or not (
                math.isfinite(timeout) and 0 < timeout <= MAX_RUN_SECONDS):
            raise ValueError(f"timeout must be a number of seconds in (0, {MAX_RUN_SECONDS:g}], got {timeout!r}")
        max_ticks = int(math.ceil(timeout / self.period)) + 1
        try:  # the first tick starts the pipeline (inside tick's guard: nothing escapes but an interrupt)
            while not self.machine.finished and self.ticks < max_ticks:
                self.tick()
        finally:
            self.pipeline.stop()
            if not self.machine.finished:
                self._stop_robot()
        return self.result(timeout)

    def result(self, timeout: float | None = None) -> LoopResult:
        mach = self.machine
        if mach.finished:
            outcome, reason = mach.outcome or "refused", mach.decision or mach.reason
        else:
            outcome = "timeout"
            reason = (f"not finished within {timeout:.1f} s (phase {mach.phase.value})" if timeout
                      else f"not finished (phase {mach.phase.value})")
            if not self._safe(self.robot.is_faulted, True):
                self._safe(lambda: self.robot.stop(decel=self.config.accel), None)
        now = self._robot_now()
        t0 = self._t_start if self._t_start is not None else now
        return LoopResult(outcome=outcome, reason=reason, final_phase=mach.phase.value,
                          robot_seconds=float(now - t0) if math.isfinite(now - t0) else math.nan,
                          ticks=self.ticks, frames=self.frames, frames_used=self.frames_used,
                          planes=self.filter.count, dropped=dict(self.dropped), contact_force_peak=self.force_peak,
                          transitions=[t.to_dict() for t in mach.log], frame_log=list(self.frame_log),
                          budget=dict(mach.budget))


#: s: the longest robot time one :meth:`PlacementLoop.run` may be given (a placement takes seconds).
MAX_RUN_SECONDS = 3600.0
#: What the loop calls on a robot (see :class:`place_safe.robot.interface.Robot`).
ROBOT_METHODS = ("step", "time", "tcp_pose", "contact_force", "fault", "speed_linear", "stop", "gripper")


def _check_arguments(robot: Any, source: Any, estimator: Any, tool: Any, config: Any, **kw: Any) -> None:
    """Raise ArgumentTypeError / ValueError (one line, what was expected) for arguments of the wrong kind."""
    from place_safe.exceptions import ArgumentTypeError

    def name(v: Any) -> str:
        return f"{type(v).__name__} {v!r}"[:80] if isinstance(v, (str, int, float)) else type(v).__name__

    missing = [m for m in ROBOT_METHODS if not callable(getattr(robot, m, None))]
    if missing:
        raise ArgumentTypeError(f"PlacementLoop: robot must be a place_safe.robot.interface.Robot (with "
                                f"{', '.join(ROBOT_METHODS)}); got {name(robot)}, which has no {', '.join(missing)}")
    if not callable(getattr(source, "read", None)):
        raise ArgumentTypeError(f"PlacementLoop: source must be a FrameSource with read(timeout) (e.g. "
                                f"place_safe.sources.open_source(uri)); got {name(source)}")
    if kw.get("pipeline") is None and not callable(getattr(estimator, "estimate", None)):
        raise ArgumentTypeError(f"PlacementLoop: estimator must have estimate(frame) (e.g. "
                                f"place_safe.recovery.make_estimator(method, calibration)); got {name(estimator)}")
    if config is not None and not isinstance(config, PlacementConfig):
        raise ArgumentTypeError(f"PlacementLoop: config must be a PlacementConfig or None (a file: "
                                f"PlacementConfig.load(path)); got {name(config)}")
    frames = tool if tool is not None else getattr(robot, "tool", None)
    if not isinstance(frames, ToolFrames):
        raise ArgumentTypeError(f"PlacementLoop: tool must be place_safe.robot.tool.ToolFrames (or None with a robot "
                                f"whose .tool is one); got {name(frames)}")
    for key, cls in (("plane_filter", PlaneFilter), ("pipeline", EstimatePipeline), ("surface_map", SurfaceMap)):
        if kw.get(key) is not None and not isinstance(kw[key], cls):
            raise ArgumentTypeError(f"PlacementLoop: {key} must be a {cls.__name__} or None; got {name(kw[key])}")
    if not callable(kw.get("host_clock")):
        raise ArgumentTypeError(f"PlacementLoop: host_clock must be a callable returning seconds; got "
                                f"{name(kw.get('host_clock'))}")
    for key, lo, hi in (("period", 1e-4, 1.0), ("max_frame_age", 1e-3, 60.0), ("read_bound", 1e-3, 60.0)):
        v = kw[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ArgumentTypeError(f"PlacementLoop: {key} must be a number of seconds, got {name(v)}")
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"PlacementLoop: {key} must be {lo:g}..{hi:g} s, got {v!r}")


def peak_params_of(estimator: Any) -> Any:
    """The calibrated peak mapping an estimator carries (``peak``: its params; ``diff``: its initialiser's),
    else the built-in one; the surface map reads zone returns with it."""
    from place_safe.recovery.points import PeakParams

    candidates = [getattr(getattr(estimator, "init", None), "params", None)]
    if getattr(estimator, "needs_histograms", False):  # proprietary maps millimetres, not bins
        candidates.insert(0, getattr(estimator, "params", None))
    for p in candidates:
        if isinstance(p, PeakParams):
            return p
    return PeakParams.default_peak()


__all__ = ["PlacementLoop", "peak_params_of", "describe_exception", "clock_domain_of", "READ_BOUND", "INTERRUPTS", "LoopResult", "EstimatePipeline", "Measurement", "ClockMap", "PoseHistory",
           "CONTROL_PERIOD"]
