"""Placement logic: the state machine that lowers a held cup onto a surface and lets go only when it is safe.

Concept: :class:`PlacementMachine` is pure decision logic (no simulator, no driver). Each control tick it
gets the fused surface (:class:`place_safe.fusion.plane_filter.FusedPlane` or None) and a :class:`RobotState`, and
returns one :class:`Command` for the robot. The caller applies the command (speedL / stopL / open
gripper) and feeds the next state.

Phases::

    IDLE --plane--> APPROACH --near--> DESCEND --at release height or contact--> CHECK
    CHECK --level, planar, close--> RELEASE (open gripper, wait, retreat up) --> DONE
    CHECK --still too high--> DESCEND (at most ``max_checks`` times)
    any active phase --tilted / not planar / no plane / stale plane / sensor timeout / inconsistent
                       / travel limit--> REFUSE (retreat up keeping the cup) --> ABORTED
    any phase before the release --robot fault--> ABORTED (no motion: the robot is stopped, holding)

Safety rule: the gripper opens only from CHECK, on the tick of a decision made from at least
``check_frames`` planes measured after the arm stopped, with a fresh plane, no fault, finite robot
state, tilt within ``max_tilt`` and the cup bottom within ``release_clearance`` of the surface (or in
contact). Every transition is logged with its reason (:attr:`PlacementMachine.log` and the
``place_safe.placement.machine`` logger).

Conventions: SI units (m, m/s, m/s^2, rad, s, N). Poses are base-frame 4x4 matrices (see
:mod:`place_safe.robot.interface`); the cup frame has its origin at the centre of the cup bottom and +z up out of
the cup, so the cup moves "down" along its -z (the tool axis). Twists are (vx, vy, vz, wx, wy, wz).
"""

from __future__ import annotations

import logging
import math
from dataclasses import asdict, dataclass, field, fields
from enum import Enum
from pathlib import Path
from typing import Any

import numpy as np

from place_safe.config import Bound, check_dataclass, dataclass_from_dict, read_json, write_json
from place_safe.exceptions import ConfigError
from place_safe.fusion.plane_filter import FusedPlane

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
class PlacementConfig:
    """Thresholds and speeds of a placement (SI units; the JSON file holds the same numbers)."""

    approach_speed: float = 0.08  # m/s while the surface is far
    descend_speed: float = 0.015  # m/s near the surface
    accel: float = 0.5  # m/s^2 for speed changes and stops
    slow_clearance: float = 0.04  # m: APPROACH -> DESCEND below this cup clearance
    stop_clearance: float = 0.003  # m: DESCEND -> CHECK at or below this clearance
    release_clearance: float = 0.005  # m: release only at or below this clearance (or in contact)
    max_tilt: float = math.radians(5.0)  # rad: steepest surface a cup may be put on
    early_refuse_tilt: float = math.radians(10.0)  # rad: refuse already while approaching above this
    max_std_angle: float = math.radians(2.0)  # rad: spread of the fused normals ("planar and consistent")
    max_std_offset: float = 0.003  # m: spread of the fused anchors about the plane
    check_frames: int = 5  # planes measured after stopping that CHECK needs
    check_timeout: float = 1.5  # s to gather them
    max_checks: int = 3  # CHECK -> DESCEND retries
    plane_timeout: float = 0.3  # s: a fused plane whose newest frame is older is stale
    sensor_timeout: float = 0.5  # s without any frame
    acquire_timeout: float = 1.5  # s in IDLE to get a first plane
    contact_force: float = 5.0  # N: contact with the surface (well under the robot's protective stop)
    max_penetration: float = 0.01  # m: clearance this far below zero without contact = estimate is wrong
    max_travel: float = 0.6  # m: descent limit
    retreat_distance: float = 0.10  # m up after release or refusal
    retreat_speed: float = 0.05  # m/s
    release_settle: float = 0.3  # s between opening the gripper and retreating
    cup_radius: float = 0.035  # m, radius of the cup bottom (rim touches first on a tilted surface)

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise :class:`~place_safe.exceptions.ConfigError` (one line naming the field) unless every value is in
        its range (:data:`PLACEMENT_BOUNDS`) and the thresholds are consistent with each other."""
        check_dataclass(self, PLACEMENT_BOUNDS, "placement config")
        if self.stop_clearance > self.release_clearance:
            raise ConfigError("placement config: stop_clearance must not exceed release_clearance "
                              f"({self.stop_clearance} > {self.release_clearance} m)")
        if self.slow_clearance <= self.release_clearance:
            raise ConfigError("placement config: slow_clearance must exceed release_clearance")
        if self.early_refuse_tilt < self.max_tilt:
            raise ConfigError("placement config: early_refuse_tilt must be >= max_tilt")

    def to_dict(self) -> dict[str, float]:
        return {k: (int(v) if k in ("check_frames", "max_checks") else float(v)) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: Any) -> "PlacementConfig":
        return dataclass_from_dict(cls, d, PLACEMENT_BOUNDS, "placement config")

    def save(self, path: str | Path) -> None:
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path) -> "PlacementConfig":
        return dataclass_from_dict(cls, read_json(path, "placement config", ConfigError), PLACEMENT_BOUNDS,
                                   f"placement config {path}")


#: Range of every placement setting (SI units), checked on construction and when read from a file.
PLACEMENT_BOUNDS: dict[str, Bound] = {
    "approach_speed": Bound(0.0, 1.0, "m/s", lo_open=True),
    "descend_speed": Bound(0.0, 0.5, "m/s", lo_open=True),
    "accel": Bound(0.0, 10.0, "m/s^2", lo_open=True),
    "slow_clearance": Bound(0.0, 1.0, "m", lo_open=True),
    "stop_clearance": Bound(0.0, 0.1, "m"),
    "release_clearance": Bound(0.0, 0.1, "m", lo_open=True),
    "max_tilt": Bound(0.0, math.pi / 4, "rad", lo_open=True),
    "early_refuse_tilt": Bound(0.0, math.pi / 2, "rad", lo_open=True),
    "max_std_angle": Bound(0.0, math.pi / 4, "rad", lo_open=True),
    "max_std_offset": Bound(0.0, 0.1, "m", lo_open=True),
    "check_frames": Bound(1, 1000, "frames"),
    "check_timeout": Bound(0.0, 60.0, "s", lo_open=True),
    "max_checks": Bound(1, 100, "retries"),
    "plane_timeout": Bound(0.0, 10.0, "s", lo_open=True),
    "sensor_timeout": Bound(0.0, 10.0, "s", lo_open=True),
    "acquire_timeout": Bound(0.0, 60.0, "s", lo_open=True),
    "contact_force": Bound(0.0, 200.0, "N", lo_open=True),
    "max_penetration": Bound(0.0, 0.1, "m"),
    "max_travel": Bound(0.0, 2.0, "m", lo_open=True),
    "retreat_distance": Bound(0.0, 1.0, "m", lo_open=True),
    "retreat_speed": Bound(0.0, 1.0, "m/s", lo_open=True),
    "release_settle": Bound(0.0, 10.0, "s"),
    "cup_radius": Bound(0.0, 0.5, "m"),
}


@dataclass
class RobotState:
    """What the machine needs from the robot each tick (base frame, SI units)."""

    time: float  # s, robot clock
    base_T_tcp: np.ndarray  # 4x4
    base_T_cup: np.ndarray  # 4x4, origin at the cup bottom centre, +z up out of the cup
    contact_force: float = 0.0  # N
    fault: str | None = None
    last_frame_time: float | None = None  # s, when the newest sensor frame (accepted or not) arrived

    def problem(self) -> str | None:
        """Why this state cannot be trusted (fault, non-finite values), or None."""
        if self.fault:
            return f"robot fault: {self.fault}"
        for name in ("base_T_tcp", "base_T_cup"):
            T = np.asarray(getattr(self, name), dtype=float)
            if T.shape != (4, 4) or not np.all(np.isfinite(T)):
                return f"robot state {name} is not a finite 4x4 pose"
        if not (math.isfinite(self.time) and math.isfinite(self.contact_force)):
            return "robot time or contact force is not finite"
        return None


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


@dataclass
class PlacementMachine:
    """The placement state machine (see module docstring). Feed :meth:`step` once per control tick."""

    config: PlacementConfig = field(default_factory=PlacementConfig)

    def __post_init__(self) -> None:
        self.reset()

    def reset(self) -> None:
        self.phase = Phase.IDLE
        self.reason = ""
        self.outcome: str | None = None  # "released" / "refused" once final
        self.decision = ""  # why the cup was released or refused (the reason of that transition)
        self.log: list[Transition] = []
        self.gripper_opened = False
        self.last_clearance = math.nan
        self._t_phase = math.nan
        self._t_start = math.nan
        self._start_pos: np.ndarray | None = None
        self._mark: dict[str, Any] = {}
        self._checks = 0
        self._last_twist: tuple[float, ...] | None = None

    @property
    def finished(self) -> bool:
        return self.phase in FINAL

    # -- helpers -------------------------------------------------------------------------------
    def _go(self, target: Phase, t: float, reason: str) -> None:
        tr = Transition(float(t), self.phase, target, reason)
        self.log.append(tr)
        log.info("t=%.3f s %s -> %s: %s", t, self.phase.value, target.value, reason)
        self.phase, self.reason, self._t_phase = target, reason, float(t)
        self._mark = {}
        self._last_twist = None
        if target in (Phase.RELEASE, Phase.REFUSE) or (target == Phase.ABORTED and not self.decision):
            self.decision = reason
        if target == Phase.DONE:
            self.outcome = "released"
        elif target == Phase.ABORTED:
            self.outcome = "refused"

    def _refuse(self, t: float, reason: str) -> Command:
        self._go(Phase.REFUSE, t, reason)
        return Command(CommandKind.STOP, accel=self.config.accel)

    def _speed(self, v: np.ndarray) -> Command:
        """speedL at linear velocity ``v`` (3,) m/s, no rotation."""
        tw = tuple(float(x) for x in v) + (0.0, 0.0, 0.0)
        if tw == self._last_twist:
            return Command.hold()
        self._last_twist = tw
        return Command(CommandKind.SPEED, tw, self.config.accel)

    def _plane_problem(self, plane: FusedPlane | None, now: float, note: str | None) -> str | None:
        cfg = self.config
        if plane is None:
            return "no surface plane" + (f" ({note})" if note else "")
        if not (np.all(np.isfinite(plane.normal_base)) and math.isfinite(plane.offset_base)
                and math.isfinite(plane.tilt_rad)):
            return "fused plane is not finite"
        age = plane.age(now)
        if not (age <= cfg.plane_timeout):
            return (f"surface plane is stale ({age:.2f} s old > {cfg.plane_timeout:.2f} s)"
                    + (f"; last frame: {note}" if note else ""))
        return None

    def _sensor_problem(self, state: RobotState) -> str | None:
        t_last = state.last_frame_time
        ref = self._t_start if t_last is None else t_last
        if state.time - ref > self.config.sensor_timeout:
            return f"sensor timeout: no frame for {state.time - ref:.2f} s (> {self.config.sensor_timeout:.2f} s)"
        return None

    def _clearance(self, plane: FusedPlane, state: RobotState) -> float:
        cup = np.asarray(state.base_T_cup, dtype=float)
        axis = cup[:3, 2]
        return plane.distance_along(cup[:3, 3], -axis, self.config.cup_radius, axis)

    def _planar_problem(self, plane: FusedPlane) -> str | None:
        cfg = self.config
        if plane.std_angle > cfg.max_std_angle or plane.std_offset > cfg.max_std_offset:
            return (f"surface not planar or estimates inconsistent: spread {math.degrees(plane.std_angle):.2f} deg / "
                    f"{plane.std_offset * 1e3:.1f} mm (limits {math.degrees(cfg.max_std_angle):.1f} deg / "
                    f"{cfg.max_std_offset * 1e3:.1f} mm)")
        return None

    # -- the tick ------------------------------------------------------------------------------
    def step(self, state: RobotState, plane: FusedPlane | None, note: str | None = None) -> Command:
        """One control tick: the command for the robot. ``note`` says why the last frame gave no plane
        (it is quoted in refusal reasons)."""
        cfg = self.config
        now = float(state.time) if isinstance(state.time, (int, float)) else math.nan
        if self.finished:
            return Command.hold()
        if math.isnan(self._t_start):
            self._t_start, self._t_phase = now, now
        bad = state.problem()
        if bad is not None:
            if self.phase == Phase.RELEASE and self.gripper_opened:
                self._go(Phase.DONE, now, f"cup released; retreat stopped: {bad}")
            else:
                self._go(Phase.ABORTED, now, f"{bad}; the robot holds the cup where it stopped")
            return Command.hold()
        tcp = np.asarray(state.base_T_tcp, dtype=float)[:3, 3]
        cup = np.asarray(state.base_T_cup, dtype=float)
        down = -cup[:3, 2]
        up = np.array([0.0, 0.0, 1.0])

        if self.phase == Phase.IDLE:
            self._start_pos = tcp.copy()
            if self._plane_problem(plane, now, note) is None:
                self._go(Phase.APPROACH, now, f"surface seen: tilt {math.degrees(plane.tilt_rad):.1f} deg, "
                                              f"{plane.n} planes")
            elif now - self._t_start > cfg.acquire_timeout:
                return self._refuse(now, f"no surface plane within {cfg.acquire_timeout:.1f} s"
                                    + (f" ({note})" if note else ""))
            elif (why := self._sensor_problem(state)) is not None:
                return self._refuse(now, why)
            else:
                return Command.hold()

        if self.phase in (Phase.APPROACH, Phase.DESCEND):
            why = self._plane_problem(plane, now, note) or self._sensor_problem(state)
            if why is not None:
                return self._refuse(now, why)
            if plane.tilt_rad > cfg.early_refuse_tilt:
                return self._refuse(now, f"surface tilted {math.degrees(plane.tilt_rad):.1f} deg "
                                         f"(> {math.degrees(cfg.max_tilt):.1f} deg allowed)")
            travelled = float(np.linalg.norm(tcp - self._start_pos))
            if travelled > cfg.max_travel:
                return self._refuse(now, f"no surface reached within {cfg.max_travel:.2f} m of descent")
            c = self.last_clearance = self._clearance(plane, state)
            if state.contact_force >= cfg.contact_force:
                self._go(Phase.CHECK, now, f"contact {state.contact_force:.1f} N at estimated clearance "
                                           f"{c * 1e3:.1f} mm")
                return Command(CommandKind.STOP, accel=cfg.accel)
            if c < -cfg.max_penetration:
                return self._refuse(now, f"cup {-c * 1e3:.1f} mm below the estimated surface without contact: "
                                         "the surface estimate is wrong")
            if self.phase == Phase.APPROACH:
                if c > cfg.slow_clearance:
                    return self._speed(cfg.approach_speed * down)
                self._go(Phase.DESCEND, now, f"clearance {c * 1e3:.1f} mm < {cfg.slow_clearance * 1e3:.0f} mm: slow down")
            if c > cfg.stop_clearance:
                return self._speed(cfg.descend_speed * down)
            self._go(Phase.CHECK, now, f"clearance {c * 1e3:.1f} mm: stop and check")
            return Command(CommandKind.STOP, accel=cfg.accel)

        if self.phase == Phase.CHECK:
            m = self._mark
            why = self._plane_problem(plane, now, note) or self._sensor_problem(state)
            if why is not None:
                return self._refuse(now, why)
            # count planes measured after the stop command (frames arrive in measurement order)
            if plane.stamp >= self._t_phase:
                m["fresh"] = m.get("fresh", 0) + max(0, plane.count - m.get("seen", plane.count - 1))
            m["seen"] = plane.count
            fresh = m.get("fresh", 0)
            if fresh < cfg.check_frames:
                if now - self._t_phase > cfg.check_timeout:
                    return self._refuse(now, f"only {fresh} of {cfg.check_frames} surface planes within "
                                             f"{cfg.check_timeout:.1f} s of stopping" + (f" ({note})" if note else ""))
                return Command.hold()
            c = self.last_clearance = self._clearance(plane, state)
            if plane.tilt_rad > cfg.max_tilt:
                return self._refuse(now, f"surface tilted {math.degrees(plane.tilt_rad):.1f} deg "
                                         f"(> {math.degrees(cfg.max_tilt):.1f} deg allowed)")
            if (why := self._planar_problem(plane)) is not None:
                return self._refuse(now, why)
            contact = state.contact_force >= cfg.contact_force
            if c < -cfg.max_penetration and not contact:
                return self._refuse(now, f"cup {-c * 1e3:.1f} mm below the estimated surface without contact: "
                                         "the surface estimate is wrong")
            if contact or c <= cfg.release_clearance:
                self._go(Phase.RELEASE, now, f"level ({math.degrees(plane.tilt_rad):.2f} deg, spread "
                                             f"{math.degrees(plane.std_angle):.2f} deg / {plane.std_offset * 1e3:.1f} mm), "
                                             f"clearance {c * 1e3:.1f} mm, contact {state.contact_force:.1f} N "
                                             f"from {plane.n} planes: release")
                self.gripper_opened = True
                return Command(CommandKind.OPEN_GRIPPER)
            self._checks += 1
            if self._checks >= cfg.max_checks:
                return self._refuse(now, f"still {c * 1e3:.1f} mm above the surface after {self._checks} checks")
            self._go(Phase.DESCEND, now, f"clearance {c * 1e3:.1f} mm > {cfg.release_clearance * 1e3:.1f} mm: descend again")
            return self._speed(cfg.descend_speed * down)

        if self.phase in (Phase.RELEASE, Phase.REFUSE):
            m = self._mark
            if now - self._t_phase < (cfg.release_settle if self.phase == Phase.RELEASE else 0.0):
                return Command.hold()
            if "z0" not in m:
                m["z0"] = float(tcp[2])
            if tcp[2] - m["z0"] >= cfg.retreat_distance:
                final = Phase.DONE if self.phase == Phase.RELEASE else Phase.ABORTED
                what = "released" if final == Phase.DONE else f"refused ({self.reason})"
                self._go(final, now, f"cup {what}; retreated {cfg.retreat_distance * 1e3:.0f} mm")
                return Command(CommandKind.STOP, accel=cfg.accel)
            return self._speed(cfg.retreat_speed * up)

        return Command.hold()


__all__ = ["Phase", "FINAL", "PlacementConfig", "PlacementMachine", "RobotState", "Command", "CommandKind",
           "Transition"]
