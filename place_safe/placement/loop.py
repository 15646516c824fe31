"""The placement loop: frame source -> estimator -> fusion -> decision -> robot, once per control tick.

Concept: :class:`PlacementLoop` is the one road from the sensor to the gripper, the same object on the
real UR5 (ur-rtde robot, TMF8820 over I2C), in MuJoCo (``SimRobot`` + ``SimToF``) and in scenario runs.
The caller chooses the robot, the frame source, the estimator and the tool frames; the loop owns:

* the **sensor pipeline** (:class:`~place_safe.io.pipeline.SensorPipeline`, the one pipeline the streams use
  too, with its fault policy): for a real source a reader thread reads frames and estimates their planes
  off the control thread, keeping only the newest result, so a 125 Hz tick never blocks on I/O or on the
  solver; a source driven by the robot's clock (the simulated sensor, ``clock_domain == "robot"``) is
  polled once per tick instead -- on a helper thread waited for at most
  :data:`~place_safe.io.pipeline.READ_BOUND` seconds, so a source that blocks is a dead sensor, not a
  hung loop -- and estimated inline;
* the **clock map** (:class:`~place_safe.placement.time_alignment.ClockMap`): frame stamps are on the
  source's clock (host ``time.monotonic`` for hardware); the loop converts them to the robot's clock
  before anything compares them with robot time;
* the **pose at the measurement time** (:class:`~place_safe.placement.time_alignment.PoseHistory`): the
  TCP pose recorded every tick, interpolated at the frame's stamp, times the configured ``tcp_T_sensor``
  (a frame is read ~0.1 s after it was measured: 8 mm of travel at approach speed);
* **frame gating** (:class:`~place_safe.io.pipeline.FrameGate` on the robot's clock): frames whose stamp
  is not finite, lies in the future, is older than ``max_frame_age`` or is not later than the newest one
  already used (duplicates, out-of-order) are dropped with a reason, so a frozen or replaying sensor
  cannot count as fresh evidence;
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
import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable

import numpy as np

from place_safe.exceptions import ArgumentTypeError, RobotFault
from place_safe.fusion.plane_filter import PlaneFilter
from place_safe.fusion.surface_map import CONSENSUS_RELATIVE, MIN_INLIERS, FootprintVerdict, SurfaceMap
from place_safe.geometry import Plane
from place_safe.io.pipeline import (INTERRUPTS, PLACEMENT_POLICY, READ_BOUND, FrameGate, Measurement, SensorPipeline,
                                    clock_domain_of, describe_exception, is_interrupt_here, stamp_of)
from place_safe.io.source import FrameSource
from place_safe.placement import rules
from place_safe.placement.config import PlacementConfig
from place_safe.placement.machine import CommandKind, PlacementMachine, RobotState, Transition
from place_safe.placement.time_alignment import ClockMap, PoseHistory
from place_safe.recovery.estimator import (Estimator, PlaneEstimate, check_arguments, describe,
                                          reference_tilt_problem)
from place_safe.recovery.points import PeakParams, fit_planes, plane_covariance
from place_safe.robot.interface import Robot, RobotLimits
from place_safe.robot.tool import ToolFrames
from place_safe.sensor.zones import N_ZONES, zone_numbers

log = logging.getLogger("place_safe.placement.loop")

#: s, control period (125 Hz, the UR CB3 controller's rate).
CONTROL_PERIOD = 0.008
#: Zones still on the known surface from which a frame gives the surface's height (with the remembered
#: slope) when clutter or a step covers the others.
MIN_ON_KNOWN = 3
#: rad: the slope uncertainty of such a height-only estimate (it measures no slope).
KNOWN_SLOPE_STD = math.radians(5.0)
#: m: the least height uncertainty per zone of such an estimate.
KNOWN_HEIGHT_STD = 0.0005
#: m: a zone that saw two surfaces (:attr:`FrameSurfaces.split <place_safe.fusion.surface_map.FrameSurfaces.split>`)
#: in a frame is held to see them still in later frames taken within this distance across the sensor's axis of
#: that frame's sensor position (the same orientation within :data:`SPLIT_HOLD_ANGLE`) ...
SPLIT_HOLD_RADIUS = 0.005
SPLIT_HOLD_ANGLE = math.radians(1.0)
#: ... and from at least this fraction of that frame's range (closer, the zone's field shrinks towards its own
#: direction and may leave the edge behind; farther, it holds more of the other surface).
SPLIT_HOLD_RANGE = 0.7
#: Frames with zones that saw two surfaces that the loop remembers for it.
SPLIT_HOLD_FRAMES = 200
#: The fault the machine sees when ``robot.fault()`` itself fails.
_NO_ANSWER = "robot does not answer"


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
    transitions: list[Transition] = field(default_factory=list)  # the machine's log, in order
    frame_log: list[dict] = field(default_factory=list)
    budget: dict[str, float] = field(default_factory=dict)  # s spent on each part (PlacementMachine.budget)
    contact_latency: float = math.nan  # s: the touch latency the contact rule used (the robot's, where longer)

    def to_dict(self) -> dict:
        """JSON form (what ``place --json`` writes; docs/interfaces.md): transitions as
        ``{"time", "from", "to", "reason"}`` objects."""
        d = dict(self.__dict__)
        d["transitions"] = [t.to_dict() for t in self.transitions]
        return d


def within_robot_limits(config: PlacementConfig, robot: Any) -> PlacementConfig:
    """``config`` with its speeds and accelerations capped at the robot's ``limits`` (``max_linear_speed``,
    ``max_linear_accel``), so that the descent profile is planned with the braking the arm really has
    (a driver would clip a faster command and the arm would then stop later than planned). A robot
    without readable limits gets :class:`~place_safe.robot.interface.RobotLimits`' defaults (0.25 m/s,
    1.2 m/s^2): a config's cruise sized for an arm that states a faster limit is not trusted blind."""
    try:
        lim = getattr(robot, "limits", None)
        v = getattr(lim, "max_linear_speed", None)
        a = getattr(lim, "max_linear_accel", None)
    except Exception:  # a robot whose limits cannot be read: its driver clips what it must
        v = a = None
    ok = (lambda x: isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) and x > 0)
    if not ok(v):
        v = RobotLimits().max_linear_speed
    if not ok(a):
        a = RobotLimits().max_linear_accel
    changes: dict[str, float] = {}
    for name in ("approach_speed", "descend_speed", "survey_speed", "retreat_speed", "near_surface_speed"):
        if getattr(config, name) > v:
            changes[name] = float(v)
    for name in ("accel", "lateral_accel"):
        if getattr(config, name) > a:
            changes[name] = float(a)
    return config.replace(**changes) if changes else config


def with_robot_contact_latency(config: PlacementConfig, robot: Any) -> PlacementConfig:
    """``config`` with ``contact_latency`` raised to the robot's own (:meth:`~place_safe.robot.interface.Robot.
    contact_latency`: its detector's 10 N touch latency at the force noise it measured at rest) where that is
    longer, at most the field's 1 s (a touch never seen: 1 s). A detector that measured a noisier arm than its settings
    say sees a touch later, so a touch counts as arrival only lower down (:func:`~place_safe.placement.rules.
    contact_limit`); where no touch can count any more (the limit below zero) every touch is an obstacle, and a warning
    says why. A robot that cannot say (None, or no such method) leaves ``config`` as it is; one whose answer is no
    latency (it raised, NaN, not a number) too, with a warning."""
    got = getattr(robot, "contact_latency", None)
    if not callable(got):
        return config
    try:
        raw = got()
        # inf, or an integer beyond any float: a touch never seen
        never = (isinstance(raw, (float, np.floating)) and raw == math.inf) or (
            type(raw) is int and raw > 0 and rules.number(raw) is None)
        latency = 1.0 if never else rules.number(raw)
    except Exception as exc:  # a robot that cannot say keeps the configured latency
        log.warning("the robot's contact latency could not be read (%s): the placement's %.0f ms stands",
                    describe_exception(exc), 1e3 * config.contact_latency)
        return config
    if raw is None:
        return config
    if latency is None:
        log.warning("the robot's contact latency is not a number of seconds (%r): the placement's %.0f ms stands",
                    raw, 1e3 * config.contact_latency)
        return config
    if not latency > config.contact_latency:
        return config
    out = config.replace(contact_latency=float(min(latency, 1.0)))
    if rules.contact_limit(out) < 0.0:
        log.warning("the robot's contact detector reports a touch %.0f ms late at the force noise it measured at rest "
                    "(%.1f mm of descent): no touch can count as arrival, every touch is refused as an obstacle",
                    1e3 * out.contact_latency, 1e3 * out.descend_speed * out.contact_latency)
    return out


def _in_base(tcp: Any, tcp_T_frame: np.ndarray) -> np.ndarray:
    """A tool frame's base-frame pose (4x4) from the TCP's ``tcp``; NaN where ``tcp`` is no matrix (the machine then
    refuses the robot state)."""
    try:
        return np.asarray(tcp, dtype=float) @ tcp_T_frame
    except Exception:
        return np.full((4, 4), np.nan)


class PlacementLoop:
    """One placement: ``PlacementLoop(robot, source, estimator, tool, config).run()`` (see module doc).

    Parameters
    ----------
    robot: a :class:`~place_safe.robot.interface.Robot`, connected by the caller (its force zeroed: the loop takes
        its contact latency when made and again when it starts).
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

    Failure policy: :meth:`tick` and :meth:`run` never block on the source (see :class:`~place_safe.io.pipeline.SensorPipeline`)
    and never raise for what the robot, the source or the estimator do: any exception class ends in a
    safe stop (``stopL``, the cup held, the machine aborted) with the reason in the result. The one
    exception is an interrupt on the control thread (``KeyboardInterrupt``: Ctrl-C; ``SystemExit``):
    the loop makes the same safe stop, records the reason ("interrupted: ...") and then re-raises it,
    so the program ends as the user asked; :meth:`result` still tells what happened.
    """

    def __init__(self, robot: Robot, source: FrameSource, estimator: Estimator, tool: ToolFrames | None = None,
                 config: PlacementConfig | None = None, *, period: float = CONTROL_PERIOD,
                 max_frame_age: float = 0.5, log_frames: bool = True, plane_filter: PlaneFilter | None = None,
                 pipeline: SensorPipeline | None = None, host_clock: Callable[[], float] = time.monotonic,
                 surface_map: SurfaceMap | None = None, read_bound: float = READ_BOUND) -> None:
        _check_arguments(robot, source, estimator, tool, config, period=period, max_frame_age=max_frame_age,
                         read_bound=read_bound, plane_filter=plane_filter, pipeline=pipeline,
                         surface_map=surface_map, host_clock=host_clock)
        self.robot, self.source, self.estimator = robot, source, estimator
        self.tool = tool if tool is not None else robot.tool
        self.config = with_robot_contact_latency(within_robot_limits(config if config is not None
                                                                     else PlacementConfig(), robot), robot)
        self.period = float(period)
        self.max_frame_age = float(max_frame_age)
        self.log_frames = log_frames
        self.host_clock = host_clock
        reference = reference_tilt_std_of(estimator if estimator is not None else getattr(pipeline, "estimator", None))
        self.filter = plane_filter if plane_filter is not None else PlaneFilter(
            window=max(7, int(rules.most_check_frames(self.config)) + 2))
        # the filter (its own, or the caller's) counts at least the reference error of the estimator's calibration
        self.filter.reference_tilt_std = max(self.filter.reference_tilt_std, reference)
        if self.filter.window < self.config.check_frames:
            raise ValueError(f"the plane filter's window ({self.filter.window}) cannot hold check_frames "
                             f"({self.config.check_frames}) planes: nothing could ever be released")
        self.machine = PlacementMachine(self.config, period=self.period)
        if surface_map is None:
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
        # the frames with zones that saw two surfaces (_held_split), one row each: sensor position (3), axis (3),
        # median range (1), zones (N_ZONES); a ring of SPLIT_HOLD_FRAMES rows, _split_rows of them filled
        self._split_seen = np.zeros((SPLIT_HOLD_FRAMES, 7 + N_ZONES))
        self._split_rows = 0
        self._ambiguity = 0.0  # rad, the newest recorded frame's slope ambiguity (_surfaces; 0: none)
        self._clock_error: str | None = None  # the host clock's first failure (_clock_failed); the placement ends on it
        self._host_last: float | None = None  # its newest good reading (s)
        self.pipeline = pipeline if pipeline is not None else SensorPipeline(
            source, estimator, replace(PLACEMENT_POLICY, read_bound=read_bound), clock=self._pipeline_clock)
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
        self.gate = FrameGate(max_age=self.max_frame_age, future_tolerance=self.period)
        self._last_arrival: float | None = None  # robot time of the newest measurement's arrival
        self._last_age: float | None = None  # s, from its measurement to its arrival (a frame the gate passed)
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
            if is_interrupt_here(exc):
                raise
            return math.nan
        return t

    def _host_now(self) -> float | None:
        """The host clock's reading (s), or None when it failed: raised, gave no finite number, or stepped back. The
        sensor's frames are timed by it (the pipeline's arrivals and read bound, host-stamped frames on the robot's
        clock), so the first failure is kept in ``_clock_error`` and :meth:`_tick` ends the placement on it, naming the
        clock (it was read as frames "unstamped", "stale" or "future", or an internal error when it raised)."""
        try:
            value = self.host_clock()
        except BaseException as exc:
            if is_interrupt_here(exc):
                raise
            why = f"raised {describe_exception(exc)}"
        else:
            t = rules.number(value)
            if t is None:
                why = f"gave {describe(value)}, not a finite number of seconds"
            elif self._host_last is not None and t < self._host_last:
                why = f"stepped back {self._host_last - t:.3g} s"
            else:
                self._host_last = t
                return t
        self._clock_failed(why)
        return None

    def _pipeline_clock(self) -> float:
        """The host clock as the pipeline reads it (arrivals, on its own thread or in a polled read on this one): the
        reading, or NaN where the clock raises, kept in ``_clock_error`` for :meth:`_tick` (a raising clock escaped
        from the pipeline's polled read as "internal error"). The loop's own reading (:meth:`_host_now`) judges the
        values; the pipeline's NaN reads as a frame without a usable time."""
        try:
            return self.host_clock()
        except BaseException as exc:
            if is_interrupt_here(exc):
                raise
            self._clock_failed(f"raised {describe_exception(exc)}")
            return math.nan

    def _clock_failed(self, why: str) -> None:
        if self._clock_error is None:  # the first failure is the one said
            self._clock_error = f"host clock failed: it {why}; the sensor's frames cannot be timed"

    def _safe(self, fn: Callable[[], Any], default: Any) -> Any:
        try:
            return fn()
        except BaseException as exc:  # any exception class; only an interrupt on this thread goes on
            if is_interrupt_here(exc):
                raise
            return default

    def _use(self, m: Measurement, now: float) -> None:
        """Gate one measurement and offer it to the fusion."""
        frame, est = m.frame, m.estimate
        self.frames += 1
        self._last_arrival = now
        stamp = self.clock.to_robot(stamp_of(frame))
        accepted = False
        self._last_age = None
        if (why := self.gate.check(stamp, now)) is not None:
            self._drop(why)
        else:
            self._last_age = max(now - stamp, 0.0)  # the machine brakes for the latency it measures (_latency)
            pose = self.history.at(stamp)
            if pose is None:
                self._drop("no pose: no robot pose recorded at the frame's measurement time")
            else:
                self.gate.accept(stamp)
                self.frames_used += 1
                base_T_sensor = pose @ self._tcp_T_sensor
                est, why = self._surfaces(frame, est, base_T_sensor, stamp)
                if est is None:
                    self._drop(why)
                else:
                    accepted = self.filter.update(est, base_T_sensor, stamp, ambiguity=self._ambiguity)
                    self._note = (why if accepted else self.filter.last_reject_reason)
                    if accepted and (restart := getattr(self.filter, "restarted", None)):
                        self._note = f"{why}; {restart}" if why else restart
        if self.log_frames:
            seconds = rules.number(self._safe(lambda: getattr(est, "seconds", None), None))
            entry = {"t": now, "stamp": stamp, "accepted": accepted,
                     "ms": seconds * 1e3 if seconds is not None else math.nan,
                     "plane": _logged(self._safe(lambda: getattr(est, "plane", None), None)),
                     "truth": _logged(self._safe(lambda: getattr(frame, "truth", None), None))}
            if not accepted:
                entry["reason"] = self._note
            self.frame_log.append(entry)

    def _surfaces(self, frame: Any, est: Any, base_T_sensor: np.ndarray, stamp: float) -> tuple[Any, str | None]:
        """Record the frame in the surface map; a frame that saw more than one surface gets the plane of the
        zones that agree (a majority), or is dropped. Returns (estimate or None, note); the frame's slope ambiguity
        (:func:`~place_safe.fusion.surface_map.slope_ambiguity`, rad, 0: none) is left in ``_ambiguity`` for the
        fusion."""
        self._ambiguity = 0.0
        try:
            fs = self.surface.add(frame, base_T_sensor, stamp)
        except Exception as exc:  # the map is evidence, not control: a bug there must not stop the loop
            return est, f"surface map failed: {describe_exception(exc)}"
        if fs is None:
            return est, None
        est, note = self._frame_plane(fs, est, base_T_sensor)
        angle = rules.number(getattr(fs, "ambiguity", None))
        if angle is not None and angle > 0 and getattr(est, "plane", None) is not None:
            # the fusion weighs it so, keeps it out of the memory and holds the window's tilt to it (PlaneFilter.update)
            self._ambiguity = angle
            why = f"its zones read as well as a plane {math.degrees(angle):.1f} deg from it (slope ambiguous by that)"
            note = f"{note}; {why}" if note else why
        return est, note

    def _frame_plane(self, fs: Any, est: Any, base_T_sensor: np.ndarray) -> tuple[Any, str | None]:
        """The plane of a recorded frame ``fs`` (see :meth:`_surfaces`): the estimate ``est`` as it is, or the
        plane of the zones that agree, or None, with a note."""
        held = self._held_split(fs)
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

            def what(off: np.ndarray) -> str:
                return (f"zone(s) {zone_numbers(off)} off the known surface"
                        + (f" ({fs.describe()})" if fs.multi_surface else ""))

            if off.any() and n_on >= MIN_ON_KNOWN and known.source == "memory":
                # the known surface's slope is remembered: the frame gives it at the height of the zones still on
                # it, and measures no slope of its own. The zones beside what lies off it may be partly covered
                # without a shoulder to show it (random scene 17 of seed 57: a box's edge under a corner zone lifts
                # it 1.4-1.7 mm at 7 cm, within the tolerance; the plane of the 7 zones on the table was 2.3 deg
                # off, the fused plane with it, and the survey's views of the footprint, judged against that, were
                # vetoed as raised); with 3-4 zones there is no slope of their own either
                self.multi_surface += 1
                return self._known_plane(fs, on, known, base_T_sensor), (
                    f"{what(off)}: the known surface's slope, its height from the {n_on} zones still on it")
            if off.any() and n_on >= MIN_INLIERS:  # no slope remembered yet: the plane of the zones on it
                self.multi_surface += 1
                on = self._one_surface(fs, on, held)
                n_on = int(on.sum())
                return self._zone_plane(fs, on, base_T_sensor), f"{what(off)}: plane from the {n_on} zones still on it"
            if off.any() and known.source == "memory":
                # clutter beside the footprint covers most of the view, and the zones that still see the known
                # surface have the clutter's edge mixed into their returns: their peaks still lie on it (within
                # the frame's tolerance, which then bounds their height error), so they give its height. A
                # frame's own majority would be the clutter's top
                try:
                    mixed = self.surface.on_plane(fs, known.normal_base, known.offset_base, mixed=True)
                except Exception:  # evidence, not control (see above)
                    mixed = np.zeros(len(fs.valid), dtype=bool)
                n_mixed = int(mixed.sum())
                if n_mixed >= MIN_ON_KNOWN and (fs.valid & ~mixed).any():
                    self.multi_surface += 1
                    return self._known_plane(fs, mixed, known, base_T_sensor, height_std=fs.tolerance), (
                        f"{what(fs.valid & ~mixed)}: the known surface's slope, its height from the {n_mixed} zones "
                        "still on it (a nearer surface mixed into their returns)")
        single = self._one_surface(fs, fs.inliers, held)  # the consensus zones that see one surface
        if not fs.multi_surface:
            if np.array_equal(single, fs.inliers):
                return est, None
            # random scene 136 of seed 54 made level: the far row reached past the table's edge and saw the floor
            # down to 84 mm; closer, and at rest, its floor return fell below the second-return test while the row
            # still read 0.4-0.9 mm near, and those frames' own planes (2 deg off) took the fused slope with them
            return self._zone_plane(fs, single, base_T_sensor), (
                f"zone(s) {zone_numbers(fs.inliers & ~single)} saw two surfaces "
                f"from about this pose: plane from the {int(single.sum())} others")
        self.multi_surface += 1
        off = fs.valid & ~fs.inliers
        if not off.any():
            if not np.array_equal(single, fs.inliers):  # zones that see two surfaces left out
                return (self._zone_plane(fs, single, base_T_sensor),
                        f"more than one surface in view, plane from the {int(single.sum())} zones that see one: "
                        f"{fs.describe()}")
            return est, f"more than one surface in view: {fs.describe()}"
        if int(fs.inliers.sum()) < MIN_INLIERS:
            return None, (f"multi-surface: more than one surface in view and no {MIN_INLIERS} zones agree "
                          f"(edge, step or clutter): {fs.describe()}")
        return (self._zone_plane(fs, single, base_T_sensor),
                f"more than one surface in view, plane from the {int(single.sum())} zones that agree: {fs.describe()}")

    def _held_split(self, fs: Any) -> np.ndarray:
        """Zones (9,) of a recorded frame that saw two surfaces in an earlier frame taken from about its pose
        (within :data:`SPLIT_HOLD_RADIUS` across the axis, :data:`SPLIT_HOLD_ANGLE`, and from at least
        :data:`SPLIT_HOLD_RANGE` of that frame's range) and do not show it now: the other surface's share of the
        zone's field may have fallen below what the second-return test sees (a floor 0.7 m down returns
        1/100 as much per area as a table at 8 cm) while its first return still comes from part of its field only.
        Remembers this frame's own split zones for the frames after it."""
        T = np.asarray(fs.base_T_sensor, dtype=float)
        p, axis = T[:3, 3], T[:3, 2]
        ranges = np.linalg.norm(fs.points_base[fs.valid] - p, axis=1)
        r = float(np.median(ranges)) if ranges.size else math.nan
        if not math.isfinite(r) or len(fs.valid) != N_ZONES:
            return np.zeros(len(fs.valid), dtype=bool)
        seen = self._split_seen[:min(self._split_rows, SPLIT_HOLD_FRAMES)]
        d = p - seen[:, 0:3]
        across = d - np.outer(d @ axis, axis)
        near = ((np.einsum("ij,ij->i", across, across) <= SPLIT_HOLD_RADIUS ** 2)
                & (seen[:, 3:6] @ axis >= math.cos(SPLIT_HOLD_ANGLE)) & (r >= SPLIT_HOLD_RANGE * seen[:, 6]))
        held = np.any(seen[near, 7:] > 0.5, axis=0)
        if fs.split.any():
            self._split_seen[self._split_rows % SPLIT_HOLD_FRAMES] = np.concatenate((p, axis, [r], fs.split))
            self._split_rows += 1
        return held & fs.valid & ~fs.split

    @staticmethod
    def _one_surface(fs: Any, zones: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
        """``zones`` (9,) of a recorded frame without those that see two surfaces (:attr:`FrameSurfaces.split
        <place_safe.fusion.surface_map.FrameSurfaces.split>`) or are held to (``held``, :meth:`_held_split`), when
        :data:`MIN_INLIERS` of them remain; else ``zones`` as they are. Such a zone reads its first surface off by up
        to 1-2 % of the range: within the consensus tolerance, but enough to tilt a frame's plane by degrees at 10 cm."""
        single = np.asarray(zones, dtype=bool) & ~fs.split
        if held is not None and int((fewer := single & ~np.asarray(held, dtype=bool)).sum()) >= MIN_INLIERS:
            return fewer
        return single if int(single.sum()) >= MIN_INLIERS else zones

    @staticmethod
    def _known_plane(fs: Any, zones: np.ndarray, known: Any, base_T_sensor: np.ndarray,
                     height_std: float = KNOWN_HEIGHT_STD) -> Any:
        """An estimate (sensor frame) with the known surface's normal and the height the calibrated peak
        points of ``zones`` give it (their median). It measures no slope: its normal carries
        :data:`KNOWN_SLOPE_STD` so the fusion's slope stays with the frames that measured one. Each zone's
        height counts as uncertain by at least ``height_std`` (m; zones whose returns have a nearer surface
        mixed in: the tolerance they were held to)."""
        T = np.asarray(base_T_sensor, dtype=float)
        n_b = np.asarray(known.normal_base, dtype=float)
        heights = fs.points_base[np.asarray(zones, dtype=bool)] @ n_b
        d_b = float(np.median(heights))
        n_s = -(T[:3, :3].T @ n_b)  # towards the surface, as the sensor frame's planes are (n_z > 0)
        d_s = float(n_b @ T[:3, 3]) - d_b
        if not (n_s[2] > 0 and d_s > 0):
            return PlaneEstimate(None, reason="the known surface is not in front of the sensor")
        spread = float(np.std(heights)) if heights.size > 1 else 0.0
        var_d = max(spread, height_std) ** 2 / heights.size
        cov = np.diag([KNOWN_SLOPE_STD ** 2, KNOWN_SLOPE_STD ** 2, var_d])
        return PlaneEstimate(Plane(n_s, d_s), residual=spread, covariance=cov, method_used="peak-known-slope")

    def _zone_plane(self, fs: Any, zones: np.ndarray, base_T_sensor: np.ndarray) -> Any:
        """The plane (sensor frame) fitted to the calibrated peak points of ``zones`` of a recorded frame,
        as an estimate with its covariance ("peak-consensus"); None-plane estimate when the fit fails. The
        covariance is the calibrated peak method's for those zones (:meth:`PeakEstimator.covariance
        <place_safe.recovery.peak.PeakEstimator.covariance>`: the fit's, the near-range errors, the calibrated floor
        and the tilt term) where the estimator carries one (:func:`peak_estimator_of`), else the fit's alone (which
        stated 0.08-0.11 deg where the estimator, with its floor, stated 0.3)."""
        T = np.asarray(base_T_sensor, dtype=float)
        pts = np.nan_to_num((fs.points_base - T[:3, 3]) @ T[:3, :3])
        zones = np.asarray(zones, dtype=bool)
        n, d, rms, ok = fit_planes(pts[None], zones[None])
        if not ok[0]:
            return PlaneEstimate(None, reason="no plane through the zones that agree")
        plane = Plane(n[0], float(d[0]))
        peak = peak_estimator_of(self.estimator)
        try:
            cov = peak.covariance(pts, zones, plane) if peak is not None else plane_covariance(pts, zones, plane)
        except (ValueError, np.linalg.LinAlgError):
            cov = plane_covariance(pts, zones, plane)
        return PlaneEstimate(plane, residual=float(rms[0]), covariance=cov, method_used="peak-consensus")

    def _footprint_verdict(self, fused: Any, base_T_sensor: np.ndarray) -> Any:
        """The surface map's verdict on the landing footprint seen from the sensor's pose (None without a fused
        plane)."""
        if fused is None or self._landing_T_cup is None:
            return None
        try:
            key = (fused.stamp, fused.count, len(self.surface.frames))
            if key != self._footprint_key:
                self._footprint = self.surface.footprint(fused.normal_base, fused.offset_base, self._landing_T_cup)
                self._footprint_key = key
            return self.surface.sight(self._footprint, fused.normal_base, fused.offset_base, self._landing_T_cup,
                                      base_T_sensor)
        except Exception as exc:
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
            if is_interrupt_here(exc):
                raise
            self._cmd_error = f"command {cmd.kind.value} failed: {describe_exception(exc)}"
            if cmd.kind == CommandKind.OPEN_GRIPPER:
                self.machine.gripper_failed(self._robot_now(), self._cmd_error)
            self._stop_robot()

    def _stop_robot(self) -> None:
        try:
            self.robot.stop(decel=self.config.accel, asynchronous=True)
        except BaseException as exc:  # noqa: BLE001 - the stop is best effort; an interrupt still goes on
            if is_interrupt_here(exc):
                raise

    # -- the tick ------------------------------------------------------------------------------
    def start(self) -> None:
        """Start the sensor pipeline and record the first pose (``run`` calls it)."""
        if self._started:
            return
        self._started = True
        # the robot may have been connected (and its force zeroed) since the loop was made: its latency now
        latest = with_robot_contact_latency(self.config, self.robot)
        if latest is not self.config:
            self.config = latest
            self.machine.config = latest
        self.pipeline.start()
        now = self._robot_now()
        self._t_start = now
        tcp = self._safe(self.robot.tcp_pose, np.full((4, 4), np.nan))
        self.history.add(now, tcp)
        landing = _in_base(tcp, self._tcp_T_cup)
        self._landing_T_cup = landing if np.all(np.isfinite(landing)) else None
        if (host := self._host_now()) is not None:
            self.clock.observe(now, host)

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
            if is_interrupt_here(exc):
                raise
            self._cmd_error = f"robot step failed: {describe_exception(exc)}"
            self._stop_robot()  # our own failure, not the controller's stop: the arm may still move
        now = self._robot_now()
        tcp = self._safe(self.robot.tcp_pose, np.full((4, 4), np.nan))
        self.history.add(now, tcp)
        if (host := self._host_now()) is not None:
            self.clock.observe(now, host)
        force = self._safe(self.robot.contact_force, math.nan)
        if (f := rules.number(force)) is not None:
            self.force_peak = max(self.force_peak, f)
        m = self.pipeline.take()
        if m is not None:
            self._use(m, now)
        note = self._note
        if self.pipeline.error is not None:
            note = f"sensor error: {self.pipeline.error}"
        fault = self._safe(self.robot.fault, _NO_ANSWER)
        if fault is _NO_ANSWER:
            self._stop_robot()  # a robot that cannot report its state may still move: stop it ourselves
        elif rules.fault_text(fault) is None:
            fault = self._cmd_error or None
        if self._clock_error is not None and not self.machine.finished:
            self._stop_robot()  # (after the robot's own report, which the reason keeps)
            told = "no report" if fault is _NO_ANSWER else rules.fault_text(fault)
            return self.machine.abort(now, self._clock_error + (f"; robot fault: {told}" if told else ""))
        cup, sensor = _in_base(tcp, self._tcp_T_cup), _in_base(tcp, self._tcp_T_sensor)
        state = RobotState(now, tcp, cup, force, fault, self._last_arrival, self._last_age, sensor)
        fused = self.filter.fused(now) if math.isfinite(now) else None
        cmd = self.machine.step(state, fused, note, self._footprint_verdict(fused, sensor))
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
                          transitions=list(mach.log), frame_log=list(self.frame_log),
                          budget=dict(mach.budget), contact_latency=float(mach.config.contact_latency))


#: s: the longest robot time one :meth:`PlacementLoop.run` may be given (a placement takes seconds).
MAX_RUN_SECONDS = 3600.0
#: What the loop calls on a robot (see :class:`place_safe.robot.interface.Robot`).
ROBOT_METHODS = ("step", "time", "tcp_pose", "contact_force", "fault", "speed_linear", "stop", "gripper")


def _check_arguments(robot: Any, source: Any, estimator: Any, tool: Any, config: Any, **kw: Any) -> None:
    """Raise ArgumentTypeError / ValueError (one line, what was expected) for arguments of the wrong kind."""
    missing = [m for m in ROBOT_METHODS if not callable(getattr(robot, m, None))]
    if missing:
        raise ArgumentTypeError(f"PlacementLoop: robot must be a place_safe.robot.interface.Robot (with "
                                f"{', '.join(ROBOT_METHODS)}); got {describe(robot)}, which has no "
                                f"{', '.join(missing)}")
    if not callable(getattr(source, "read", None)):
        raise ArgumentTypeError(f"PlacementLoop: source must be a FrameSource with read(timeout) (e.g. "
                                f"place_safe.sources.open_source(uri)); got {describe(source)}")
    if kw.get("pipeline") is None and not callable(getattr(estimator, "estimate", None)):
        raise ArgumentTypeError(f"PlacementLoop: estimator must have estimate(frame) (e.g. "
                                f"place_safe.recovery.make_estimator(method, calibration)); got {describe(estimator)}")
    if config is not None and not isinstance(config, PlacementConfig):
        raise ArgumentTypeError(f"PlacementLoop: config must be a PlacementConfig or None (a file: "
                                f"PlacementConfig.load(path)); got {describe(config)}")
    frames = tool if tool is not None else getattr(robot, "tool", None)
    if not isinstance(frames, ToolFrames):
        raise ArgumentTypeError(f"PlacementLoop: tool must be place_safe.robot.tool.ToolFrames (or None with a robot "
                                f"whose .tool is one); got {describe(frames)}")
    check_arguments("PlacementLoop", plane_filter=(kw.get("plane_filter"), PlaneFilter),
                    pipeline=(kw.get("pipeline"), SensorPipeline), surface_map=(kw.get("surface_map"), SurfaceMap))
    if not callable(kw.get("host_clock")):
        raise ArgumentTypeError(f"PlacementLoop: host_clock must be a callable returning seconds; got "
                                f"{describe(kw.get('host_clock'))}")
    for key, lo, hi in (("period", 1e-4, 1.0), ("max_frame_age", 1e-3, 60.0), ("read_bound", 1e-3, 60.0)):
        v = kw[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise ArgumentTypeError(f"PlacementLoop: {key} must be a number of seconds, got {describe(v)}")
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ValueError(f"PlacementLoop: {key} must be {lo:g}..{hi:g} s, got {v!r}")


def reference_tilt_std_of(estimator: Any) -> float:
    """rad, the tilt error every plane of ``estimator`` shares through its calibration's reference
    (``estimator.reference_tilt_std``, set by :func:`~place_safe.recovery.make_estimator`); 0 for an estimator
    without one. A value that is not a number in 0..``MAX_REFERENCE_TILT`` rad raises ValueError (one line)."""
    v = getattr(estimator, "reference_tilt_std", 0.0)
    if (why := reference_tilt_problem(v)) is not None:
        raise ValueError(f"PlacementLoop: the estimator's reference_tilt_std {why}")
    return float(v)


def peak_estimator_of(estimator: Any) -> Any:
    """The calibrated peak estimator an estimator is or carries (``peak``: itself; ``diff``: its initialiser), whose
    covariance the loop's own planes through some of a frame's zones take; None for others (proprietary, fakes)."""
    from place_safe.recovery.peak import PeakEstimator

    for e in (estimator, getattr(estimator, "init", None)):
        if isinstance(e, PeakEstimator):
            return e
    return None


def _logged(plane: Any) -> dict | None:
    """A plane for the frame log (its ``to_dict``), or None for anything that is not a :class:`Plane` (an estimator's
    or a source's garbage is dropped by the filter; the log must not fail on it)."""
    return plane.to_dict() if isinstance(plane, Plane) else None


def peak_params_of(estimator: Any) -> Any:
    """The calibrated peak mapping an estimator carries (``peak``: its params; ``diff``: its initialiser's),
    else the built-in one; the surface map reads zone returns with it."""
    candidates = [getattr(getattr(estimator, "init", None), "params", None)]
    if getattr(estimator, "needs_histograms", False):  # proprietary maps millimetres, not bins
        candidates.insert(0, getattr(estimator, "params", None))
    for p in candidates:
        if isinstance(p, PeakParams):
            return p
    return PeakParams.default_peak()


__all__ = ["PlacementLoop", "LoopResult", "peak_params_of", "peak_estimator_of", "reference_tilt_std_of",
           "CONTROL_PERIOD", "MAX_RUN_SECONDS"]
