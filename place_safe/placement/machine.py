"""Placement logic: the state machine that lowers a held cup onto a surface and lets go only when it is safe.

Concept: :class:`PlacementMachine` is pure decision logic (no simulator, no driver). Each control tick it
gets the fused surface (:class:`place_safe.fusion.FusedPlane` or None) and a :class:`RobotState`, and
returns one :class:`Command` for the robot; :class:`place_safe.placement.loop.PlacementLoop` applies it.
A diagram of the machine is in ``docs/placement.md``.

Phases::

    IDLE --plane--> APPROACH --near--> DESCEND --at stop clearance, or contact at the surface--> CHECK
    (in APPROACH, before descending below where the landing footprint is still in view: survey --
     move sideways (and up if too low) until the surface map has seen the footprint supported in
     ``footprint_frames`` frames, then back over the landing spot)
    CHECK --level, planar, close, enough fresh planes--> RELEASE (open gripper, wait, retreat up) --> DONE
    CHECK --still too high--> DESCEND (at most ``max_checks`` times)
    CHECK --footprint points vetoed or in doubt that no second look has seen--> APPROACH (once: up to
                       ``traverse_clearance`` first, then the second look from over them, back and down again)
    any active phase --tilted / not planar / no plane / stale plane / sensor timeout / no support under
                       the footprint (edge, step, clutter) / obstacle (contact
                       above the surface) / travel limit, or a surface farther than it (a floor
                       past an edge) / deadline--> REFUSE (retreat up keeping the cup)
                       --> ABORTED (at CHECK, with the arm at rest and the sensor still answering, a plane
                       that is only stale is waited on until ``check_timeout``: a stalled transfer or a
                       corrupted frame delays the check, it does not refuse it; the check then decides on
                       a window of planes all measured after the gap, and not from the too-close hold)
    any phase before the release --robot fault, invalid robot state, robot clock frozen or running
                       backwards, internal error--> ABORTED (the robot holds the cup where it stopped)

The release rule (the only path to :attr:`CommandKind.OPEN_GRIPPER`), checked on the tick it fires:

* the robot reports no fault and a finite, rigid pose, a finite non-negative contact force and a clock
  that advances;
* the fused plane is finite, fresh (``plane_timeout``), its tilt lies in ``[0, max_tilt]`` with
  ``level_confidence`` (``tilt + z * sigma <= max_tilt``, ``sigma`` from :meth:`PlacementMachine.tilt_sigma`)
  and its spread within ``max_std_angle`` / ``max_std_offset`` (every comparison fails closed on NaN);
* it rests on at least ``check_frames`` distinct measurement times, each after the stop command plus
  ``check_settle`` and none in the future (the same frame fed twice counts once), and the TCP has not
  moved more than ``rest_tolerance`` since then (the arm really stopped);
* the cup's axis is within ``max_tilt`` of the surface normal (it lands on its base, not its rim);
* the surface map (:mod:`place_safe.fusion.surface_map`) saw the landing footprint (the cup bottom plus
  ``footprint_margin``) in at least ``footprint_frames`` frames with every zone over it on the fused
  surface (within ``footprint_tolerance``) and reports no edge, step or clutter there -- observed, not
  extrapolated from the patch beside the cup the sensor sees at the end;
* the surface is still (:func:`~place_safe.placement.rules.still_problem`): the planes measured at rest
  (or, too close to read, the newest of the window) agree in offset within what their covariances allow,
  with ``still_confidence``, and show no trend; and they agree in normal, with no turn
  (:func:`~place_safe.placement.rules.slope_still_problem`: a table that tips under the cup), nor read the surface
  confidently steeper than ``max_tilt`` (:func:`~place_safe.placement.rules.rest_tilt_problem`); the newest of them
  is not far off the others (:func:`~place_safe.placement.rules.newest_plane_problem`), and no plane the fusion's
  gates rejected is pending (:func:`~place_safe.placement.rules.pending_problem`): CHECK waits on these until
  ``check_timeout``;
* the cup bottom's clearance above the plane lies in ``[floor, release_clearance]``, ``floor`` the noise's
  allowance below zero (:func:`~place_safe.placement.rules.clearance_floor`, at most ``release_clearance``),
  or the cup is in contact (``contact_force``) with a clearance in ``[-max_penetration, contact_limit]``
  (:func:`~place_safe.placement.rules.contact_limit`: ``contact_clearance``, at most ``cup_radius tan(max_tilt)``
  less the travel while the touch is detected, above which something under the cup could leave it tilted beyond
  ``max_tilt``):
  contact higher above the sensed surface is an obstacle, and a cup below the sensed surface without
  contact means the estimate is wrong or the surface moved; both refuse.

A contact reported far above the sensed surface during the descent is first a question about the force
reading: the arm stops hard (``obstacle_decel``) and it is an obstacle only if the contact lasts
``obstacle_confirm`` s with the arm at rest; one that vanishes is noted (:attr:`PlacementMachine.notes`)
and the descent goes on, at most ``max_unconfirmed`` times. Within ``near_surface_distance`` of the surface
the approach is no faster than ``near_surface_speed`` (the arm's robot file sets 50 mm/s). A plane the fusion's
gates rejected as an outlier is no evidence for the fused surface, but one closer to the cup slows the descent at
once to what it could stop from (``FusedPlane.pending``): a box put under the cup is rejected
``max_consecutive_rejects`` times before the fused plane follows it.

Every phase has a deadline counted both on the robot clock and in control ticks (``period`` seconds
each), so a frozen or jumping robot clock still ends the machine. :meth:`PlacementMachine.step` never
raises: bad robot state, bad planes and internal errors end in ABORTED or REFUSE with the reason.
Every transition is logged with its reason (:attr:`PlacementMachine.log`).

Conventions: SI units (m, m/s, m/s^2, rad, s, N). Poses are base-frame 4x4 matrices (see
:mod:`place_safe.robot.interface`); the cup frame has its origin at the centre of the cup bottom and +z up
out of the cup, so the cup moves "down" along its -z (the tool axis). Twists are (vx, vy, vz, wx, wy, wz).
"""

from __future__ import annotations

import logging
import math
from collections import deque
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from place_safe.geometry import MAX_REACH, transform_problem
from place_safe.fusion.plane_filter import FusedPlane, clearance_along
from place_safe.placement.config import PlacementConfig
from place_safe.placement import rules
from place_safe.placement.rules import number
from place_safe.placement.speed import braking_speed, descent_speed, stoppable_speed

log = logging.getLogger("place_safe.placement.machine")


class Phase(str, Enum):
    IDLE = "idle"
    APPROACH = "approach"
    DESCEND = "descend"
    CHECK = "check"
    RELEASE = "release"
    DONE = "done"
    REFUSE = "refuse"
    ABORTED = "aborted"


#: Phases in which the machine has finished.
FINAL = (Phase.DONE, Phase.ABORTED)


@dataclass
class RobotState:
    """What the machine needs from the robot each tick (base frame, SI units)."""

    time: float  # s, robot clock
    base_T_tcp: np.ndarray  # 4x4
    base_T_cup: np.ndarray  # 4x4, origin at the cup bottom centre, +z up out of the cup
    contact_force: float = 0.0  # N
    fault: str | None = None
    last_frame_time: float | None = None  # s, when the newest sensor frame (accepted or not) arrived
    last_frame_age: float | None = None  # s, from that frame's measurement to its arrival (None: not known)
    # 4x4, the sensor's pose (None: not known; the loop always gives it): a frame too close to read is believed only
    # with the sensor itself that close to the fused plane (TOO_CLOSE_SENSOR_RANGE)
    base_T_sensor: np.ndarray | None = None

    def problem(self) -> str | None:
        """Why this state cannot be trusted (fault, malformed or non-finite values), or None."""
        if (fault := rules.fault_text(self.fault)) is not None:
            return f"robot fault: {fault}"
        for name in ("base_T_tcp", "base_T_cup"):
            if (why := transform_problem(getattr(self, name), reach=MAX_REACH)) is not None:
                return f"robot state {name} {why}"
        if number(self.time) is None:
            return "robot time is not a finite number"
        f = number(self.contact_force)
        if f is None or f < 0:
            return "robot contact force is not a finite non-negative number"
        if f > MAX_FORCE_READING:
            return f"robot contact force {f:.3g} N is no reading of a touch (> {MAX_FORCE_READING:g} N)"
        if self.last_frame_time is not None and number(self.last_frame_time) is None:
            return "time of the last sensor frame is not a finite number"
        if self.last_frame_age is not None and number(self.last_frame_age) is None:
            return "age of the last sensor frame is not a finite number"
        return None


#: N: no contact force an arm this size can read (a UR5 carries 5 kg; its joints stall at a few hundred newtons); a
#: larger reading is a broken estimate, refused as robot state, not taken as a touch 1e308 N strong.
MAX_FORCE_READING = 1e4
#: m: the farthest the sensor can be from a surface it reads "too close" (:mod:`place_safe.recovery.too_close` fires
#: on a median zone range under 14.8 mm, on a dark centre zone under 3 cm, on a calibrated plane under 14.8 mm; the
#: real sweep's 2.0 cm frame is its farthest), with 15 mm for the near mapping's errors; farther, such a frame sees
#: something else (nothing beyond the cover glass), not the fused plane's surface
TOO_CLOSE_SENSOR_RANGE = 0.045


class CommandKind(str, Enum):
    HOLD = "hold"  # keep doing what was last commanded
    SPEED = "speed"  # speedL(twist, accel)
    STOP = "stop"  # stopL(accel)
    OPEN_GRIPPER = "open_gripper"


@dataclass(frozen=True)
class Command:
    kind: CommandKind
    twist: tuple[float, ...] | None = None  # (6,) for SPEED
    accel: float = 0.5

    @classmethod
    def hold(cls) -> "Command":
        return cls(CommandKind.HOLD)


@dataclass
class Transition:
    time: float
    source: Phase
    target: Phase
    reason: str

    def to_dict(self) -> dict:
        return {"time": self.time, "from": self.source.value, "to": self.target.value, "reason": self.reason}


#: Control ticks in a row without the robot clock advancing after which the clock counts as frozen.
CLOCK_STALL_TICKS = 25
#: m: a survey move (out to see the footprint, or back over the landing spot) is done this close.
SURVEY_DONE = 0.001
#: m: the second look at doubtful footprint points has arrived this close to its pose.
RECHECK_ARRIVED = 0.003
#: 1/s: a sideways move ends no faster than this times the distance left (an arm tracking a speed command
#: lags it by speed / its Cartesian gain; a slower end does not overshoot the landing spot).
LATERAL_GAIN = 8.0
#: m of view margin kept when descending before the footprint was seen.
SURVEY_VIEW_SLACK = 0.005
#: m above the certifying height (the surface map's close height) by which the view is centred on the
#: footprint while the cup descends towards it, and how much faster than the even pace that needs the sideways
#: move goes (it finishes early, not late).
PASS_AHEAD = 0.03
PASS_PACE = 1.5
#: s the survey may go on with footprint points in doubt (seen raised or lowered, not seen clean since from as high or
#: centred on them) before it takes the second look, centred on them: the survey's own passes see them from its
#: pose again and again, and from there a zone reaching past the footprint may keep raising them.
DOUBT_PATIENCE = 2.0
#: s the footprint may be in view from close enough to certify it (over one pass or several) without being certified,
#: beyond the sensor's latency, before the survey refuses the cup: three frames certify it within half a second even on
#: a slow bus, and over a step that keeps part of the footprint off the surface the survey went on climbing back to its
#: pose and descending again for the whole 30 s of the descent (a board's edge 12 mm under the rim: random board 141
#: of seed 4).
SURVEY_PATIENCE = 3.0
#: Arrival gaps of sensor frames over which the machine measures the frame period (median).
FRAME_GAPS = 8
#: The quantile of the last ``FRAME_GAPS`` frames' ages at arrival (measurement to arrival, robot clock) that counts
#: as the sensor's latency where it exceeds ``sensor_latency`` (:meth:`PlacementMachine._latency`): a bus slower
#: than the configuration assumes (a Linux I2C adapter's default 100 kHz delivers frames 0.5 s old, 400 kHz
#: 0.12-0.17 s) slows the descent to what it can stop from, where the configured 0.15 s would brake too late; a
#: single late frame (a latency spike) does not.
LATENCY_QUANTILE = 0.8
#: s over which the largest age the fused plane reached counts as the sensor's latency (see
#: :meth:`PlacementMachine._latency`): a bus that stalls now and then is as slow as its stalls, since a surprise at
#: the start of the next one reaches the machine that late (2 s forgot a stall 2.5 s before the next, and a box was
#: met at 0.055 m/s; a placement takes 2.5-6 s).
LATENCY_MEMORY = 5.0
#: Fraction of ``footprint_margin``: a cup bottom this close sideways to the landing spot lies inside the
#: footprint the survey certified (its disc reaches ``footprint_margin`` past the cup's rim), so the descent
#: below ``traverse_clearance`` may go on while the last of the way back is made.
OVER_FOOTPRINT = 0.8
#: s the robot clock may step back (rounding) before it counts as running backwards.
CLOCK_BACK_TOLERANCE = 1e-6


@dataclass
class _Check:
    """CHECK phase state: when the stop was commanded; where the TCP was once enough planes were in."""

    t_stop: float
    at_rest: np.ndarray | None = None
    # (verdict, why) of a footprint verdict during this check, once a plane at rest was fused, that did not clear the
    # footprint (a problem, or points in doubt): the first such, or a later one that says where to look from when it
    # did not; a verdict that comes and goes with the plane refined at rest must not release on a clean tick
    doubt: tuple[Any, str] | None = None
    # s: the newest measurement in the fused plane when it first went stale at rest (None: it never did); until the
    # window holds only planes measured after it, the check does not decide (the surface may have moved unseen)
    gap: float | None = None


@dataclass
class _Recheck:
    """The second look at doubtful footprint points: when it began (``t0``: reset while the cup still climbs to
    ``traverse_clearance``; ``begun``: when it was decided), its ticks, the close frames the surface map had counted
    when it arrived over them (None: still moving), and whether it is over."""

    t0: float
    ticks: int = 0
    arrived: float | None = None
    done: bool = False
    begun: float = field(init=False)
    climb_ticks: int = 0

    def __post_init__(self) -> None:
        self.begun = self.t0


@dataclass
class _Suspect:
    """A contact reported far above the sensed surface, being confirmed: when it was first reported, its
    ticks, the TCP position of the previous tick and since when the arm is at rest (None: still moving)."""

    t0: float
    force: float
    clearance: float
    ticks: int = 0
    last_tcp: np.ndarray | None = None
    rest_since: float | None = None


@dataclass
class _Retreat:
    """RELEASE / REFUSE phase state: TCP height when the retreat started (None until it starts)."""

    z0: float | None = None


def _doubt_said(verdict: Any) -> str:
    """' (what the latest view of the points in doubt saw)' from a footprint verdict, or '' when it says nothing."""
    doubt = getattr(verdict, "doubt", None)
    return f" ({doubt})" if isinstance(doubt, str) and doubt else ""


class PlacementMachine:
    """The placement state machine (see module docstring). Feed :meth:`step` once per control tick.

    ``period``: the control period in seconds (deadlines are also counted in ticks of this length).
    """

    def __init__(self, config: PlacementConfig | None = None, period: float = 0.008) -> None:
        self.config = config if config is not None else PlacementConfig()
        if not (isinstance(period, (int, float)) and math.isfinite(period) and period > 0):
            raise ValueError(f"control period must be a positive number of seconds, got {period!r}")
        self.period = float(period)
        self.reset()

    def reset(self) -> None:
        self.phase = Phase.IDLE
        self.reason = ""
        self.outcome: str | None = None  # "released" / "refused" once final
        self.decision = ""  # why the cup was released or refused (the reason of that transition)
        self.log: list[Transition] = []
        self.gripper_opened = False
        self.last_clearance = math.nan
        # (cup clearance, sensor height above the plane or None) when the current run of too-close frames began
        self._blind_from: tuple[float, float | None] | None = None
        self._tick_view: tuple[Any, Any] = (None, None)  # this tick's (fused plane, robot state), for _blind
        self.ticks = 0
        self._t_phase = math.nan
        self._phase_ticks = 0
        self._t_start = math.nan
        self._last_now: float | None = None
        self._stall = 0
        self._start_pos: np.ndarray | None = None
        self._check: _Check | None = None
        self._retreat = _Retreat()
        self._checks = 0
        self._descent_t0 = math.nan
        self._descent_ticks = 0
        self._last_twist: tuple[float, ...] | None = None
        self._footprint: Any = None
        self._surveyed = False
        self._recheck: _Recheck | None = None
        self._look_target: np.ndarray | None = None  # TCP position (base) of a second look made the way CHECK's is
        self._doubt_since: float | None = None  # robot time the survey's verdict began to have points in doubt
        self._doubt_ticks = 0
        self._doubt_after_look = False  # the doubt counted since the second look ended (not since before it)
        self._suspect: _Suspect | None = None
        self._unconfirmed = 0
        self.notes: list[str] = []  # what the machine noticed without changing phase (unconfirmed contacts)
        self._sideways = False
        self._back = math.inf  # m sideways from over the landing spot (known once the footprint is seen)
        # time budget: s of robot time spent on each part of the placement (accelerate, cruise, brake,
        # survey, slow band, stop, check frames, release, retreat, ...), counted tick by tick
        self.budget: dict[str, float] = {}
        self._budget_prev: tuple[float | None, np.ndarray | None] = (None, None)
        self._budget_bucket: str | None = None
        self._hint: str | None = None
        self._survey_share = 0.0  # fraction of this tick's time the survey takes from the descent (the rest: _hint)
        self._view_cap = math.inf  # m/s: the pass-through's limit on the descent this tick (see _pass_speed)
        self._certify_ticks = 0  # ticks the footprint was in view from the certifying height, not yet certified
        self._passed: float | None = None  # robot time the footprint was last in view from the certifying height
        self._window_t0: float | None = None  # ... and first, in this pass
        self._early_back = False  # the way back began before the certifying frames were in (once only)
        self._early_back_failed = False  # ... and they did not certify the footprint
        self._early_back_t = math.nan
        self._last_frame: float | None = None  # arrival time of the newest frame, and the gaps between arrivals
        self._frame_gaps: list[float] = []
        self._frame_ages: list[float] = []  # s, the last FRAME_GAPS frames' ages at arrival (see _latency)
        self._pending_c = math.inf  # m, cup clearance to the closest gate-rejected plane pending (_descent_speed)
        # (robot time, the fused plane's age then) of the last LATENCY_MEMORY s, ages falling from the front (the
        # largest first: a later, older reading drops those it outranks), see _latency
        self._plane_ages: deque[tuple[float, float]] = deque()
        self._budget_share = 0.0
        self._tcp_speed = 0.0

    @property
    def finished(self) -> bool:
        return self.phase in FINAL

    # -- transitions -----------------------------------------------------------------------------
    def _go(self, target: Phase, t: float, reason: str) -> None:
        tr = Transition(float(t), self.phase, target, reason)
        self.log.append(tr)
        log.info("t=%.3f s %s -> %s: %s", t, self.phase.value, target.value, reason)
        self.phase, self.reason, self._t_phase, self._phase_ticks = target, reason, float(t), 0
        self._last_twist = None
        if target in (Phase.RELEASE, Phase.REFUSE) or (target == Phase.ABORTED and not self.decision):
            self.decision = reason
        if target == Phase.DONE:
            self.outcome = "released"
        elif target == Phase.ABORTED:
            self.outcome = "refused"
        if target in (Phase.RELEASE, Phase.REFUSE):
            self._retreat = _Retreat()

    def _refuse(self, t: float, reason: str, decel: float | None = None) -> Command:
        self._go(Phase.REFUSE, t, reason)
        return Command(CommandKind.STOP, accel=self.config.accel if decel is None else decel)

    def _abort(self, t: float, why: str, faulted: bool = False) -> Command:
        """End now holding the cup (or, once it is released, end as released). A faulted robot has
        stopped by itself and gets no further command (HOLD); otherwise the machine commands a stop."""
        if self.gripper_opened:
            self._go(Phase.DONE, t, f"cup released; retreat stopped: {why}")
        else:
            self._go(Phase.ABORTED, t, f"{why}; the robot holds the cup where it stopped")
        return Command.hold() if faulted else Command(CommandKind.STOP, accel=self.config.accel)

    def abort(self, t: float, why: str) -> Command:
        """End the placement now (a fault outside the machine's view, e.g. the loop's); never raises. Once
        finished, the outcome stands and ``why`` is only appended to :attr:`reason` (and noted)."""
        if self.finished:
            self.reason = f"{self.reason}; then {why}"
            self.notes.append(str(why))
            return Command.hold()
        return self._abort(t if isinstance(t, (int, float)) else math.nan, why)

    def gripper_failed(self, t: float, why: str) -> None:
        """The open-gripper command failed: the cup is taken as still held and the placement refused."""
        self.gripper_opened = False
        if not self.finished:
            self.decision = f"{why}; the gripper may still hold the cup"
            self._go(Phase.ABORTED, t if isinstance(t, (int, float)) else math.nan, self.decision)

    def _speed(self, v: np.ndarray, lateral: bool = False) -> Command:
        """speedL at linear velocity ``v`` (3,) m/s, no rotation; at ``lateral_accel`` at most if the move
        (or the one it replaces) goes sideways (the liquid's lateral acceleration), else at ``accel``."""
        tw = tuple(float(x) for x in v) + (0.0, 0.0, 0.0)
        if tw == self._last_twist:
            return Command.hold()
        prev = self._sideways
        self._sideways = lateral
        self._last_twist = tw
        accel = self.config.accel
        if lateral or prev:
            accel = min(accel, self.config.lateral_accel)
        return Command(CommandKind.SPEED, tw, accel)

    def _descent_speed(self, c: float) -> float:
        """Speed (m/s) down towards the surface at cup clearance ``c`` (:func:`~place_safe.placement.speed.descent_speed`),
        and no faster than at the clearance to a closer plane the fusion's gates have rejected and not yet outweighed
        (:meth:`_pending_clearance`): a surface that rose (a box put under the cup) is rejected as an
        outlier ``max_consecutive_rejects`` times before the fused plane follows it, and the braking assumed news
        ``latency`` s late, not that much later (an adversarial search: a box appearing 15-21 mm under the cup was met at
        0.032-0.037 m/s)."""
        cfg = self.config
        # (descent_speed grows with the clearance: the closer of the two is the slower)
        return descent_speed(min(c, self._pending_c), cfg.slow_clearance, cfg.brake_margin, self._latency(), cfg.accel,
                             cfg.approach_speed, cfg.descend_speed)

    def _pending_clearance(self, plane: FusedPlane, state: RobotState) -> float:
        """Cup clearance (m) to the closest of the gate-rejected planes pending in ``plane`` (``FusedPlane.pending``:
        rejected, and fewer than :data:`~place_safe.fusion.plane_filter.PENDING_CLEARS` planes accepted since), inf
        without any (malformed ones are skipped: the fused plane's
        own checks decide)."""
        best = math.inf
        for item in getattr(plane, "pending", ()) or ():
            try:
                n, d = item
                c = self._cup_clearance(n, float(d), state)
            except (TypeError, ValueError, OverflowError):
                continue
            if math.isfinite(c):
                best = min(best, c)
        return best

    def _motion_bucket(self, v: float) -> str:
        """Budget bucket of a descent commanded at ``v`` m/s: accelerating (the arm is still slower than
        a speed it was given), cruising at ``approach_speed``, or braking (the profile holds it lower)."""
        if v >= self.config.approach_speed - 1e-9:
            return "cruise" if self._tcp_speed >= 0.95 * v else "accelerate"
        return "accelerate" if self._tcp_speed < 0.95 * v - 0.005 else "brake"

    def _bucket(self, now: float) -> str | None:
        """What the time until the next tick is spent on (see :attr:`budget`)."""
        if self._suspect is not None:
            return "confirm contact"
        p = self.phase
        if p == Phase.IDLE:
            return "wait for surface"
        if p == Phase.APPROACH:
            return self._hint or "brake"
        if p == Phase.DESCEND:
            return "slow band"
        if p == Phase.CHECK:
            chk = self._check
            return "stop" if chk is None or now - chk.t_stop < self.config.check_settle else "check frames"
        if p == Phase.RELEASE:
            return "release" if self._retreat.z0 is None else "retreat"
        if p == Phase.REFUSE:
            return "retreat"
        return None

    def _account(self, state: RobotState, now: float) -> None:
        """Add the time since the previous tick to what it was spent on; measure the TCP speed."""
        prev_t, prev_pos = self._budget_prev
        try:
            pos = np.asarray(state.base_T_tcp, dtype=float)[:3, 3].copy()
        except (TypeError, ValueError, IndexError):
            pos = None
        if prev_t is not None and now > prev_t:
            if self._budget_bucket is not None:
                dt, share = now - prev_t, self._budget_share
                if share > 0:  # the survey slowed the descent: its share of the tick is the survey's
                    self.budget["survey"] = self.budget.get("survey", 0.0) + dt * share
                self.budget[self._budget_bucket] = self.budget.get(self._budget_bucket, 0.0) + dt * (1.0 - share)
            if pos is not None and prev_pos is not None and np.all(np.isfinite(pos)):
                self._tcp_speed = float(np.linalg.norm(pos - prev_pos)) / (now - prev_t)
        self._budget_prev = (now, pos)
        frame = number(getattr(state, "last_frame_time", None))
        if frame is not None and self._last_frame is not None and frame > self._last_frame:
            self._frame_gaps = (self._frame_gaps + [frame - self._last_frame])[-FRAME_GAPS:]
        age = number(getattr(state, "last_frame_age", None))
        if frame is not None and age is not None and (self._last_frame is None or frame > self._last_frame):
            self._frame_ages = (self._frame_ages + [max(age, 0.0)])[-FRAME_GAPS:]
        if frame is not None:
            self._last_frame = frame

    def _latency(self) -> float:
        """s from a measurement to the machine acting on it, as the descent's braking assumes it: ``sensor_latency``,
        or the measured one where it is longer: :data:`LATENCY_QUANTILE` of the last frames' ages at arrival (once
        ``FRAME_GAPS // 2`` are known), and the largest age the fused plane reached in the last :data:`LATENCY_MEMORY`
        s (now included). News comes no sooner than the evidence has been old: a bus that slows near the surface keeps
        the descent stoppable from the first tick the evidence ages, and one that stalls now and then (delivering its
        backlog, whose newest frame is young) as slow as its stalls, where the arrival ages alone followed half a
        second late or not at all (an adversarial search: a box met at 0.055-0.057 m/s)."""
        latency = max(self.config.sensor_latency, self._plane_ages[0][1] if self._plane_ages else 0.0)
        if len(self._frame_ages) >= FRAME_GAPS // 2:
            latency = max(latency, float(np.quantile(self._frame_ages, LATENCY_QUANTILE)))
        return latency

    def _frame_period(self) -> float | None:
        """s between frames, measured (the median of the last ``FRAME_GAPS`` arrival gaps; None before)."""
        if len(self._frame_gaps) < FRAME_GAPS // 2:
            return None
        return float(np.median(self._frame_gaps))

    def _elapsed(self, now: float, t0: float, ticks: int) -> float:
        """Time since ``t0``: the larger of the robot-clock and the tick count (a frozen clock still ends)."""
        return max(now - t0 if math.isfinite(t0) else 0.0, ticks * self.period)

    # -- checks (each fails closed) --------------------------------------------------------------
    def _blind(self, note: str | None) -> bool:
        """Whether the last frame was too close to read and that run of such frames began with the cup close
        enough to the fused plane for the sensor to be that close to it (``too_close_clearance``, on the
        clearance computed last before the run) and, where the sensor's pose is known, the sensor itself within
        :data:`TOO_CLOSE_SENSOR_RANGE` of that plane. Keeps where the run began (a run that began far above the plane
        sees something in front of the sensor, however close the cup gets on the old plane). The sensor's own
        distance matters where it sits well above the cup's bottom (the packaged tool: 7 cm): there a frame "too
        close" with the cup 2 cm up cannot be the table (nothing beyond the cover glass: the table pulled away, a
        black patch), and holding the old plane released a cup 0.3 m above the surface (a review, session 74)."""
        if not rules.too_close(note):
            self._blind_from = None
            return False
        if self._blind_from is None:
            self._blind_from = (self.last_clearance, self._sensor_above(*self._tick_view))
        clearance, sensor = self._blind_from
        return clearance <= self.config.too_close_clearance and (sensor is None or sensor <= TOO_CLOSE_SENSOR_RANGE)

    def _sensor_above(self, plane: FusedPlane | None, state: RobotState) -> float | None:
        """m of the sensor above the fused plane along its normal, None where the state gives no sensor pose, NaN
        where it cannot be computed (no plane, a malformed pose or plane: :meth:`_blind` then believes no
        too-close frame)."""
        pose = getattr(state, "base_T_sensor", None)
        if pose is None:
            return None
        try:
            t = np.asarray(pose, dtype=float)
            if plane is None or transform_problem(t, reach=MAX_REACH) is not None:
                return math.nan
            height = float(np.dot(np.asarray(plane.normal_base, dtype=float), t[:3, 3]) - float(plane.offset_base))
        except (TypeError, ValueError, AttributeError, OverflowError):
            return math.nan
        return abs(height) if math.isfinite(height) else math.nan

    def _clearance(self, plane: FusedPlane, state: RobotState) -> float:
        try:
            return self._cup_clearance(plane.normal_base, plane.offset_base, state)
        except ValueError:
            return math.nan

    def _cup_clearance(self, normal: Any, offset: float, state: RobotState) -> float:
        """Travel (m) of the cup's bottom rim down its axis to the base-frame plane ``normal . x = offset``
        (:func:`~place_safe.fusion.plane_filter.clearance_along`; ValueError for a malformed plane or pose)."""
        cup = np.asarray(state.base_T_cup, dtype=float)
        axis = cup[:3, 2]
        return float(clearance_along(normal, offset, cup[:3, 3], -axis, self.config.cup_radius, axis))

    def _lateral(self, move: np.ndarray, limit: float) -> np.ndarray:
        """Velocity (3,) along ``move`` (m) at most ``limit`` m/s, slowing so it stops at its end."""
        dist = float(np.linalg.norm(move))
        if not (dist > SURVEY_DONE):
            return np.zeros(3)
        return np.round(move / dist * self._lateral_speed(dist, limit), 3)

    def _lateral_speed(self, dist: float, limit: float) -> float:
        """m/s of a sideways move ``dist`` m from its end: at most ``limit``, slowing so it stops there."""
        a = min(self.config.accel, self.config.lateral_accel)
        return min(limit, 0.8 * math.sqrt(2.0 * a * dist), LATERAL_GAIN * dist)

    def _lateral_time(self, dist: float, target: float, speed: float) -> float:
        """s a sideways move :meth:`_lateral` makes (no faster than ``speed`` m/s now) takes from ``dist`` m to
        ``target`` m from its end (at least one control period)."""
        t, d = 0.0, dist
        step = max((dist - target) / 40.0, 1e-4)
        while d > target:
            v = self._lateral_speed(d, max(speed, 1e-3))
            t += step / v
            d -= step
        return max(t, self.period)

    def _axial(self, dist: float) -> float:
        """Speed (m/s) along the tool axis for a move of ``dist`` m: at most ``approach_speed``, slowing so
        it stops at its end (0 when done)."""
        if not (abs(dist) > SURVEY_DONE):
            return 0.0
        return math.copysign(min(self.config.approach_speed, 0.8 * math.sqrt(2.0 * self.config.accel * abs(dist))),
                             dist)

    def _survey(self, state: RobotState, c: float, now: float) -> Command | np.ndarray | None:
        """See the landing footprint from close enough on one surface, then come back over the landing spot.

        Returns a command (the survey move, or a refusal), a sideways velocity (3,) to add to the descent
        (the way back over the landing spot, taken while descending), or None to let the descent go on.
        The footprint must be seen from no higher than the surface map's close height, where zones are
        small enough to show clutter in it. While the straight descent would bring it there with the
        footprint still in view, the cup simply descends; otherwise the sensor moves over the footprint,
        sideways and down (or up) at once, to the survey pose, and waits there for the frames."""
        cfg = self.config
        if cfg.footprint_frames == 0:
            return None
        fp = self._footprint
        tcp = np.asarray(state.base_T_tcp, dtype=float)[:3, 3]
        down = -np.asarray(state.base_T_cup, dtype=float)[:3, 2]
        if self._surveyed or rules.footprint_seen(self._footprint) >= cfg.footprint_frames:
            self._surveyed = True  # latched: no second survey; CHECK still needs the footprint supported
            return self._way_back(tcp, down, c)
        if fp is None:
            if self._elapsed(now, self._descent_t0, self._descent_ticks) > cfg.acquire_timeout:
                return self._refuse(now, "no support evidence: no surface map of the cup's landing footprint")
            self._hint = "survey"
            return self._speed(np.zeros(3))
        if self._early_back and not self._early_back_failed \
                and self._elapsed(now, self._early_back_t, 0) > self._latency() + (self._frame_period() or 0.0):
            self._early_back_failed = True  # the frames taken before the way back began are in: not certified
        if (self._passed is not None and not bool(getattr(fp, "in_view", False))
                and self._elapsed(now, self._passed, 0) <= self._latency()):
            # the view left the footprint, but frames taken over it from the certifying height are still in
            # flight (they arrive sensor_latency after they were taken): keep descending -- no lower than
            # the descent's cap for uncertified ground lets the cup stop above traverse_clearance -- rather
            # than climbing back to the survey pose, which frames that do not certify it still bring
            return self._way_back(tcp, down, c) if self._early_back and not self._early_back_failed else None
        if self._passed is None or not bool(getattr(fp, "in_view", False)):
            self._passed = self._window_t0 = None
        if bool(getattr(fp, "in_view", False)):
            # pass through: the frames the sensor takes now arrive sensor_latency later; the descent goes on
            # while the footprint stays in view that long (if those frames do not certify it, the cup climbs
            # back to the survey pose: slower, never less safe -- nothing is released without them)
            margin = number(getattr(fp, "view_margin", None))
            need = number(getattr(fp, "certify_margin", None))
            need = max(need, 0.0) if need is not None else 0.0
            if margin is not None and margin > SURVEY_VIEW_SLACK and margin - need > SURVEY_VIEW_SLACK:
                self._view_cap = self._pass_speed(margin, need)
                if need <= 0:
                    self._passed = now  # frames taken now can certify the footprint
                    self._certify_ticks += 1
                    if self._certify_ticks * self.period > SURVEY_PATIENCE + self._latency():
                        return self._refuse(now, "no support evidence: the cup's footprint was in view from close "
                                                 f"enough for {self._certify_ticks * self.period:.1f} s and not seen "
                                                 f"on one surface (certified in {rules.footprint_seen(fp)} of the "
                                                 f"{cfg.footprint_frames} frames needed)")
                    self._window_t0 = now if self._window_t0 is None else self._window_t0
                    if self._frames_taken(now) and not self._early_back_failed:
                        # enough frames taken over the footprint: start back over the landing spot while
                        # they are in flight (the cup stays above traverse_clearance until they certify it);
                        # once only -- if they do not certify it, the survey pose and its wait follow
                        self._view_cap = math.inf
                        if not self._early_back:
                            self._early_back, self._early_back_t = True, now
                        return self._way_back(tcp, down, c)
                # keep descending: the footprint stays in view down to where frames certify it; meanwhile
                # centre the view on it (the view narrows on the way down)
                try:
                    move = np.asarray(getattr(fp, "look_shift"), dtype=float).reshape(3)
                except (TypeError, ValueError, AttributeError):
                    return None
                if not np.all(np.isfinite(move)):
                    return None
                side = move - down * float(move @ down)
                dist = float(np.linalg.norm(side))
                if not dist > SURVEY_DONE:
                    return None
                # paced: centred by the time the sensor is PASS_AHEAD above the certifying height at the
                # descent speed, no faster (the speed limit is on the whole move: a slower sideways move leaves
                # the descent more of it)
                t_go = (need + PASS_AHEAD) / max(self._descent_speed(c), cfg.descend_speed)
                return self._lateral(side, min(cfg.survey_speed, PASS_PACE * dist / t_go))
        # to the survey pose (the sensor over the footprint, just high enough to hold it), then wait there
        try:
            move = np.asarray(getattr(fp, "look_shift"), dtype=float).reshape(3)
        except (TypeError, ValueError, AttributeError):
            return self._refuse(now, "surface map gave no way to bring the cup's footprint into view")
        if not np.all(np.isfinite(move)):
            return self._refuse(now, "surface map gave no way to bring the cup's footprint into view")
        return self._toward(move, down, c)

    def _way_back(self, tcp: np.ndarray, down: np.ndarray, c: float) -> np.ndarray | None:
        """The sideways velocity (3,) back over the landing spot (the start pose's axis), sharing the speed
        limit with the descent; None once there. Sets ``_back`` (m still to go)."""
        cfg = self.config
        back = self._start_pos - tcp
        back -= down * float(back @ down)
        self._back = float(np.linalg.norm(back))
        if not self._back > SURVEY_DONE:
            return None
        # share the speed limit with the descent, in proportion to what each has left before the cup may
        # go below traverse_clearance (within half the footprint margin of the landing spot)
        limit = self._share(self._back, c - cfg.traverse_clearance)
        return self._lateral(back, limit)

    def _frames_taken(self, now: float) -> bool:
        """Whether ``footprint_frames`` frames (and one more, for the phase of the frame clock) were taken
        since the view first held the footprint from the certifying height (needs a measured frame period)."""
        period = self._frame_period()
        return (self._window_t0 is not None and period is not None
                and now - self._window_t0 >= (self.config.footprint_frames + 1) * period)

    def _pass_speed(self, margin: float | None, need: float) -> float:
        """Speed (m/s) at most while descending past the footprint: the sensor may still descend ``margin`` m
        before the footprint leaves the view and must descend ``need`` m before frames certify it. Between
        the two heights (the window) the cup must be able to stop, reacting ``sensor_latency`` late and
        braking at ``accel``, before the view loses the footprint (less ``SURVEY_VIEW_SLACK``), so that the
        certifying frames, which arrive ``sensor_latency`` after they were taken, are taken inside the window
        and no climb back to the survey pose is needed; above the window the planned braking at ``accel``
        reaches that speed at the window's top. With the frame period measured, the window may be crossed
        faster: in the time ``footprint_frames + 1`` frames take (frames still in flight when the view leaves
        the footprint count: :meth:`_survey` descends on, under the cap for uncertified ground, until they
        are in). (Faster descents left the window before the frames were in and climbed back.)"""
        cfg = self.config
        if margin is None:
            return math.inf
        window = margin - need - SURVEY_VIEW_SLACK
        inside = stoppable_speed(window, self._latency(), cfg.accel)
        period = self._frame_period()
        if period is not None and period > 0:
            # frames measured at this period: footprint_frames of them (and one more, for the phase of the
            # frame clock) are taken while the sensor crosses the window; those in flight when the view
            # leaves it still count (see _survey)
            inside = max(inside, window / ((cfg.footprint_frames + 1) * period))
        return braking_speed(need, cfg.accel, inside)

    def _toward(self, move: np.ndarray, down: np.ndarray, c: float) -> Command:
        """speedL towards a pose ``move`` (m, base frame) away: sideways at up to ``survey_speed``, along the
        tool axis (``down``) at up to ``approach_speed`` and never past the slow band, both slowing to stop
        at the pose."""
        cfg = self.config
        along = float(move @ down)  # > 0: down towards the surface
        if along > 0:  # never faster than the cup could stop before the slow band
            along = min(along, max(c - cfg.slow_clearance, 0.0))
        lateral = move - down * float(move @ down)
        side = self._lateral(lateral, self._share(float(np.linalg.norm(lateral)), along))
        axial = self._axial(along)
        self._hint = "survey"
        if axial > 0:  # down: the descent gets what the sideways move leaves of approach_speed
            axial = min(axial, math.sqrt(max(cfg.approach_speed ** 2 - float(side @ side), 0.0)))
            free = self._descent_speed(c)
            if free > 0:  # budget: the part of the descent still made is the descent's
                self._hint = self._motion_bucket(round(free, 3))
                self._survey_share = min(max(1.0 - axial / free, 0.0), 1.0)
        return self._speed(np.round(side + axial * down, 3), lateral=bool(np.any(side)))

    def _share(self, sideways: float, down: float) -> float:
        """Speed limit (m/s) of a sideways move of ``sideways`` m made while the cup descends ``down`` m: the
        moves share ``approach_speed`` (the arm's limit is on the whole speed) in proportion to their lengths,
        so that both end together; ``survey_speed`` when there is no descent to share with. At least
        ``descend_speed``."""
        cfg = self.config
        if not (down > SURVEY_DONE and sideways > 0):
            return cfg.survey_speed
        share = cfg.approach_speed * sideways / math.hypot(sideways, down)
        return min(cfg.survey_speed, max(share, cfg.descend_speed))

    def _second_look(self, state: RobotState, c: float, now: float) -> Command | None:
        """Before refusing for footprint points that only zones seeing more than one surface covered, look
        once more from over those points (the view centred on them, at the survey height): a corner zone
        reaches 4 cm past the footprint, so an edge or a box beside it puts a second surface into a zone
        that also covers part of the footprint. Returns the move or the wait, or None once the look is
        done (``footprint_frames`` close frames from there), timed out or not possible: then refuse. From below
        ``traverse_clearance`` the look is made the way CHECK's is (:meth:`_look_from_check`)."""
        cfg = self.config
        r = self._recheck
        if (r is not None and r.done) or not cfg.recheck_timeout > 0 or cfg.footprint_frames == 0:
            return None
        fp = self._footprint
        frames = number(getattr(fp, "close_frames", None))
        try:
            move = np.asarray(getattr(fp, "recheck_shift"), dtype=float).reshape(3)
        except (TypeError, ValueError, AttributeError):
            move = None
        if frames is None or move is None or not np.all(np.isfinite(move)):
            return None
        if c < cfg.traverse_clearance:
            # low (a problem from frames still in flight): sideways from here the cup would sweep into what the
            # zones saw beside the footprint. A first look goes the way CHECK's does (:meth:`_look_from_check`):
            # straight up to traverse_clearance, then over the points, made whatever the verdict says meanwhile (a
            # climb that gave way to the descent whenever the verdict cleared bounced between the two heights until
            # the descent's deadline). After any look begun before (under way, over, or left on its way when the
            # survey's frames cleared its points, which now show a problem again): refuse -- a second low look there
            # ended in the slow band touching the box (random scene 69 of seed 76, 16.7 N, refused at 7.8 s, not 3.7)
            if r is not None:
                return None
            self._aim_look(state, move, now)
            return self._look_from_check(state, c, now)
        if r is None:
            r = self._recheck = _Recheck(now)
        r.ticks += 1
        return self._look_there(r, move, frames, state, c, now)

    def _look_at_doubt(self, state: RobotState, c: float, now: float) -> Command | None:
        """The second look (:meth:`_second_look`) at footprint points in doubt that the survey has not cleared
        within :data:`DOUBT_PATIENCE`: no problem, but points seen raised (or lowered) and not seen clean since (the
        verdict's ``recheck_point``). Once begun it goes on as any second look (a doubt that comes and goes with the
        verdict ends it early); the cup then surveys, descends or refuses as the verdict says. Points still in doubt
        :data:`DOUBT_PATIENCE` after the look is over refuse the cup: the survey's passes would only see them again
        from where they were raised (until the surface map forgets its oldest frames). None: no look now."""
        fp = self._footprint
        r = self._recheck
        if r is None or r.done:
            if getattr(fp, "problem", None) is not None or getattr(fp, "recheck_point", None) is None:
                self._doubt_since, self._doubt_ticks = None, 0
                return None
            if r is not None and not self._doubt_after_look:  # the look is over: its own patience starts now
                self._doubt_since, self._doubt_ticks, self._doubt_after_look = None, 0, True
            if self._doubt_since is None:
                self._doubt_since = now
            self._doubt_ticks += 1
            if not self._elapsed(now, self._doubt_since, self._doubt_ticks) > DOUBT_PATIENCE:
                return None
            if r is not None:  # looked from over them already: the survey's passes would only see them again
                look = "looking from over them" if r.arrived is not None else "the second look at them (timed out)"
                return self._refuse(now, f"no support evidence: footprint points seen off the surface were not seen "
                                         f"clean within {DOUBT_PATIENCE:.1f} s of {look}" + _doubt_said(fp))
        return self._second_look(state, c, now)  # (None once the look is over)

    def _look_there(self, r: _Recheck, move: np.ndarray | None, frames: float | None, state: RobotState, c: float,
                    now: float) -> Command | None:
        """The part both second looks share: within ``recheck_timeout`` of ``r.t0``, the TCP ``move`` to the pose
        over the points (None: no move), then ``footprint_frames`` more close frames (``frames``, the verdict's
        count; None: not known) there. The move or the wait, or None once over (``r.done``)."""
        cfg = self.config
        if self._elapsed(now, r.t0, r.ticks) > cfg.recheck_timeout:
            r.done = True
            return None
        if move is not None and float(np.linalg.norm(move)) > RECHECK_ARRIVED:
            return self._toward(move, -np.asarray(state.base_T_cup, dtype=float)[:3, 2], c)
        if frames is None:
            r.done = True
            return None
        if r.arrived is None:
            r.arrived = frames
        if frames >= r.arrived + cfg.footprint_frames:
            r.done = True
            return None
        self._hint = "survey"
        return self._speed(np.zeros(3))

    def _look_from_check(self, state: RobotState, c: float, now: float) -> Command | None:
        """The second look decided at CHECK (:meth:`_can_look_again`), or for a problem first seen with the cup below
        ``traverse_clearance`` in the approach (:meth:`_second_look`), made whatever the verdict says meanwhile
        (a doubt that came up with the plane refined at rest may come and go with it): straight up to
        ``traverse_clearance`` first (sideways from a few millimetres up, the cup would sweep into what the
        zones saw beside the footprint), then to the pose over the doubtful points, then ``footprint_frames``
        close frames from there. Returns the move or the wait, or None when there is none or it is over (then
        the footprint is judged as in any approach, and the cup goes back over the landing spot and down)."""
        cfg = self.config
        r = self._recheck
        if self._look_target is None or r is None or r.done:
            return None
        r.ticks += 1
        if r.arrived is None and c < cfg.traverse_clearance:
            r.climb_ticks += 1
            if self._elapsed(now, r.begun, r.climb_ticks) > cfg.recheck_timeout:  # the arm did not rise
                r.done = True
                return None
            r.t0, r.ticks = now, 0  # the look's own time starts above traverse_clearance
            self._hint = "survey"
            down = -np.asarray(state.base_T_cup, dtype=float)[:3, 2]
            return self._speed(np.round(self._axial(min(c - cfg.traverse_clearance, -2.0 * SURVEY_DONE)) * down, 3))
        move = (self._look_target - np.asarray(state.base_T_tcp, dtype=float)[:3, 3]) if r.arrived is None else None
        return self._look_there(r, move, number(getattr(self._footprint, "close_frames", None)), state, c, now)

    def _go_look_again(self, state: RobotState, now: float, why: str, verdict: Any = None) -> Command:
        """CHECK -> APPROACH for the second look over the doubtful points of ``verdict`` (default the latest;
        :meth:`_look_from_check`), its TCP target fixed now; the arm holds this tick."""
        verdict = self._footprint if verdict is None else verdict
        self._aim_look(state, np.asarray(getattr(verdict, "recheck_shift"), dtype=float).reshape(3), now)
        self._check = None
        self._go(Phase.APPROACH, now, f"{why}: look again from over those points")
        self._descent_t0, self._descent_ticks = now, 0
        return Command.hold()

    def _aim_look(self, state: RobotState, move: np.ndarray, now: float) -> None:
        """Begin a second look made the way CHECK's is (:meth:`_look_from_check`): its TCP target ``move`` (m, base
        frame) from the TCP now, and its clock."""
        self._look_target = np.asarray(state.base_T_tcp, dtype=float)[:3, 3] + move
        self._recheck = _Recheck(now)

    def _doubted(self) -> bool:
        """Whether footprint points the survey had certified are in doubt again (the verdict's ``supported`` below
        ``footprint_frames`` after the survey latched): a later view from over the footprint saw them raised. The
        descent then keeps the cap for uncertified ground, as before the survey; CHECK looks at them again (random
        scene 10 of seed 75: a box 5 mm inside the cup's rim, raised in two views after three clean ones, was met at
        full speed, 38.5 N)."""
        return self._surveyed and rules.footprint_seen(self._footprint) < self.config.footprint_frames

    def _looked(self) -> bool:
        """Whether a second look has been made: arrived over the doubtful points, ended (done, or timed out) or decided
        the way CHECK's is (:meth:`_look_from_check`). A look at points in doubt left on its way there, because the
        survey's frames cleared them, is not."""
        r = self._recheck
        return r is not None and (r.arrived is not None or r.done or self._look_target is not None)

    def _look_said(self) -> str:
        """What a refusal for the footprint adds about the second look: seen from over the points, or a look that
        ended before it got there (timed out, the arm did not rise); nothing when none was made."""
        r = self._recheck
        if r is not None and r.arrived is not None:
            return " (also from over those points)"
        return " (the second look at them timed out before it got there)" if self._looked() else ""

    def _can_look_again(self, verdict: Any = None) -> bool:
        """Whether a footprint problem, or points in doubt, found at CHECK may send the cup back up for the second
        look (once: no second look made yet (:meth:`_looked`), the rule and its time on, and a verdict -- default
        the latest -- that says where to look from)."""
        cfg = self.config
        verdict = self._footprint if verdict is None else verdict
        if self._looked() or not cfg.recheck_timeout > 0 or cfg.footprint_frames == 0:
            return False
        try:
            move = np.asarray(getattr(verdict, "recheck_shift"), dtype=float).reshape(3)
        except (TypeError, ValueError, AttributeError):
            return False
        return bool(np.all(np.isfinite(move))) and number(getattr(self._footprint, "close_frames", None)) is not None

    def _footprint_doubt(self) -> str | None:
        """Why the latest footprint verdict does not clear the footprint (a problem, or points in doubt: supported
        in fewer than ``footprint_frames`` frames), or None."""
        cfg = self.config
        if (why := rules.footprint_problem(self._footprint, cfg)) is not None:
            return why
        if cfg.footprint_frames and rules.footprint_seen(self._footprint) < cfg.footprint_frames:
            return "no support evidence: footprint points in doubt" + _doubt_said(self._footprint)
        return None

    def tilt_sigma(self, plane: FusedPlane) -> float:
        """Standard error (rad) of the fused plane's tilt (:func:`place_safe.placement.rules.tilt_sigma`)."""
        return rules.tilt_sigma(plane)

    def check_frames_needed(self, plane: FusedPlane) -> int:
        """Post-stop measurements CHECK waits for (:func:`place_safe.placement.rules.check_frames_needed`)."""
        return rules.check_frames_needed(plane, self.config)

    def post_stop_stamps(self, plane: FusedPlane, now: float) -> list[float]:
        """Distinct measurement times in the fused plane taken after the stop (+ ``check_settle``) and not
        after ``now`` (empty outside CHECK; :func:`place_safe.placement.rules.post_stop_stamps`)."""
        return rules.post_stop_stamps(plane, now, None if self._check is None else self._check.t_stop, self.config)

    # -- the tick --------------------------------------------------------------------------------
    def step(self, state: RobotState, plane: FusedPlane | None, note: str | None = None,
             footprint: Any = None) -> Command:
        """One control tick: the command for the robot. ``note`` says why the last frame gave no plane
        (it is quoted in refusal reasons); ``footprint`` is the surface map's
        :class:`~place_safe.fusion.surface_map.FootprintVerdict` for the landing footprint (None: nothing
        known about it). Never raises."""
        if self.finished:
            return Command.hold()
        self._footprint = footprint
        try:
            return self._step(state, plane, note)
        except Exception as exc:  # never raise into the control loop: stop, hold the cup, say why
            now = self._last_now if self._last_now is not None else math.nan
            return self._abort(now, f"internal error: {type(exc).__name__}: {exc}".splitlines()[0])

    def _step(self, state: RobotState, plane: FusedPlane | None, note: str | None) -> Command:
        self.ticks += 1
        self._phase_ticks += 1
        now = number(getattr(state, "time", None))
        if now is None:
            return self._abort(self._last_now if self._last_now is not None else math.nan,
                               "robot time is not a finite number")
        if self._last_now is not None:
            if now < self._last_now - CLOCK_BACK_TOLERANCE:
                return self._abort(now, f"robot clock ran backwards by {self._last_now - now:.3f} s")
            self._stall = self._stall + 1 if now <= self._last_now else 0
            if self._stall >= CLOCK_STALL_TICKS:
                return self._abort(now, f"robot clock frozen for {self._stall} control ticks")
        self._last_now = now
        if math.isnan(self._t_start):
            self._t_start, self._t_phase = now, now
        bad = state.problem() if isinstance(state, RobotState) else "robot state is not a RobotState"
        if bad is not None:
            return self._abort(now, bad, faulted=rules.fault_text(getattr(state, "fault", None)) is not None)
        self._account(state, now)
        self._tick_view = (plane, state)
        stamp = number(getattr(plane, "stamp", None)) if plane is not None else None
        if stamp is not None:  # the fused plane's age this tick (the window's largest stays in front)
            age = max(now - stamp, 0.0)
            while self._plane_ages and self._plane_ages[-1][1] <= age:
                self._plane_ages.pop()
            self._plane_ages.append((now, age))
        while self._plane_ages and self._plane_ages[0][0] < now - LATENCY_MEMORY:
            self._plane_ages.popleft()
        self._hint = None
        self._survey_share = 0.0
        self._view_cap = math.inf
        cmd = _HANDLERS[self.phase](self, state, plane, note, now)
        self._budget_bucket = self._bucket(now)
        self._budget_share = self._survey_share if self.phase == Phase.APPROACH and self._suspect is None else 0.0
        return cmd

    # -- phase handlers ------------------------------------------------------------------------------
    def _on_idle(self, state: RobotState, plane: FusedPlane | None, note: str | None, now: float) -> Command:
        cfg = self.config
        self._start_pos = np.asarray(state.base_T_tcp, dtype=float)[:3, 3].copy()
        problem = rules.plane_problem(plane, now, note, cfg, self.period, lambda: self._blind(note))
        if problem is None:
            self._descent_t0, self._descent_ticks = now, 0
            self._go(Phase.APPROACH, now, f"surface seen: tilt {math.degrees(plane.tilt_rad):.1f} deg, "
                                          f"{plane.n} planes")
            return self._on_descent(state, plane, note, now)
        if self._elapsed(now, self._t_start, self.ticks - 1) > cfg.acquire_timeout:
            detail = problem if plane is not None else note
            return self._refuse(now, f"no surface plane within {cfg.acquire_timeout:.1f} s"
                                + (f" ({detail})" if detail else ""))
        if (why := rules.sensor_problem(state.last_frame_time, now, self._t_start, note, cfg)) is not None:
            return self._refuse(now, why)
        return Command.hold()

    def _contact_rule(self, state: RobotState, c: float, now: float) -> Command | None:
        """Contact: arrival when the sensed surface is within :func:`~place_safe.placement.rules.contact_limit`, else an
        obstacle."""
        cfg = self.config
        force = float(state.contact_force)
        if force < cfg.contact_force:
            return None
        if c <= rules.contact_limit(cfg):
            self._check = _Check(now)
            self._go(Phase.CHECK, now, f"contact {force:.1f} N at estimated clearance {rules.number_text(c * 1e3)} mm")
            return Command(CommandKind.STOP, accel=cfg.accel)
        # far above the sensed surface: first a question about the force reading. Stop hard at once (every
        # millimetre pressed on into an obstacle adds force), then confirm while the arm is at rest.
        self._suspect = _Suspect(now, force, c)
        self._last_twist = None
        log.info("t=%.3f s contact %.1f N with the cup bottom %.1f mm above the sensed surface: stopping to confirm",
                 now, force, c * 1e3)
        return Command(CommandKind.STOP, accel=cfg.obstacle_decel)

    def _confirm_contact(self, state: RobotState, c: float, now: float) -> Command | None:
        """A contact far above the sensed surface is an obstacle only if it persists ``obstacle_confirm`` s with
        the arm at rest (a touch that pushes back keeps pushing while the arm stands on it; a glitch of the
        force estimate does not). Returns the command while confirming, or None once it vanished."""
        cfg = self.config
        s = self._suspect
        s.ticks += 1
        force = float(state.contact_force)
        tcp = np.asarray(state.base_T_tcp, dtype=float)[:3, 3].copy()
        moved = math.inf if s.last_tcp is None else float(np.linalg.norm(tcp - s.last_tcp))
        s.last_tcp = tcp
        if moved <= cfg.rest_tolerance * 0.1:
            s.rest_since = now if s.rest_since is None else s.rest_since
        else:
            s.rest_since = None
        if force >= cfg.contact_force:
            s.force = max(s.force, force)
            if s.rest_since is not None and now - s.rest_since >= cfg.obstacle_confirm:
                self._suspect = None
                return self._refuse(now, f"obstacle: contact {force:.1f} N with the cup bottom "
                                         f"{rules.contact_clearance_text(cfg, s.clearance)} mm "
                                         f"above the sensed surface ({rules.contact_limit_text(cfg)}), confirmed "
                                         f"for {now - s.rest_since:.2f} s with the arm at rest (something under the cup, "
                                         "or the tool's cup offset is off)",
                                    decel=cfg.obstacle_decel)
            if self._elapsed(now, s.t0, s.ticks) > cfg.obstacle_confirm + 2.0:  # never at rest: refuse all the same
                self._suspect = None
                return self._refuse(now, f"obstacle: contact {force:.1f} N with the cup bottom "
                                         f"{rules.number_text(s.clearance * 1e3)} mm above the sensed surface and the "
                                         "arm did not come to rest",
                                    decel=cfg.obstacle_decel)
            return Command.hold()
        if s.rest_since is None and self._elapsed(now, s.t0, s.ticks) < cfg.obstacle_confirm:
            return Command.hold()  # let the stop take effect before judging
        self._suspect = None
        self._unconfirmed += 1
        note = (f"t={now:.3f} s: contact {s.force:.1f} N {rules.number_text(s.clearance * 1e3)} mm above the sensed "
                "surface vanished "
                f"within {now - s.t0:.2f} s ({self._unconfirmed} of {cfg.max_unconfirmed} allowed): force reading, "
                "not an obstacle; descending on")
        self.notes.append(note)
        log.info(note)
        if self._unconfirmed > cfg.max_unconfirmed:
            return self._refuse(now, f"the force reading is unreliable: {self._unconfirmed} contacts far above the "
                                     "sensed surface vanished again")
        self._last_twist = None
        return None

    def _on_descent(self, state: RobotState, plane: FusedPlane | None, note: str | None, now: float) -> Command:
        """APPROACH and DESCEND: move down towards the surface, fast while it is far, slow near it."""
        cfg = self.config
        self._descent_ticks += 1
        why = (rules.plane_problem(plane, now, note, cfg, self.period, lambda: self._blind(note))
               or rules.sensor_problem(state.last_frame_time, now, self._t_start, note, cfg))
        if why is not None:
            return self._refuse(now, why)
        if (why := rules.steep_problem(plane, cfg)) is not None:
            return self._refuse(now, why)
        if (why := rules.confidently_tilted(plane, cfg)) is not None:
            return self._refuse(now, why)
        if self._elapsed(now, self._descent_t0, self._descent_ticks) > cfg.descent_timeout:
            return self._refuse(now, f"surface not reached within {cfg.descent_timeout:.1f} s")
        tcp = np.asarray(state.base_T_tcp, dtype=float)[:3, 3]
        travelled = float(np.linalg.norm(tcp - self._start_pos))
        if not (travelled <= cfg.max_travel):
            return self._refuse(now, f"no surface reached within {cfg.max_travel:.2f} m of descent")
        c = self.last_clearance = self._clearance(plane, state)
        self._pending_c = self._pending_clearance(plane, state)
        if not math.isfinite(c):
            return self._refuse(now, "cup clearance above the surface cannot be computed (surface parallel to the "
                                     "tool axis or cup pose invalid)")
        # do not start a long fall towards a floor past an edge: the surface's depth below the start pose (along the
        # cup's axis) is what the descent must cover. Sideways and upward moves (a survey over a footprint seen on a
        # steep reading) do not count: seed 98's random scene 20 climbed about 100 mm towards a 72.5 deg plane through
        # the table and the floor past its edge, and its 100 mm of travel plus the table then 518 mm below refused
        descended = float((tcp - self._start_pos) @ -np.asarray(state.base_T_cup, dtype=float)[:3, 2])
        if descended + c > cfg.max_travel:
            return self._refuse(now, f"no support within reach: the surface seen is {c * 1e3:.0f} mm below the cup, "
                                     f"beyond the {cfg.max_travel:.2f} m descent limit (past an edge, or nothing "
                                     "under the cup)")
        if self._suspect is not None:
            if (cmd := self._confirm_contact(state, c, now)) is not None:
                return cmd
        elif (cmd := self._contact_rule(state, c, now)) is not None:
            return cmd
        if c < -cfg.max_penetration:
            return self._refuse(now, f"cup {rules.number_text(-c * 1e3)} mm below the estimated surface without "
                                     "contact: the surface estimate is wrong")
        if self.phase == Phase.APPROACH and (look := self._look_from_check(state, c, now)) is not None:
            return look
        if (why := rules.footprint_problem(self._footprint, cfg)) is not None:
            look = self._second_look(state, c, now) if self.phase == Phase.APPROACH else None
            if look is not None:
                return look
            # something seen under the footprint while descending: stop hard (obstacle_decel) unless moving
            # sideways (the liquid's lateral acceleration), so an obstacle seen late is not run into
            return self._refuse(now, why + self._look_said(),
                                decel=None if self._sideways else max(cfg.accel, cfg.obstacle_decel))
        side = np.zeros(3)
        # (a look made the way CHECK's is returned above while under way; once over, a doubt left refuses here too)
        if self.phase == Phase.APPROACH and not self._surveyed \
                and (look := self._look_at_doubt(state, c, now)) is not None:
            return look
        if self.phase == Phase.APPROACH:
            cmd = self._survey(state, c, now)
            if isinstance(cmd, Command):
                return cmd
            if cmd is not None:
                side = cmd
        down = -np.asarray(state.base_T_cup, dtype=float)[:3, 2]
        if self.phase == Phase.APPROACH:
            if c > cfg.slow_clearance:
                v = self._descent_speed(c)
                if c <= cfg.near_surface_distance:
                    v = max(cfg.descend_speed, min(v, cfg.near_surface_speed))
                if cfg.footprint_frames and (not self._surveyed or self._doubted()):
                    # the footprint is not certified yet: something may stand on it (clutter, a step), so
                    # keep room to stop above traverse_clearance even learning of it sensor_latency late (or
                    # go no faster than the slow band's speed, at which a touch stays gentle); so do points seen
                    # raised after the survey certified the footprint (CHECK then looks at them again)
                    v = min(v, max(cfg.descend_speed,
                                   stoppable_speed(min(c, self._pending_c) - cfg.traverse_clearance,
                                                   self._latency(), cfg.accel)))
                free = v
                v = min(v, self._view_cap)  # passing the footprint: frames inside the window (_pass_speed)
                if np.any(side):
                    # the speed limit holds for the whole move: the descent gets what the sideways part leaves
                    # of approach_speed (rather than the arm scaling both down)
                    v = min(v, math.sqrt(max(cfg.approach_speed ** 2 - float(side @ side), 0.0)))
                    # moving back over the landing spot: the ground under the way is unseen
                    over = OVER_FOOTPRINT * cfg.footprint_margin  # (closer: over the seen footprint)
                    if self._back > over:
                        # reach traverse_clearance no sooner than the way back comes within `over` (if the
                        # sideways move stalls, the descent slows to a stop above traverse_clearance)
                        t_side = self._lateral_time(self._back, over, float(np.linalg.norm(side)))
                        room = c - cfg.traverse_clearance
                        v = min(v, max(self._axial(room), room / t_side if room > 0 else 0.0, 0.0))
                # budget: the survey's time is what it takes from the descent
                # budget: what the survey takes from the descent is the survey's, the rest the descent's
                self._hint = self._motion_bucket(round(free, 3))
                self._survey_share = min(max(1.0 - v / free, 0.0), 1.0) if free > 0 else 0.0
                return self._speed(np.round(side + round(v, 3) * down, 3), lateral=bool(np.any(side)))
            if np.any(side):  # back over the landing spot before the slow, final part of the descent
                self._hint = "survey"
                return self._speed(side, lateral=True)
            shown, slow = rules.compared_text(c * 1e3, cfg.slow_clearance * 1e3, 1, 0)
            self._go(Phase.DESCEND, now, f"clearance {shown} mm < {slow} mm: slow down")
        if c > cfg.stop_clearance:
            return self._speed(cfg.descend_speed * down)
        self._check = _Check(now)
        self._go(Phase.CHECK, now, f"clearance {rules.number_text(c * 1e3)} mm: stop and check")
        return Command(CommandKind.STOP, accel=cfg.accel)

    def _on_check(self, state: RobotState, plane: FusedPlane | None, note: str | None, now: float) -> Command:
        """Stopped: gather fresh planes, then release, descend again or refuse."""
        cfg = self.config
        blind = lambda: self._blind(note)  # noqa: E731
        late = self._elapsed(now, self._t_phase, self._phase_ticks) > cfg.check_timeout
        plane_why = rules.plane_problem(plane, now, note, cfg, self.period, blind)
        sensor_why = rules.sensor_problem(state.last_frame_time, now, self._t_start, note, cfg)
        # at rest a plane that is only old says no fresh plane came yet (a stalled transfer, a corrupted frame), not
        # that the cup moves blind: wait for one while the sensor answers and the arm stands still, until
        # check_timeout; the check then decides only on a window of planes measured after the gap
        stale = (plane_why is not None and sensor_why is None and not late
                 and rules.plane_problem(plane, now, note, cfg, self.period, blind, check_age=False) is None)
        if (plane_why or sensor_why) is not None and not stale:
            return self._refuse(now, plane_why or sensor_why)
        if (why := self._touch_too_high(state, plane)) is not None:
            return self._refuse(now, why)
        if stale and self._check.gap is None:
            self._check.gap = float(plane.stamp)
        fresh = len(self.post_stop_stamps(plane, now))
        if fresh and (fp_why := self._footprint_doubt()) is not None:
            # remembered for the deciding tick, once the fused plane holds a plane measured at rest (a doubt against
            # the plane fused on the way down that the first plane at rest settles is no doubt); a verdict that says
            # where to look from is kept over one that does not
            if self._check.doubt is None or (not self._can_look_again(self._check.doubt[0])
                                             and self._can_look_again(self._footprint)):
                self._check.doubt = (self._footprint, fp_why)
        if self._check.at_rest is None and now - self._check.t_stop >= cfg.check_settle:
            self._check.at_rest = np.asarray(state.base_T_tcp, dtype=float)[:3, 3].copy()
        if stale:  # hold, unless the arm is seen moving
            return self._not_at_rest(state, now) or Command.hold()
        need = self.check_frames_needed(plane)
        gap = self._check.gap
        if gap is not None and (not plane.stamps or min(plane.stamps) <= gap):
            # planes fused before the gap are still in the window: a surface that moved in it would hide behind them
            if late:
                return self._refuse(now, f"the fused plane still holds planes measured before the sensor's gap at "
                                         f"rest {cfg.check_timeout:.1f} s after stopping")
            return self._not_at_rest(state, now) or Command.hold()
        if fresh < need and not (self._blind(note) and cfg.too_close_hold > 0 and gap is None):
            if late:
                return self._refuse(now, f"only {fresh} of {need} surface planes measured within "
                                         f"{cfg.check_timeout:.1f} s of stopping" + (f" ({note})" if note else ""))
            return self._not_at_rest(state, now) or Command.hold()
        c = self.last_clearance = self._clearance(plane, state)
        if not math.isfinite(c):
            return self._refuse(now, "cup clearance above the surface cannot be computed")
        if (why := rules.level_problem(plane, cfg)) is not None:
            return self._refuse(now, why)
        if (why := rules.planar_problem(plane, cfg)) is not None:
            return self._refuse(now, why)
        if (why := rules.footprint_problem(self._footprint, cfg)) is not None:
            if not self._can_look_again():
                return self._refuse(now, why + self._look_said())
            # the doubt came up only here (the fused plane refined at rest moved a zone's reading over the line):
            # look again from over those points, as the approach would have, then come back down
            return self._go_look_again(state, now, why)
        if cfg.footprint_frames and rules.footprint_seen(self._footprint) < cfg.footprint_frames:
            if self._can_look_again():  # points in doubt (raised or lowered in their latest view): the look may lift it
                return self._go_look_again(state, now, "footprint points in doubt" + _doubt_said(self._footprint))
            return self._refuse(now, f"no support evidence: the surface under the cup's footprint was seen on one "
                                     f"plane in {rules.footprint_seen(self._footprint)} frames "
                                     f"(< {cfg.footprint_frames})" + _doubt_said(self._footprint))
        if self._check.doubt is not None:
            # clean now, but not on every tick of this check: the verdict comes and goes with the plane refined at
            # rest; the look from over the points it named settles it, and after a look it refuses
            verdict, why = self._check.doubt
            why = f"{why} earlier in this check (the footprint's verdict comes and goes)"
            if self._can_look_again(verdict):
                return self._go_look_again(state, now, why, verdict)
            return self._refuse(now, why + self._look_said())
        cup = np.asarray(state.base_T_cup, dtype=float)
        cup_to_surface = math.acos(max(-1.0, min(1.0, float(cup[:3, 2] @ np.asarray(plane.normal_base, float)))))
        if not (cup_to_surface <= cfg.max_tilt):
            axis, allowed = rules.compared_text(math.degrees(cup_to_surface), math.degrees(cfg.max_tilt))
            return self._refuse(now, f"cup axis {axis} deg from the surface normal (> {allowed} deg): it would land on "
                                     "its rim")
        if self._check.at_rest is None:
            self._check.at_rest = np.asarray(state.base_T_tcp, dtype=float)[:3, 3].copy()
        if (cmd := self._not_at_rest(state, now)) is not None:
            return cmd
        post = self.post_stop_stamps(plane, now)
        if (why := rules.still_problem(plane, post, cfg)) is not None:
            return self._refuse(now, why)
        if (why := rules.slope_still_problem(plane, post, cfg) or rules.rest_tilt_problem(plane, post, cfg)) is not None:
            # more planes at rest first (stray planes are then set aside), until the check's deadline (refusing at
            # max_check_frames refused a still table with two junk planes among five: an adversarial search)
            if not self._blind(note) and not late:
                return Command.hold()
            return self._refuse(now, why)
        # the newest plane at rest far off the others, or a plane the gates rejected at rest (a box, a tip beyond the
        # gates: FusedPlane.pending): the next planes tell a stray plane from a surface that changed; until the deadline
        if (why := rules.newest_plane_problem(plane, post, cfg) or rules.pending_problem(plane)) is not None:
            return self._refuse(now, why) if late else Command.hold()
        force = float(state.contact_force)
        contact = force >= cfg.contact_force  # within contact_limit: _touch_too_high refused this tick otherwise
        if c < -cfg.max_penetration or (not contact and c < rules.clearance_floor(plane, post, cfg)):
            return self._refuse(now, f"cup {rules.number_text(-c * 1e3)} mm below the estimated surface"
                                     + ("" if contact else " without contact")
                                     + ": the surface estimate is wrong or the surface moved")
        if contact or c <= cfg.release_clearance:
            self._go(Phase.RELEASE, now, f"level ({math.degrees(plane.tilt_rad):.2f} deg +- "
                                         f"{math.degrees(rules.tilt_sigma(plane)):.2f} deg, spread "
                                         f"{math.degrees(plane.std_angle):.2f} deg / {plane.std_offset * 1e3:.1f} mm), "
                                         f"clearance {rules.number_text(c * 1e3)} mm, contact {force:.1f} N "
                                         + (f"from {fresh} planes measured at rest: release"
                                            if fresh >= need else
                                            f"from the fused plane of the farther frames (sensor too close to "
                                            f"read, {fresh} planes at rest): release"))
            self.gripper_opened = True
            return Command(CommandKind.OPEN_GRIPPER)
        self._checks += 1
        if self._checks >= cfg.max_checks:
            return self._refuse(now, f"still {rules.number_text(c * 1e3)} mm above the surface after {self._checks} "
                                     "checks")
        self._check = None
        shown, release = rules.compared_text(c * 1e3, cfg.release_clearance * 1e3)
        self._go(Phase.DESCEND, now, f"clearance {shown} mm > {release} mm: descend again")
        self._descent_t0, self._descent_ticks = now, 0
        return self._speed(cfg.descend_speed * -np.asarray(state.base_T_cup, dtype=float)[:3, 2])

    def _touch_too_high(self, state: RobotState, plane: FusedPlane) -> str | None:
        """CHECK, every tick: a contact read while the cup stands higher above the sensed surface than
        :func:`~place_safe.placement.rules.contact_limit` (the cup settling onto something after the stop, or pressed
        onto it and let go as the grip gives) is an obstacle, though it may have faded by the tick that decides."""
        cfg = self.config
        force = float(state.contact_force)
        if force < cfg.contact_force:
            return None
        c, limit = self._clearance(plane, state), rules.contact_limit(cfg)
        if not c > limit:
            return None
        return (f"obstacle: contact {force:.1f} N with the cup bottom {rules.contact_clearance_text(cfg, c)} mm above "
                "the sensed surface "
                f"({rules.contact_limit_text(cfg)}) while checking: something under the cup, or the tool's cup offset is "
                "off")

    def _not_at_rest(self, state: RobotState, now: float) -> Command | None:
        """CHECK: the refusal when the TCP moved more than ``rest_tolerance`` from where it was once the stop settled
        (None while it stands, or before that pose is taken)."""
        cfg, at_rest = self.config, self._check.at_rest
        if at_rest is None:
            return None
        moved = float(np.linalg.norm(np.asarray(state.base_T_tcp, dtype=float)[:3, 3] - at_rest))
        if moved <= cfg.rest_tolerance:
            return None
        shown, tolerance = rules.compared_text(moved * 1e3, cfg.rest_tolerance * 1e3)
        return self._refuse(now, f"the arm did not stop: the TCP moved {shown} mm after the stop (> {tolerance} mm)")

    def _on_retreat(self, state: RobotState, plane: FusedPlane | None, note: str | None, now: float) -> Command:
        """RELEASE (after the gripper opened) and REFUSE: wait, then move straight up, then finish."""
        cfg = self.config
        released = self.phase == Phase.RELEASE
        final = Phase.DONE if released else Phase.ABORTED
        elapsed = self._elapsed(now, self._t_phase, self._phase_ticks)
        if elapsed > cfg.retreat_timeout + (cfg.release_settle if released else 0.0):
            what = "released" if released else f"refused ({self.reason})"
            self._go(final, now, f"cup {what}; retreat not finished within {cfg.retreat_timeout:.1f} s, stopped")
            return Command(CommandKind.STOP, accel=cfg.accel)
        if released and elapsed < cfg.release_settle:
            return Command.hold()
        z = float(np.asarray(state.base_T_tcp, dtype=float)[2, 3])
        if self._retreat.z0 is None:
            self._retreat.z0 = z
        if z - self._retreat.z0 >= cfg.retreat_distance:
            what = "released" if released else f"refused ({self.reason})"
            self._go(final, now, f"cup {what}; retreated {cfg.retreat_distance * 1e3:.0f} mm")
            return Command(CommandKind.STOP, accel=cfg.accel)
        return self._speed(cfg.retreat_speed * np.array([0.0, 0.0, 1.0]))


_HANDLERS = {
    Phase.IDLE: PlacementMachine._on_idle,
    Phase.APPROACH: PlacementMachine._on_descent,
    Phase.DESCEND: PlacementMachine._on_descent,
    Phase.CHECK: PlacementMachine._on_check,
    Phase.RELEASE: PlacementMachine._on_retreat,
    Phase.REFUSE: PlacementMachine._on_retreat,
}


__all__ = ["Phase", "FINAL", "PlacementConfig", "PlacementMachine", "RobotState", "Command", "CommandKind",
           "Transition"]
