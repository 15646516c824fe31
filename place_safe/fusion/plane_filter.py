"""Plane fusion: per-frame sensor-frame plane estimates -> one robust plane in the robot base frame.

Concept: a :class:`PlaneFilter` takes each frame's :class:`~place_safe.recovery.estimator.PlaneEstimate`
(sensor frame) together with ``base_T_sensor`` at the frame's measurement time, moves the plane into
the base frame and keeps a short window of accepted planes. Its output, :class:`FusedPlane`, is a
robust centre of that window with its spread, so a placement decision rests on several consistent
frames, not on one.

Conventions
-----------
* Base-frame plane ``n . x = offset`` with unit ``n`` pointing to the side the sensor was on (for a
  table under a downward-looking sensor: up). ``height_at(p) = n . p - offset`` is the signed distance
  of ``p`` above the surface (m).
* ``tilt_rad`` is the angle between ``n`` and the base +z axis (the base frame of a floor-mounted UR5
  is level; see :mod:`place_safe.robot.kinematics`).
* Each accepted plane is kept as its normal and its *anchor*: where the sensor's optical axis meets it,
  in base coordinates. Fusing anchors instead of offsets keeps the estimate local: a 1 deg normal
  error changes the offset about the base origin (~0.5 m away) by ~9 mm but moves nothing at the anchor.
* Centre: component-wise median of the window's normals and anchors, refined by one Huber-weighted
  mean (Huber constant :data:`HUBER_K` robust sigmas). Spread: weighted RMS angle of the normals from
  the fused normal (``std_angle``, rad) and RMS distance of the anchors from the fused plane
  (``std_offset``, m), both unweighted: every plane in the window counts in the spread.
* Gates: once the window holds ``min_frames`` planes, a new plane more than ``angle_gate`` (rad) from
  the fused normal or whose anchor is more than ``offset_gate`` (m) off the fused plane is rejected as
  an outlier. ``max_consecutive_rejects`` gate rejections in a row (frames without a plane between
  them do not count, nor break the run: a frame too close to measure says nothing about the surface) mean
  the surface itself changed (or the old window was wrong): the window is cleared and the new plane starts it.
  Until then the rejected planes are listed in ``FusedPlane.pending`` (base-frame normal and offset), each until
  :data:`PENDING_CLEARS` planes have been accepted after it: a surface that rose under the cup may be what they show,
  and the descent brakes for it at once.
* Too close: while the newest frames are too close to read (no plane, reason
  :data:`~place_safe.recovery.too_close.TOO_CLOSE_REASON`: the return overlaps the internal return) the
  window is not aged (``max_age``): the farther frames' planes, in the base frame, are what there is, and
  the machine decides how long it trusts them (``PlacementConfig.too_close_hold``). Such a frame neither
  updates nor vetoes.
* Rejected without touching the window: no plane (``estimate.plane is None``), non-finite values,
  a malformed pose, and a measurement time not later than the newest accepted one (the same frame fed
  twice, or frames out of order, never count as new evidence). Times are seconds on the robot clock;
  planes older than ``max_age`` are dropped. ``FusedPlane.stamps`` lists the measurement times the
  fused plane rests on (distinct by construction).
* Uncertainty: an estimate's ``covariance`` ((n_x, n_y, d) in the sensor frame, see
  :mod:`place_safe.recovery.estimator`) gives the variance of its normal's direction, the largest
  eigenvalue of the (n_x, n_y) block (rad^2; rotating the plane into the base frame does not change it).
  When a plane in the window has one, the Huber weights are multiplied by the inverse variances; a plane without
  a usable one (None, not finite) is weighed as the least certain plane with one and adds nothing to the
  standard error (:func:`_inverse_variances`).
  ``FusedPlane.tilt_std`` (rad) is the standard error of the fused normal's direction: the larger of
  ``sqrt(1 / sum(1 / var_i))`` over the planes with one (NaN without any) and the window's own spread over
  ``sqrt(n)``,
  so model disagreement the covariances do not know about still counts. The tilt error every plane shares
  through the calibration's reference (``reference_tilt_std``, rad; a table touched by the arm to calibrate
  against, :class:`~place_safe.recovery.estimator.Reference`) is added to it once, in quadrature: no number of
  frames averages it away, and no estimate's covariance holds it.
* Memory of the normal: every plane accepted since the window last started (``reset``, or cleared after
  ``max_consecutive_rejects``) is remembered (at most ``memory`` planes, for ``memory_age`` seconds).
  A surface does not change its slope while the window follows it, and the frames from farther up
  measure the slope better than those at a few centimetres (zones farther apart, less pile-up and
  parallax), so once ``memory_frames`` planes are remembered and their inverse-variance weighted
  normal lies within ``memory_gate`` of the window's own, that normal is the fused one (through the window's anchor:
  the offset stays local and recent), and ``tilt_std`` is its standard error with the memory counted as at most
  :data:`MEMORY_INDEPENDENT` independent planes (their errors are correlated). Where the window's normal is known
  to :data:`MEMORY_WIDE_STD` or better (its planes combined, with the reference error: ``window_tilt_std``) and reads
  the surface steeper than the memory, the gate is ``memory_wide_gate`` (:data:`MEMORY_WIDE_GATE`) instead (a memory
  steeper than the window keeps the narrow gate: :meth:`PlaneFilter._memory_gate`), and a memory fused beyond
  ``memory_gate`` is marked (``FusedPlane.memory_wide``): such a window's reading is held to the level bound by itself wherever it is the
  steeper (below; within ``memory_gate`` only where it is steeper by half its error), and close planes of a textured surface read its
  slope 1-2 deg off while stating a few tenths (a checker's light and dark squares share a zone's footprint unevenly,
  which moves its return across the footprint's ranges; random seeds 66 and 102: the window's 4.6 deg against a
  2.9 deg checker table fused, the survey's views of the footprint then read 4-5 mm high against it, and a table that
  was safe was refused). A window whose combined error is larger (with the loop's window of 7 to 9 planes, planes
  stating about 3 deg each or more) keeps the narrow gate: its reading says little of the level, and a remembered
  slope farther off would decide alone. The fused plane carries the window's
  own tilt and standard error too (``window_tilt_rad``, ``window_tilt_std``): where the window reads the surface
  steeper, the level rules hold its reading to the bound as well (:func:`place_safe.placement.rules.window_reading`;
  a table that tilted since the memory began, or a memory mixing a table's two slopes, released the cup on the
  remembered one: an adversarial search). A gate on their combined standard errors instead (3 of them) refused a
  3.9 deg checker table whose close planes read 0.5 deg steep (random seed 57, scene 26). ``FusedPlane.source`` says which: ``"memory"`` or ``"window"``.
  Planes that scatter far beyond what they state (:data:`BIRGE_QUANTILE`) are fused without their inverse-variance
  weights, in the window and in the memory, and every standard error is scaled by their scatter. ``std_angle`` is
  always the window's own spread about its own normal (the planarity check), ``std_offset`` the RMS
  distance of its anchors from the fused plane. Each window plane's normal and its direction's standard error
  (``FusedPlane.normals``, ``normal_stds``) and its anchor's height and offset error (``heights``, ``height_stds``)
  let the machine test that the surface stays still while the cup stands above it
  (:func:`place_safe.placement.rules.still_problem`, :func:`~place_safe.placement.rules.slope_still_problem`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from place_safe.exceptions import NoPlaneError
from place_safe.recovery.estimator import reference_tilt_problem
from place_safe.recovery.too_close import TOO_CLOSE_REASON
from place_safe.geometry import MAX_REACH, Plane, finite_number, transform_problem

#: rad: a window whose normal has at most this standard error (``FusedPlane.window_tilt_std``) and reads the surface
#: steeper than the memory has the memory's normal fused within ``PlaneFilter.memory_wide_gate`` of its own, not
#: ``memory_gate`` (module doc).
MEMORY_WIDE_STD = math.radians(1.0)
#: rad, ``PlaneFilter.memory_wide_gate``'s default (module doc).
MEMORY_WIDE_GATE = math.radians(2.5)
#: Huber constant in robust sigmas (95 % efficiency for Gaussian noise).
HUBER_K = 1.345
#: Median absolute deviation -> Gaussian sigma.
MAD_TO_SIGMA = 1.4826
#: Floor of the robust residual scales (rad, m) so a noise-free window does not give zero weights.
MIN_SCALE_RAD = 1e-4
MIN_SCALE_M = 1e-5
_Z = np.array([0.0, 0.0, 1.0])
#: The memory of the normal counts as at most this many independent planes in its standard error.
MEMORY_INDEPENDENT = 10
#: Planes whose angles about their weighted normal have a chi-square beyond this quantile of its distribution
#: (:func:`_birge`) are fused without their inverse-variance weights (the Huber weights alone): one plane stating 0.04
#: deg, 2 deg off six others stating 0.5-0.7 deg, drew the weighted normal to itself, and a 5.3 deg table passed as
#: 3.4 deg (an adversarial search). The standard error is scaled by the root of the chi-square per degree of freedom.
BIRGE_QUANTILE = 0.999
#: A gate-rejected plane stays pending (``FusedPlane.pending``) until this many planes have been accepted after it: a
#: box seen on only half the frames was pending only until the next table frame, and the descent, braked by three of
#: its frames, sped up again 2.8 mm above it (an adversarial search).
PENDING_CLEARS = 3


@dataclass(frozen=True)
class FusedPlane:
    """The fused surface in the base frame (see module docstring for the conventions)."""

    normal_base: np.ndarray  # (3,) unit, towards the sensor's side
    offset_base: float  # m, n . x = offset
    tilt_rad: float  # angle of the normal from base +z
    std_angle: float  # rad, spread of the window's normals
    std_offset: float  # m, spread of the window's anchors about the plane
    n: int  # planes in the window
    stamp: float = math.nan  # s, measurement time of the newest accepted plane
    count: int = 0  # planes accepted since the last reset
    anchor: np.ndarray | None = None  # (3,) fused anchor point on the plane (base frame)
    stamps: tuple[float, ...] = ()  # s, measurement times of the planes in the window (increasing)
    tilt_std: float = math.nan  # rad, standard error of the fused normal's direction (see module doc)
    source: str = "window"  # where the normal comes from: "window" or "memory" (see module doc)
    memory_n: int = 0  # planes remembered since the window last started
    heights: tuple[float, ...] = ()  # m, each window plane's anchor above the fused plane (in stamps' order)
    height_stds: tuple[float, ...] = ()  # m, each one's offset std from its covariance (NaN: none)
    reference_tilt_std: float = 0.0  # rad, the calibration's reference error, in tilt_std (see module doc)
    # the window's own normal's tilt and its standard error (with the reference error), whatever the source: where
    # the memory's normal is fused, the level rules hold the window's reading to the same bound (rules.level_problem)
    window_tilt_rad: float = math.nan
    window_tilt_std: float = math.nan
    # each window plane's unit normal (base frame) and its direction's standard error (rad; NaN: none stated), in
    # stamps' order: whether the surface keeps its slope while the cup stands still (rules.slope_still_problem,
    # rules.rest_tilt_problem, rules.newest_plane_problem)
    normals: tuple[tuple[float, float, float], ...] = ()
    normal_stds: tuple[float, ...] = ()
    # gate-rejected planes not yet outweighed by PENDING_CLEARS accepted ones (base frame, (normal, offset) each): a
    # surface closer than the fused one may be what they show, and the descent brakes for it at once
    # (PlacementMachine._descent_speed)
    pending: tuple[tuple[tuple[float, float, float], float], ...] = ()
    # rad, the largest slope ambiguity of a window plane (PlaneFilter.update): the window's tilt_std holds it, and the
    # early refusal asks whether the surface is steep whichever way those frames read (PlacementMachine._on_descent)
    ambiguity: float = 0.0
    # the memory's normal was fused beyond ``memory_gate`` of the window's, through the wide gate (PlaneFilter): the two
    # readings disagree, and the level rules hold a steeper window to the bound whatever its error
    # (rules.window_reading)
    memory_wide: bool = False

    def height_at(self, point: Any) -> float:
        """Signed distance (m) of ``point`` (base frame) above the plane (negative: below / behind it)."""
        p = np.asarray(point, dtype=float).reshape(3)
        return float(self.normal_base @ p - self.offset_base)

    def age(self, now: float) -> float:
        """Seconds since the newest accepted plane was measured."""
        return float(now - self.stamp)

    def distance_along(self, point: Any, direction: Any, radius: float = 0.0, axis: Any = None) -> float:
        """Distance (m) to travel from ``point`` along ``direction`` until touching the plane.

        With ``radius > 0`` the moving object is a disc of that radius centred on ``point`` with unit
        normal ``axis`` (e.g. a cup bottom): the distance is the one at which its lowest rim point
        touches. Negative when already through the plane; ``inf`` when ``direction`` does not approach it.
        """
        return clearance_along(self.normal_base, self.offset_base, point, direction, radius, axis)

    def to_dict(self) -> dict:
        return {"normal_base": [float(v) for v in self.normal_base], "offset_base": float(self.offset_base),
                "tilt_deg": math.degrees(self.tilt_rad), "std_angle_deg": math.degrees(self.std_angle),
                "std_offset_m": float(self.std_offset), "n": int(self.n), "stamp": float(self.stamp),
                "count": int(self.count)}


def clearance_along(normal: Any, offset: float, point: Any, direction: Any, radius: float = 0.0,
                    axis: Any = None) -> float:
    """Travel (m) from ``point`` along ``direction`` to the plane ``normal . x = offset`` (see
    :meth:`FusedPlane.distance_along`); the rim term needs ``axis`` when ``radius > 0``."""
    n = np.asarray(normal, dtype=float).reshape(3)
    p = np.asarray(point, dtype=float).reshape(3)
    u = np.asarray(direction, dtype=float).reshape(3)
    nu = np.linalg.norm(u)
    if not (np.all(np.isfinite(n)) and np.all(np.isfinite(p)) and np.all(np.isfinite(u)) and nu > 0
            and math.isfinite(offset)):
        raise ValueError("clearance_along needs finite normal, offset, point and a non-zero direction")
    u = u / nu
    height = float(n @ p - offset)
    if radius > 0:
        if axis is None:
            raise ValueError("clearance_along: a disc radius needs the disc axis")
        a = np.asarray(axis, dtype=float).reshape(3)
        a = a / np.linalg.norm(a)
        height -= radius * float(np.linalg.norm(n - (n @ a) * a))  # lowest rim point
    approach = -float(n @ u)  # rate at which height falls per metre travelled
    if approach <= 1e-9:
        return math.inf if height > 0 else -math.inf
    return height / approach


def plane_to_base(plane: Plane, base_T_sensor: Any) -> tuple[np.ndarray, float, np.ndarray]:
    """Sensor-frame plane -> (unit normal towards the sensor, offset, anchor) in the base frame.

    The anchor is where the optical axis meets the plane. Raises ValueError for a non-finite or
    non-rigid pose.
    """
    # a reflection flips the normal, a pose beyond any arm's reach is not the sensor's: neither is a pose
    if (why := transform_problem(base_T_sensor, 1e-6, reach=MAX_REACH)) is not None:
        raise ValueError(f"base_T_sensor {why}")
    T = np.asarray(base_T_sensor, dtype=float)
    R, t = T[:3, :3], T[:3, 3]
    n = -(R @ plane.normal)  # the sensor-frame normal points away from the sensor; flip towards it
    anchor = t + R @ np.array([0.0, 0.0, plane.z0])
    return n, float(n @ anchor), anchor


class PlaneFilter:
    """Robust running estimate of a surface from per-frame plane estimates (see module docstring).

    Parameters
    ----------
    window: planes kept (the newest ``window`` accepted ones).
    angle_gate: rad, outlier gate on the normal (default 5 deg).
    offset_gate: m, outlier gate on the anchor's distance from the fused plane (default 10 mm).
    min_frames: planes needed before :meth:`fused` answers and before the gates apply.
    max_consecutive_rejects: gate rejections in a row after which the window restarts.
    max_age: s; planes measured longer ago than this (relative to the newest time seen) are dropped.
    memory: planes remembered for the normal (0: no memory, the window alone).
    memory_frames: remembered planes needed before the memory's normal is used.
    memory_gate: rad; the memory's normal is used only within this angle of the window's.
    memory_wide_gate: rad; the gate instead where the window's normal is known to :data:`MEMORY_WIDE_STD` and reads
        the surface steeper than the memory (see the module doc), at least ``memory_gate`` (None: the larger of ``memory_gate`` and :data:`MEMORY_WIDE_GATE`).
    memory_age: s; remembered planes older than this (relative to the newest time seen) are forgotten.
    reference_tilt_std: rad; the tilt error every plane shares through the estimator's calibration (its
        reference: :class:`~place_safe.recovery.estimator.Reference`), added once to the fused ``tilt_std``.
    """

    def __init__(self, window: int = 7, angle_gate: float = math.radians(5.0), offset_gate: float = 0.01,
                 min_frames: int = 3, max_consecutive_rejects: int = 5, max_age: float = 1.0,
                 memory: int = 300, memory_frames: int = 15, memory_gate: float = math.radians(1.5),
                 memory_age: float = 30.0, reference_tilt_std: float = 0.0,
                 memory_wide_gate: float | None = None) -> None:
        if window < 1 or not (1 <= min_frames <= window) or max_consecutive_rejects < 1:
            raise ValueError("PlaneFilter needs window >= 1, 1 <= min_frames <= window, max_consecutive_rejects >= 1")
        if memory < 0 or memory_frames < 1:
            raise ValueError("PlaneFilter needs memory >= 0 and memory_frames >= 1")
        wide = max(memory_gate, MEMORY_WIDE_GATE) if memory_wide_gate is None else memory_wide_gate
        for name, v in (("angle_gate", angle_gate), ("offset_gate", offset_gate), ("max_age", max_age),
                        ("memory_gate", memory_gate), ("memory_age", memory_age), ("memory_wide_gate", wide)):
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"PlaneFilter.{name} must be a positive finite number; got {v!r}")
        self.window, self.angle_gate, self.offset_gate = int(window), float(angle_gate), float(offset_gate)
        self.min_frames, self.max_consecutive_rejects = int(min_frames), int(max_consecutive_rejects)
        self.max_age = float(max_age)
        self.memory, self.memory_frames = int(memory), int(memory_frames)
        if wide < memory_gate:
            raise ValueError("PlaneFilter needs memory_wide_gate >= memory_gate")
        self.memory_gate, self.memory_age = float(memory_gate), float(memory_age)
        self.memory_wide_gate = float(wide)
        self.reference_tilt_std = reference_tilt_std
        self.reset()

    @property
    def reference_tilt_std(self) -> float:
        """rad, the calibration's reference error the fused tilt's standard error holds (see the class doc)."""
        return self._reference_tilt_std

    @reference_tilt_std.setter
    def reference_tilt_std(self, value: float) -> None:
        if (why := reference_tilt_problem(value)) is not None:
            raise ValueError(f"PlaneFilter.reference_tilt_std {why}")
        self._reference_tilt_std = float(value)
        self._dirty = True  # a fused plane already made states the old one

    def reset(self) -> None:
        """Forget every plane and counter."""
        self._items: deque[tuple[float, np.ndarray, np.ndarray, float, float, float]] = deque(maxlen=self.window)
        self._memory: deque[tuple[float, np.ndarray, float]] = deque(maxlen=max(self.memory, 1))
        self._cache: FusedPlane | None = None
        # gate-rejected planes ((base-frame normal, offset), ``count`` when rejected) still pending (FusedPlane.pending)
        self._pending: list[tuple[tuple[tuple[float, float, float], float], int]] = []
        self._dirty = True
        self.count = 0  # accepted since reset
        self.rejected = 0  # rejected since reset
        self.consecutive_rejects = 0
        self.last_reject_reason: str | None = None
        # why the window last restarted on a run of gate rejections, until it holds min_frames planes again (None: it
        # did not, or it is full again): a refusal for want of a plane says what happened to the one there was
        self.restarted: str | None = None
        self.too_close = False  # the newest frame was too close to read (its return overlaps the internal return)
        self.last_time = -math.inf
        self.newest_accepted = -math.inf

    # -- input ---------------------------------------------------------------------------------
    def update(self, estimate: Any, base_T_sensor: Any, stamp: float, ambiguity: float = 0.0) -> bool:
        """Offer one frame's estimate (a PlaneEstimate, a Plane or None) measured at ``stamp`` with the
        sensor at ``base_T_sensor``. Returns whether it was accepted; the reason for a rejection is
        in :attr:`last_reject_reason`.

        ``ambiguity`` (rad; 0, negative or not finite: none): the frame's zones read as well as another plane that far
        from the estimate's (:func:`~place_safe.fusion.surface_map.slope_ambiguity`). Such a plane is weighed as
        uncertain by that angle too, stays out of the memory of the normal, and the fused ``tilt_std`` holds the
        largest ambiguity in the window without averaging it away (the frames from one view share it:
        ``FusedPlane.ambiguity``); while it is in the window the angle gate widens by it. A board seen past its far
        edge reads as a ramp through the table's row as well as a level board; a memory made of such frames alone
        outlived them (random board 60 of seed 4: the ramp was remembered after every frame read the board level,
        and the board was refused), and the gate rejected the level frames until the window restarted empty."""
        plane = getattr(estimate, "plane", estimate)
        if plane is None:  # no evidence either way ("too close", no return): not a gate rejection in a row
            why = getattr(estimate, "reason", None) or "no plane"
            run = self.consecutive_rejects
            self._reject(f"no plane: {why}")
            self.consecutive_rejects = run
            self.too_close = isinstance(why, str) and why.startswith(TOO_CLOSE_REASON)
            return False
        if not isinstance(plane, Plane):
            return self._reject(f"not a Plane: {type(plane).__name__}")
        if (seconds := finite_number(stamp)) is None:
            return self._reject(f"bad input: timestamp is not a finite number of seconds ({type(stamp).__name__})")
        stamp = seconds
        try:
            n, _, anchor = plane_to_base(plane, base_T_sensor)
        except (TypeError, ValueError, NoPlaneError) as exc:
            return self._reject(f"bad input: {exc}")
        if not (np.all(np.isfinite(n)) and np.all(np.isfinite(anchor))):
            return self._reject("non-finite plane in the base frame")
        if stamp <= self.newest_accepted:
            return self._reject(f"measured at {stamp:.4f} s, not after the newest accepted plane "
                                f"({self.newest_accepted:.4f} s): duplicate or out of order")
        self.last_time = max(self.last_time, stamp)
        self._expire(self.last_time)
        if len(self._items) >= self.min_frames:
            f = self._fuse()
            ang = _angle(n, f.normal_base)
            off = abs(f.height_at(anchor))
            # a window whose frames read either way (f.ambiguity) may be that far off: a frame that reads the surface
            # as the other reading is no outlier (restarting the window left the descent without a plane)
            gate = self.angle_gate + f.ambiguity
            if not (ang <= gate and off <= self.offset_gate):  # (NaN: not within them)
                self._reject(f"outlier: {math.degrees(ang):.2f} deg / {off * 1e3:.1f} mm from the fused plane "
                             f"(gates {math.degrees(gate):.1f} deg / {self.offset_gate * 1e3:.1f} mm)")
                if self.consecutive_rejects < self.max_consecutive_rejects:
                    self._pending.append((((float(n[0]), float(n[1]), float(n[2])), float(n @ anchor)), self.count))
                    return False
                self._items.clear()  # the surface changed: start again from this plane
                self._memory.clear()
                self._pending.clear()
                self.restarted = (f"the surface estimate restarted after {self.consecutive_rejects} planes in a row lay "
                                  f"off the fused one, the last by {math.degrees(ang):.1f} deg / {off * 1e3:.1f} mm: "
                                  "the surface moved, or the frames do not follow the arm, as a sensor stuck on one "
                                  "measurement's do")
        var = _direction_variance(estimate)
        amb = finite_number(ambiguity)
        amb = amb if amb is not None and amb > 0 else 0.0
        if amb > 0:
            var = (var if math.isfinite(var) else 0.0) + amb ** 2
        self._items.append((stamp, n, anchor, var, _offset_std(estimate), amb))
        if self.memory > 0 and amb == 0:
            self._memory.append((stamp, n, var))
        self.newest_accepted = stamp
        self._dirty = True
        self.count += 1
        if len(self._items) >= self.min_frames:
            self.restarted = None
        # a rejected plane is outweighed once PENDING_CLEARS planes have been accepted after it
        self._pending = [p for p in self._pending if self.count - p[1] < PENDING_CLEARS]
        self.consecutive_rejects = 0
        self.too_close = False
        return True

    def _reject(self, reason: str) -> bool:
        self.rejected += 1
        self.consecutive_rejects += 1
        self.last_reject_reason = reason
        return False

    def _expire(self, now: float) -> None:
        if self.too_close:  # the sensor is too close to read: the planes of the farther frames are what there is
            return
        while self._items and self._items[0][0] < now - self.max_age:
            self._items.popleft()
            self._dirty = True
        while self._memory and self._memory[0][0] < now - self.memory_age:
            self._memory.popleft()
            self._dirty = True

    # -- output --------------------------------------------------------------------------------
    def fused(self, now: float | None = None) -> FusedPlane | None:
        """The fused plane, or None with fewer than ``min_frames`` planes (after dropping those older
        than ``max_age`` before ``now``, if given)."""
        if now is not None and math.isfinite(now):
            self._expire(now)
        if len(self._items) < self.min_frames:
            return None
        fused = self._fuse()
        return replace(fused, pending=tuple(e[0] for e in self._pending)) if self._pending else fused

    def _fuse(self) -> FusedPlane:
        if not self._dirty and self._cache is not None:
            return self._cache
        stamps = np.array([it[0] for it in self._items])
        N = np.array([it[1] for it in self._items])
        A = np.array([it[2] for it in self._items])
        n0 = np.median(N, axis=0)
        # normals far apart can have a median of nearly zero length (e_x, e_y, e_z): centre on the newest one then
        n0 = _unit(n0) if np.linalg.norm(n0) > 0.5 else N[-1]
        a0 = np.median(A, axis=0)
        # one Huber reweighting on the angular and along-normal residuals, each in robust sigmas
        ang = np.arccos(np.clip(N @ n0, -1.0, 1.0))
        off = (A - a0) @ n0
        s_ang = max(MAD_TO_SIGMA * np.median(ang), MIN_SCALE_RAD)
        s_off = max(MAD_TO_SIGMA * np.median(np.abs(off - np.median(off))), MIN_SCALE_M)
        r = np.maximum(ang / s_ang, np.abs(off - np.median(off)) / s_off)
        w = np.minimum(1.0, HUBER_K / np.maximum(r, 1e-12))
        var = np.array([it[3] for it in self._items])
        inv, inv_known = _inverse_variances(var)
        weighted = inv is not None

        def centre(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            weights = weights / weights.sum()
            normal = _unit(weights @ N)
            return normal, weights @ A, np.arccos(np.clip(N @ normal, -1.0, 1.0))

        # inverse-variance weights, scaled to mean 1 so the Huber weights keep their meaning
        n, anchor, ang_f = centre(w * inv / inv.mean() if weighted else w)
        birge, beyond = _birge(inv_known, ang_f) if weighted else (1.0, False)
        if beyond:  # the planes scatter far beyond what they state: their weights are not to be trusted
            n, anchor, ang_f = centre(w)
            birge, _ = _birge(inv_known, ang_f)
        # the spread is the plain RMS over every plane in the window: the robust weights pick the centre,
        # but a consistent minority of planes that disagree must show in the planarity check
        spread = float(np.sqrt(np.mean(ang_f**2)))
        tilt_std = spread / math.sqrt(len(self._items))
        if weighted:  # the planes that stated their error (one that did not adds no confidence), scaled by scatter
            tilt_std = max(tilt_std, float(math.sqrt(birge / np.sum(inv_known))))
        source = "window"
        ambiguity = max(it[5] for it in self._items)
        tilt_std = math.hypot(tilt_std, ambiguity)  # one view's frames share it: not averaged away
        window_tilt, window_std = _angle(n, _Z), math.hypot(tilt_std, self.reference_tilt_std)
        remembered = self._remembered()
        apart = _angle(remembered[0], n) if remembered is not None else math.inf
        tilt = window_tilt
        memory_tilt = _angle(remembered[0], _Z) if remembered is not None else math.nan
        if apart <= self._memory_gate(window_std, remembered is not None and window_tilt > memory_tilt):
            n, tilt_std = remembered
            tilt, source = memory_tilt, "memory"
        tilt_std = math.hypot(tilt_std, self.reference_tilt_std)  # shared by every plane: not averaged away
        d = float(n @ anchor)
        res = A @ n - d
        self._cache = FusedPlane(n, d, tilt, spread, float(np.sqrt(np.mean(res**2))),
                                 len(self._items), float(stamps.max()), self.count, anchor,
                                 tuple(float(s) for s in stamps), tilt_std, source, len(self._memory),
                                 tuple(float(h) for h in res), tuple(float(it[4]) for it in self._items),
                                 self.reference_tilt_std, window_tilt, window_std,
                                 tuple((float(v[0]), float(v[1]), float(v[2])) for v in N),
                                 tuple(math.sqrt(float(v)) for v in var), ambiguity=ambiguity,
                                 memory_wide=source == "memory" and apart > self.memory_gate)
        self._dirty = False
        return self._cache

    def _memory_gate(self, window_std: float, steeper: bool) -> float:
        """The angle (rad) within which the memory's normal is fused, for a window whose normal has the standard error
        ``window_std`` (rad; ``FusedPlane.window_tilt_std``: its planes combined, with the reference error) and reads
        the surface ``steeper`` than the memory or not: ``memory_wide_gate`` where it is steeper and its error at most
        :data:`MEMORY_WIDE_STD` (the window's own reading is then precise enough for the level rules to hold it to the
        bound itself, so the memory can only make the level verdict stricter), else ``memory_gate``. A memory steeper
        than a sure window is not let overrule it further: far views of a low box beside the cup had tilted the memory
        1.5-1.9 deg, the window read the table level, and the memory's plane hid the box from the footprint verdict
        (random low box 38 of seed 2: released over the box, refused with the narrow gate)."""
        return self.memory_wide_gate if steeper and window_std <= MEMORY_WIDE_STD else self.memory_gate

    def _remembered(self) -> tuple[np.ndarray, float] | None:
        """The memory's normal and its standard error (rad), or None with too few planes or variances.

        Inverse-variance weighted mean of the remembered normals, refined by one Huber reweighting on
        their angles from it; the standard error counts at most :data:`MEMORY_INDEPENDENT` planes and is
        at least their weighted spread over the square root of that."""
        if self.memory <= 0 or len(self._memory) < self.memory_frames:
            return None
        N = np.array([m[1] for m in self._memory])
        var = np.array([m[2] for m in self._memory])
        inv, inv_known = _inverse_variances(var)
        if inv is None:
            return None
        def centre(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            normal = _unit(weights @ N)
            ang = np.arccos(np.clip(N @ normal, -1.0, 1.0))
            scale = max(MAD_TO_SIGMA * float(np.median(ang)), MIN_SCALE_RAD)
            w = weights * np.minimum(1.0, HUBER_K * scale / np.maximum(ang, 1e-12))
            normal = _unit(w @ N)
            return normal, w, np.arccos(np.clip(N @ normal, -1.0, 1.0))

        n, w, ang = centre(inv)
        birge, beyond = _birge(inv_known, ang)
        if beyond:  # planes scattering far beyond what they state: their weights are not to be trusted
            n, w, ang = centre(np.ones(len(N)))
            birge, _ = _birge(inv_known, ang)
        known = int(np.count_nonzero(inv_known))
        k = min(len(N), MEMORY_INDEPENDENT)
        spread = float(np.sqrt(np.sum(w * ang**2) / np.sum(w)))
        # sqrt(1 / sum(1/var)) with the planes that stated their error counted as at most MEMORY_INDEPENDENT, scaled
        # by their scatter (_birge)
        formal = float(math.sqrt(birge * known / (min(known, MEMORY_INDEPENDENT) * np.sum(inv_known))))
        return n, max(formal, spread / math.sqrt(k))


def _birge(inv_known: np.ndarray, ang: np.ndarray) -> tuple[float, bool]:
    """How far planes scatter beyond what they state: the chi-square of their angles ``ang`` (rad) about the fused
    normal under their inverse variances ``inv_known`` (0: none stated) per degree of freedom (2 per plane, less the
    normal's 2), at least 1 (the standard error is scaled by its root), and whether it lies beyond the
    :data:`BIRGE_QUANTILE` of its distribution (the weights are then dropped)."""
    from scipy.stats import chi2

    known = inv_known > 0
    dof = max(2 * int(known.sum()) - 2, 1)
    total = float(np.sum(inv_known * ang**2))
    return max(1.0, total / dof), total > float(chi2.ppf(BIRGE_QUANTILE, dof))


def _inverse_variances(var: np.ndarray) -> tuple[np.ndarray | None, np.ndarray]:
    """Weights ``1 / var`` of planes with direction variances ``var`` (rad^2, NaN or inf where a plane stated none or
    one that is not finite), and the same with 0 for those planes. A plane without a usable error is weighed as the
    least certain plane that has one and counts nothing in the standard error: one plane without a covariance made
    the whole window unweighted, its standard error the planes' spread alone (which a shared model error does not
    show), and a window 4.7 deg tilted was released at +-0.02 deg where its planes stated 0.5 deg each. (None, zeros)
    when no plane has one."""
    known = np.isfinite(var) & (var > 0)
    if not known.any():
        return None, np.zeros(len(var))
    inv_known = np.where(known, 1.0 / np.where(known, var, 1.0), 0.0)
    return np.where(known, inv_known, inv_known[known].min()), inv_known


def _direction_variance(estimate: Any) -> float:
    """Variance (rad^2) of an estimate's normal direction along its worst axis (from its covariance, see
    :meth:`~place_safe.recovery.estimator.PlaneEstimate.tilt_std`), floored at :data:`MIN_SCALE_RAD`;
    NaN when it has none."""
    tilt_std = getattr(estimate, "tilt_std", None)
    try:
        s = tilt_std() if callable(tilt_std) else None
        s = None if s is None else float(s)
    except Exception:  # an estimate that cannot say states no uncertainty
        return math.nan
    return max(s, MIN_SCALE_RAD) ** 2 if s is not None and math.isfinite(s) else math.nan


def _offset_std(estimate: Any) -> float:
    """Standard deviation (m) of an estimate's offset ``d`` from its covariance (the anchor's error along the
    normal), NaN when it has none or it is not a finite non-negative number."""
    cov = getattr(estimate, "covariance", None)
    try:
        if np.iscomplexobj(cov):
            return math.nan
        v = float(np.asarray(cov, dtype=float)[2, 2])
    except (TypeError, ValueError, IndexError, OverflowError):
        return math.nan
    return math.sqrt(v) if math.isfinite(v) and v >= 0.0 else math.nan


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _angle(a: np.ndarray, b: np.ndarray) -> float:
    """Angle (rad) between unit vectors, accurate near 0."""
    return float(2.0 * math.atan2(np.linalg.norm(a - b), np.linalg.norm(a + b)))


__all__ = ["FusedPlane", "PlaneFilter", "plane_to_base", "clearance_along", "PENDING_CLEARS"]
