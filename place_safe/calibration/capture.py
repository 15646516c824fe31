"""Robot-driven capture: a sweep of sensor poses above a plane, with the plane as ground truth.

Concept: :func:`capture_sweep` drives any :class:`~place_safe.robot.interface.Robot` (the UR5 over ur_rtde,
MuJoCo's SimRobot, the fake stand-in) through a :class:`SweepPlan` -- distances x incidence x azimuth,
the design of Sifferman et al.'s data set -- reads frames from a
:class:`~place_safe.io.source.FrameSource` at each pose and appends them to a JSON-Lines frame file in
the shared format (docs/interfaces.md): histograms, on-sensor distances, ground-truth ``plane`` in the
sensor frame, ``pose`` (base_T_flange), ``joint_angles`` and a ``meta`` record. ``place-safe calibrate``,
``evaluate`` and ``calibrate-mount`` read it.

The ground-truth plane comes from :func:`touch_plane` (the TCP touches the surface at three or more points
with a slow guarded descent: speedL plus a threshold on the zeroed contact force, which works on a CB3
where ``moveUntilContact`` does not) or from a known table height (:func:`level_plane`). The plane in the
sensor frame uses the tool frames the caller believes (``ToolFrames``: nominal or calibrated mount), never
the simulator's truth; ``calibrate-mount`` then fits the mount from the same file.

On a robot in dry-run mode (``robot.dry_run``) every pose is checked and its planned move printed by the
robot, and nothing is read or written. A capture is resumable: poses whose index is already in the output file are skipped. Poses the robot
refuses (outside its limits, unreachable), and poses that would bring the TCP, the flange or the sensor within
:attr:`SweepPlan.min_clearance` of the plane (:func:`lowest_tool_point`, checked before the arm moves), are skipped
and counted; a latched fault ends the capture (rerun to resume after clearing it).

Conventions: base frame, SI units; a plane is ``(n, d)`` with ``n . x = d``, n pointing up, away from the
surface (towards the sensor). Incidence is the angle between the optical axis and the surface normal,
azimuth the direction (in the base x-y plane) the optical axis tilts towards.
"""

from __future__ import annotations

import json
import math
import sys
import time as _time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, ClassVar, Optional

import numpy as np
from pydantic import Field, model_validator

from place_safe.config import ParamModel, vector

from place_safe.exceptions import CalibrationError, FrameFileError, NoPlaneError, RobotFault, SensorTimeout
from place_safe.geometry import Plane, fit_plane
from place_safe.recovery.estimator import Reference
from place_safe.robot.interface import Robot

#: s between control steps while waiting for frames (the UR CB3's cycle).
STEP_S = 0.008
#: Cycles of contact force averaged before comparing with the threshold: the CB3's estimate from motor
#: currents has several newtons of noise per sample; 5 cycles (40 ms, 0.2 mm at 5 mm/s) keep single
#: noisy samples from reading as contact.
TOUCH_SAMPLES = 5
#: The most values one axis of the sweep grid may have.
MAX_GRID_VALUES = 100
#: m, the standard deviation taken for each touched contact's height: the UR5's stated pose repeatability
#: (+-0.1 mm) read as one standard deviation. The simulated arm's three touches of a level table lie 0.06-0.18 mm
#: low, 0.12 mm apart (docs/results.md, "The calibration's reference").
TOUCH_HEIGHT_STD = 1e-4
#: m/s and m/s^2, the slowest moveL between poses a plan takes (:attr:`SweepPlan.speed`, :attr:`SweepPlan.accel`): the
#: guarded descent's speed of :func:`touch_plane`, the slowest the capture moves, and an acceleration that reaches
#: it in 0.1 s. ``capture --speed 1e-9`` was taken and the first move never ended (a 0.3 m move takes 3e8 s; in
#: simulation the command ran on with no output: round 14).
MIN_SPEED = 0.005
MIN_ACCEL = 0.05
#: m, the least height of the tool (TCP, flange, sensor) above the plane that a capture pose may have
#: (:attr:`SweepPlan.min_clearance`).
MIN_CLEARANCE = 0.005


def repeated_value(values: "list[float]", period: float | None = None, tol: float = 1e-9) -> tuple[int, int] | None:
    """``(i, j)``: the first value ``values[i]`` equal to an earlier ``values[j]`` within ``tol`` (modulo ``period`` where
    given: azimuths a turn apart are one direction), or None. A sweep plan's axes are sets of poses: a repeat captured
    the same poses twice (``capture --distances 80,80``, or ranges that overlap: round 14)."""
    for i, v in enumerate(values):
        for j in range(i):
            gap = abs(v - values[j])
            if period is not None:
                gap = gap % period
                gap = min(gap, period - gap)
            if gap <= tol:
                return i, j
    return None


class SweepPlan(ParamModel):
    """Sensor poses above a plane (SI units, angles in rad); see the module docstring."""

    what: ClassVar[str] = "sweep plan"

    distances: vector(min_length=1, max_length=MAX_GRID_VALUES, ge=0.01, le=5.0) = Field(
        default_factory=lambda: [0.08, 0.12, 0.17, 0.22, 0.27], description="m")
    incidences: vector(min_length=1, max_length=MAX_GRID_VALUES, ge=0.0, le=math.radians(80.0)) = Field(
        default_factory=lambda: [0.0, math.radians(12), math.radians(24)], description="rad")
    azimuths: vector(min_length=1, max_length=MAX_GRID_VALUES, ge=-2 * math.pi, le=2 * math.pi) = Field(
        default_factory=lambda: [math.radians(a) for a in range(0, 360, 60)], description="rad")
    # base x, y the optical axis aims at; None: below the start pose
    centre: Optional[vector(2, ge=-2.0, le=2.0)] = Field(None, description="m")
    frames_per_pose: int = Field(1, ge=1, le=100, description="frames")
    settle_s: float = Field(0.25, ge=0.0, le=60.0, description="s")  # at rest before the frames count
    speed: float = Field(0.1, ge=MIN_SPEED, le=1.0, description="m/s")  # moveL
    accel: float = Field(0.5, ge=MIN_ACCEL, le=10.0, description="m/s^2")
    # subsample the grid evenly to this many poses
    max_poses: Optional[int] = Field(None, ge=1, le=10_000, description="poses")
    # s of robot time to wait for the frames of one pose
    frame_timeout_s: float = Field(2.0, gt=0.0, le=60.0, description="s")
    # m the TCP (the gripper's fingertips: capture holds no object) must stay above the plane; a pose that would bring
    # it closer is refused before the arm moves (a gripper whose tips reach 30 mm past the sensor cannot take the
    # sensor within 35 mm of a table; in simulation the first poses of a sweep from 1 cm met the table at 70 N)
    min_clearance: float = Field(MIN_CLEARANCE, ge=0.0, le=0.1, description="m")

    @model_validator(mode="after")
    def _distinct(self) -> "SweepPlan":
        for name, unit, scale, period in (("distances", "m", 1.0, None), ("incidences", "deg", 180 / math.pi, None),
                                          ("azimuths", "deg", 180 / math.pi, 2 * math.pi)):
            values = getattr(self, name)
            if (ij := repeated_value(values, period)) is not None:
                i, j = ij
                raise ValueError(f"{name}: {values[i] * scale:g} {unit} is given twice (as item {j}: "
                                 f"{values[j] * scale:g} {unit}): each value is a row of poses, captured once")
        return self

    def grid(self) -> list[tuple[float, float, float]]:
        """(distance, incidence, azimuth) of every pose; incidence 0 once per distance."""
        out = []
        for d in self.distances:
            for inc in self.incidences:
                for az in ([0.0] if inc == 0 else self.azimuths):
                    out.append((float(d), float(inc), float(az)))
        if self.max_poses is not None and self.max_poses < len(out):
            keep = np.unique(np.round(np.linspace(0, len(out) - 1, self.max_poses)).astype(int))
            out = [out[i] for i in keep]
        return out



def level_plane(height: float) -> tuple[np.ndarray, float]:
    """A level table whose top is at base-frame z = ``height`` (m)."""
    return np.array([0.0, 0.0, 1.0]), float(height)


def sensor_target(plane: tuple[np.ndarray, float], centre: np.ndarray, distance: float, incidence: float,
                  azimuth: float, x_hint: np.ndarray) -> np.ndarray:
    """base_T_sensor looking at ``centre`` (a point of the plane) from perpendicular ``distance``, its optical
    axis ``incidence`` from the normal, tilted towards ``azimuth``; sensor x as close to ``x_hint`` as allowed."""
    from scipy.spatial.transform import Rotation

    n = np.asarray(plane[0], dtype=float)
    n = n / np.linalg.norm(n)
    e1 = np.cross(n, [0.0, 1.0, 0.0]) if abs(n[1]) < 0.9 else np.cross(n, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n, e1)
    # e1/e2 span the plane; use base x/y directions projected where possible
    bx = np.array([1.0, 0.0, 0.0]) - n[0] * n
    if np.linalg.norm(bx) > 1e-6:
        e1 = bx / np.linalg.norm(bx)
        e2 = np.cross(n, e1)
    tilt_dir = math.cos(azimuth) * e1 + math.sin(azimuth) * e2
    z = -n * math.cos(incidence) + tilt_dir * math.sin(incidence)  # optical axis, towards the plane
    z /= np.linalg.norm(z)
    x = np.asarray(x_hint, dtype=float) - float(np.dot(x_hint, z)) * z
    if np.linalg.norm(x) < 1e-6:
        x = e1 - float(np.dot(e1, z)) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = np.asarray(centre, dtype=float) - z * (distance / math.cos(incidence))
    assert abs(np.linalg.det(T[:3, :3]) - 1) < 1e-9 and Rotation.from_matrix(T[:3, :3]) is not None
    return T


def plane_in_sensor(plane: tuple[np.ndarray, float], base_T_sensor: np.ndarray) -> Plane:
    """A base-frame plane ``(n, d)`` in the sensor frame (normal away from the sensor, offset > 0)."""
    n, d = np.asarray(plane[0], dtype=float), float(plane[1])
    R, p = base_T_sensor[:3, :3], base_T_sensor[:3, 3]
    ns = R.T @ n
    ds = d - float(n @ p)
    # the sensor is on the +n side (ds < 0): flip to the sensor convention (n_z > 0, d > 0)
    return Plane(-ns, -ds) if ds < 0 else Plane(ns, ds)


def touch_plane(robot: Robot, points_xy: Any, start_height: float, *, speed: float = 0.005,
                force_threshold: float = 12.0, max_depth: float = 0.15, retract: float = 0.03,
                accel: float = 0.2) -> tuple[np.ndarray, float, np.ndarray]:
    """Touch the surface with the TCP at each ``points_xy`` (base frame, >= 3) by a guarded descent and fit
    the plane through the contact points. Returns ``(n, d, points)`` (n up).

    Each descent: moveL to (x, y, ``start_height``) with the current orientation, zero the force reading
    (robots that have ``zero_force``), speedL down at ``speed`` until ``contact_force()`` exceeds
    ``force_threshold`` N averaged over :data:`TOUCH_SAMPLES` cycles -- or, for a robot with a contact detector
    (``zero_force``), its averaged output alone (CB3: the controller's force estimate has several N of noise;
    stay well above it and well below the protective stop), stop at once -- with a contact detector, rise
    slowly until it lets go (:func:`_release_point`) -- record the TCP position, retract by
    ``retract`` m. No contact within ``max_depth`` m is an error (RobotFault)."""
    pts = np.asarray(points_xy, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
        raise ValueError("touch_plane needs at least 3 points (x, y) in the base frame")
    contacts = []
    for x, y in pts:
        T = robot.tcp_pose()
        T[:3, 3] = [x, y, start_height]
        robot.move_linear(T, speed=0.05, accel=accel)
        zero = getattr(robot, "zero_force", None)
        if zero is not None:
            zero()
        base = robot.contact_force() if zero is None else 0.0
        robot.speed_linear([0.0, 0.0, -abs(speed), 0.0, 0.0, 0.0], accel=accel)
        z_start = robot.tcp_pose()[2, 3]
        t_end = robot.time() + max_depth / abs(speed) * 1.5 + 2.0
        recent: list[float] = []
        while True:
            robot.step(STEP_S)
            if robot.time() > t_end:
                robot.stop(decel=2.0)
                raise RobotFault(f"guarded descent at ({x:.3f}, {y:.3f}) m did not reach contact or "
                                 f"{max_depth * 1000:.0f} mm of travel in time (arm not moving?)")
            recent = (recent + [robot.contact_force() - base])[-TOUCH_SAMPLES:]
            # a robot with zero_force reports its contact detector's output, averaged already: no second average
            hit = recent[-1] > force_threshold if zero is not None else \
                len(recent) == TOUCH_SAMPLES and float(np.mean(recent)) > force_threshold
            if hit:
                robot.stop(decel=2.0)
                break
            if z_start - robot.tcp_pose()[2, 3] > max_depth:
                robot.stop(decel=2.0)
                raise RobotFault(f"no contact within {max_depth * 1000:.0f} mm below ({x:.3f}, {y:.3f}) m")
        if zero is not None:  # a contact detector: back off slowly until it lets go, nearer the first touch
            contacts.append(_release_point(robot, speed, accel))
        else:
            contacts.append(robot.tcp_pose()[:3, 3].copy())
        up = robot.tcp_pose()
        up[2, 3] += retract
        robot.move_linear(up, speed=0.02, accel=accel)
    P = np.array(contacts)
    plane, _ = fit_plane(P)
    n = plane.normal if plane.normal[2] > 0 else -plane.normal
    return n, float(n @ P.mean(axis=0)), P


def touched_reference(points: Any, height_std: float = TOUCH_HEIGHT_STD) -> Reference:
    """How far the plane :func:`touch_plane` fits through its contact ``points`` (k, 3) may be off, each contact's
    height along the normal ``height_std`` (m) uncertain, or as scattered as the fit's residual says where that is
    more (four or more points): ``tilt_std``, the normal's standard deviation along its worst direction (three
    touches 8 cm apart at 0.1 mm: 0.12 deg), and ``offset_std``, the offset's at the points' centroid. Raises
    ValueError when the points do not fix a plane (fewer than 3, not finite, on a line)."""
    P = np.asarray(points, dtype=float)
    if P.ndim != 2 or P.shape[1] != 3 or len(P) < 3 or not np.all(np.isfinite(P)):
        raise ValueError(f"the touched plane's uncertainty needs 3 or more finite contact points (x, y, z); got "
                         f"an array of shape {P.shape}")
    centred = P - P.mean(axis=0)
    try:
        plane, rms = fit_plane(centred)
    except NoPlaneError as exc:
        raise ValueError(f"the touch points do not fix a plane: {exc}") from None
    n = plane.normal if plane.normal[2] > 0 else -plane.normal
    if n[2] < 0.5:
        raise ValueError(f"the touch points do not fix a table: their plane is {math.degrees(math.acos(n[2])):.0f} deg "
                         "from level")
    # the plane's residuals linearised in (n_x, n_y, d), as plane_covariance does for the zones' points
    jac = np.column_stack([centred[:, :2] - centred[:, 2:] * (n[:2] / n[2]), -np.ones(len(P))])
    dof = len(P) - 3
    var = max(height_std ** 2, rms ** 2 * len(P) / dof if dof > 0 else 0.0)
    cov = var * np.linalg.inv(jac.T @ jac)
    tilt, offset = float(math.sqrt(np.linalg.eigvalsh(cov[:2, :2]).max())), float(math.sqrt(cov[2, 2]))
    try:
        return Reference(tilt_std=tilt, offset_std=offset, points=len(P), height_std=float(math.sqrt(var)))
    except CalibrationError:  # beyond what a reference may state (Reference's bounds): say why in the touches' terms
        within = f"only within {min(math.degrees(tilt), 90.0):.2g} deg"
        if var > height_std ** 2:
            raise ValueError(f"the touches disagree by {math.sqrt(var) * 1e3:.2g} mm about one plane, which they fix "
                             f"{within}: check the table and the contacts") from None
        raise ValueError(f"the touch points lie too near a line: they fix the plane {within}; touch farther "
                         "apart") from None


def _release_point(robot: Robot, speed: float, accel: float, max_back: float = 0.005) -> np.ndarray:
    """After a guarded descent stopped on contact: rise at half the descent speed until the robot's contact
    detector lets go of the contact (its averaged force below half its threshold) and return the TCP position
    there -- within a fraction of a millimetre of the first touch, where the stop at the threshold force
    (15 N: about 1 mm into a 20 kN/m contact, varying with the noise) is not."""
    z0 = robot.tcp_pose()[2, 3]
    robot.speed_linear([0.0, 0.0, abs(speed) / 2.0, 0.0, 0.0, 0.0], accel=accel)
    while robot.contact_force() > 0.0 and robot.tcp_pose()[2, 3] - z0 < max_back:
        robot.step(STEP_S)
    p = robot.tcp_pose()[:3, 3].copy()
    robot.stop(decel=2.0)
    return p


def resume_problem(path: "Path | CaptureFile", plan: "SweepPlan") -> str | None:
    """Why the capture in ``path`` (or as :func:`read_capture` read it) cannot be resumed with ``plan`` -- a pose there
    that is not the plan's pose of the same index (another distance, incidence or azimuth, or an index beyond the plan:
    a capture made with other options) -- or None. Resumed with another ``--distances``, a capture counted the poses of
    the first plan as done and never captured the new plan's poses of those indices ("2 already there", session 82)."""
    grid = plan.grid()
    stored_poses = path.poses if isinstance(path, CaptureFile) else read_capture(Path(path)).poses
    for i, stored in sorted(stored_poses.items()):
        if stored is None:
            continue  # (a pose written without its target: nothing to compare)
        if i >= len(grid):
            return f"pose {i} there is beyond this plan's {len(grid)} poses"
        if not all(math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-12) for a, b in zip(stored, grid[i])):
            d, inc, az = stored
            d2, inc2, az2 = grid[i]
            return (f"pose {i} there is at {d * 1000:g} mm, incidence {math.degrees(inc):g} deg, azimuth "
                    f"{math.degrees(az):g} deg; this plan's pose {i} at {d2 * 1000:g} mm, {math.degrees(inc2):g} deg, "
                    f"{math.degrees(az2):g} deg")
    return None


@dataclass(frozen=True)
class CaptureFile:
    """What a capture's output held when :func:`read_capture` read it: the poses already there (index ->
    ``(distance, incidence, azimuth)`` or None), where an interrupted run's unfinished last line
    starts (bytes; None: there is none) and the file's size then (-1: no file). ``capture`` reads its output once and
    passes this along (it read the file four times before capturing: the "is it a capture" check, the resume check in
    the command and again in :func:`capture_sweep`, then the indices with the cut: session 83)."""

    path: Path
    poses: dict
    cut_at: int | None = None
    size: int = -1

    @property
    def done(self) -> set[int]:
        return set(self.poses)

    def cut(self) -> "CaptureFile":
        """Cut the unfinished last line off the file (so frames appended start on a line of their own); the file as it
        is then. A file that changed since it was read (its size) is read again, and that reading is cut."""
        if self.cut_at is None:
            return self
        if _size(self.path) != self.size:  # written to meanwhile: not this reading's offset to cut at
            return read_capture(self.path).cut()
        with open(self.path, "r+b") as fh:
            fh.truncate(self.cut_at)
        return CaptureFile(self.path, self.poses, None, self.cut_at)


def _size(path: Path) -> int:
    try:
        return path.stat().st_size if path.is_file() else -1
    except OSError:
        return -1


def read_capture(path: Path) -> CaptureFile:
    """A capture's output read once, line by line (a capture of many frames need not be held whole): the pose indices
    there from its frames' ``meta.pose_index`` (a whole number >= 0) with their poses, and an unfinished last line after
    captured frames (JSON cut off: an interrupted run), which :meth:`CaptureFile.cut` cuts off. A file that is not a
    capture (any other line that is not a frame with a pose index: a calibration, a JSON list of frames, a note, text)
    raises :class:`FrameFileError` before anything is appended to it. Each index maps to its pose's
    ``(distance, incidence, azimuth)`` from the same meta (m, rad, rad; None where the frame does not say)."""
    path = Path(path)
    done: dict[int, tuple[float, float, float] | None] = {}
    if not path.is_file():
        return CaptureFile(path, done)
    cut_at = None
    with open(path, "rb") as fh:
        end = 0
        for k, line in enumerate(fh, 1):
            start, end = end, end + len(line)
            if not line.strip():
                continue
            try:
                value = json.loads(line)
            except ValueError as exc:  # (JSONDecodeError, bad UTF-8)
                if not line.endswith(b"\n") and done and isinstance(exc, json.JSONDecodeError):
                    cut_at = start  # the last line after frames, unfinished: an interrupted run's; redone
                    continue
                value = None
            index = value.get("meta", {}).get("pose_index") if isinstance(value, dict) and isinstance(
                value.get("meta"), dict) else None
            if not (isinstance(index, int) and not isinstance(index, bool) and index >= 0):
                raise FrameFileError(f"{path} exists and is not a capture to resume (line {k} is not a frame with "
                                     f"meta.pose_index): give another output file, or move this one")
            target = tuple(value["meta"].get(k) for k in ("distance", "incidence", "azimuth"))
            numbers = all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in target)
            done.setdefault(index, target if numbers else None)
    return CaptureFile(path, done, cut_at, end)


@dataclass
class CaptureResult:
    path: str
    poses: int  # planned
    captured: int  # poses captured in this run
    skipped_done: int  # already in the file (resume)
    refused: list[dict]  # poses the robot refused, with the reason
    frames: int  # frames written in this run
    seconds: float  # robot time spent

    def summary(self) -> str:
        return (f"capture {self.path}: {self.captured} poses captured now, {self.skipped_done} already there, "
                f"{len(self.refused)} refused; {self.frames} frames in {self.seconds:.1f} s robot time")


def _read_frames(robot: Robot, source: Any, n: int, t_ready: float, timeout: float) -> list:
    got = []
    deadline = robot.time() + timeout
    while len(got) < n:
        robot.step(STEP_S)
        try:
            f = source.read(0.0)
        except SensorTimeout:
            f = None
        if f is not None and (f.timestamp is None or f.timestamp >= t_ready):
            got.append(f)
        if robot.time() > deadline:
            raise SensorTimeout(f"no frame within {timeout:g} s at this pose")
    return got


def lowest_tool_point(plane: tuple[np.ndarray, float], base_T_tcp: np.ndarray, tool: Any) -> tuple[str, float]:
    """The tool point nearest the plane ``(n, d)`` (unit ``n``, base frame) with the TCP at ``base_T_tcp``, and its
    height above the plane (m): the lowest of the TCP, the flange and the sensor (``tool``'s
    :class:`~place_safe.robot.tool.ToolFrames`). The gripper's body spans them, so a pose whose lowest one keeps its
    clearance keeps the straight segments between them clear too (a height is linear along a segment). A sensor
    mounted facing up, or a tool frame pointing away from the table, puts the flange lowest: checking the TCP alone
    drove the flange into the table (a protective stop)."""
    n, d = np.asarray(plane[0], dtype=float), float(plane[1])
    base_T_flange = base_T_tcp @ np.linalg.inv(tool.flange_T_tcp)
    points = {"TCP": base_T_tcp[:3, 3], "flange": base_T_flange[:3, 3],
              "sensor": (base_T_flange @ tool.flange_T_sensor)[:3, 3]}
    part = min(points, key=lambda k: float(n @ points[k]))
    return part, float(n @ points[part]) - d


def refusal_line(entry: dict) -> str:
    """How a refused pose (an entry of ``CaptureResult.refused``) is listed: ``pose N refused: reason``."""
    return f"pose {entry['pose_index']} refused: {entry['reason']}"


def capture_sweep(robot: Robot, source: Any, plan: SweepPlan, out_path: str | Path, *,
                  plane: tuple[np.ndarray, float], tool: Any, progress: bool = True,
                  log: Callable[[str], None] | None = None,
                  reference: Reference | None = None,
                  on_refused: Callable[[dict], None] | None = None,
                  existing: CaptureFile | None = None) -> CaptureResult:
    """Run the sweep (see module docstring) and append frames to ``out_path`` (JSON Lines).

    ``plane``: the surface in the base frame (from :func:`touch_plane` or :func:`level_plane`). ``tool``:
    the :class:`~place_safe.robot.tool.ToolFrames` believed for the robot (flange_T_tcp, flange_T_sensor).
    ``reference``: how far that plane may be off (:func:`touched_reference`), written with it into each frame's
    ``meta.base_plane.reference``; ``calibrate`` keeps it as the calibration's ``reference`` section. None: not
    stated (a table height given by hand). ``on_refused``: called with each refused pose's entry (as in
    ``CaptureResult.refused``) instead of logging ``pose N refused: reason`` (a caller that lists them with the
    result). ``existing``: ``out_path`` as :func:`read_capture` read it (a caller that checked it already); None: read
    here.
    """
    from tqdm import tqdm

    log = log or (lambda s: print(s, file=sys.stderr, flush=True))

    def refuse(entry: dict) -> None:
        refused.append(entry)
        if on_refused is not None:
            on_refused(entry)
        else:
            log(refusal_line(entry))

    out = Path(out_path)

    def refuse_another_plan(capture: CaptureFile) -> None:
        if (why := resume_problem(capture, plan)) is not None:
            raise FrameFileError(f"{out} is a capture made with another plan ({why}): resume it with the options it "
                                 "was made with, or give another output file")

    capture = existing if existing is not None else read_capture(out)  # read once
    refuse_another_plan(capture)  # before anything moves or is appended
    if not getattr(robot, "dry_run", False):  # (a dry run writes nothing and leaves an unfinished line)
        cut = capture.cut()
        if cut is not capture:  # read again at the cut (written meanwhile)
            refuse_another_plan(cut)
        capture = cut
    done = capture.done
    n = np.asarray(plane[0], dtype=float)
    n = n / np.linalg.norm(n)
    pl = (n, float(plane[1]) / float(np.linalg.norm(plane[0])))
    base_plane: dict[str, Any] = {"normal": pl[0].tolist(), "offset": pl[1]}
    if reference is not None:
        base_plane["reference"] = reference.to_dict()
    tcp_T_sensor = np.linalg.inv(tool.flange_T_tcp) @ tool.flange_T_sensor
    start_sensor = robot.tcp_pose() @ tcp_T_sensor
    if plan.centre is not None:
        c = np.array([plan.centre[0], plan.centre[1], 0.0])
    else:
        c = start_sensor[:3, 3].copy()
    c = c - (float(n @ c) - pl[1]) * n if plan.centre is None else \
        np.array([c[0], c[1], (pl[1] - n[0] * c[0] - n[1] * c[1]) / n[2]])
    grid = plan.grid()
    refused: list[dict] = []
    frames_written = captured = 0
    t0 = robot.time()
    wall0 = _time.perf_counter()
    todo = [(i, g) for i, g in enumerate(grid) if i not in done]
    bar = tqdm(todo, desc="capture", unit="pose", file=sys.stderr, disable=None if progress else True)
    with open(out, "a", encoding="utf-8") as fh:
        for k, (i, (dist, inc, az)) in enumerate(bar):
            base_T_sensor = sensor_target(pl, c, dist, inc, az, start_sensor[:3, 0])
            base_T_tcp = base_T_sensor @ np.linalg.inv(tcp_T_sensor)
            part, clearance = lowest_tool_point(pl, base_T_tcp, tool)
            if clearance < plan.min_clearance:  # the tool would meet the plane: not a pose to move to
                why = (f"the {part} would come {clearance * 1000:.1f} mm from the plane, less than the "
                       f"{plan.min_clearance * 1000:g} mm clearance (at this pose it sits "
                       f"{(dist - clearance) * 1000:.0f} mm nearer the plane than the sensor)")
                refuse({"pose_index": i, "distance": dist, "incidence": inc, "azimuth": az, "reason": why})
                continue
            try:
                robot.move_linear(base_T_tcp, speed=plan.speed, accel=plan.accel)
            except RobotFault as exc:
                if robot.is_faulted():
                    raise RobotFault(f"capture stopped at pose {i} (rerun to resume after clearing): {exc}") from exc
                refuse({"pose_index": i, "distance": dist, "incidence": inc, "azimuth": az, "reason": str(exc)})
                continue
            if getattr(robot, "dry_run", False):  # the plan is printed by the robot; nothing moved, nothing to record
                captured += 1
                continue
            robot.step(plan.settle_s)
            t_ready = robot.time()
            frames = _read_frames(robot, source, plan.frames_per_pose, t_ready, plan.frame_timeout_s)
            q = robot.joint_positions()
            tcp = robot.tcp_pose()
            flange = tcp @ np.linalg.inv(tool.flange_T_tcp)
            sensor = tcp @ tcp_T_sensor
            truth = plane_in_sensor(pl, sensor)
            for j, f in enumerate(frames):
                d = f.to_dict()
                d["plane"] = truth.to_dict()
                d["pose"] = flange.tolist()
                d["joint_angles"] = [float(v) for v in q]
                d["meta"] = {"pose_index": i, "frame": j, "distance": dist, "incidence": inc, "azimuth": az,
                             "time": robot.time(), "base_T_tcp": tcp.tolist(), "base_plane": base_plane}
                if f.truth is not None:  # a simulated source knows the true plane: kept apart, for checks only
                    d["meta"]["source_truth"] = f.truth.to_dict()
                fh.write(json.dumps(d) + "\n")
                frames_written += 1
            fh.flush()
            captured += 1
            if progress and bar.disable:  # no bar (output not a terminal): a line every 10 poses; quiet: none
                el = _time.perf_counter() - wall0
                eta = el / (k + 1) * (len(todo) - k - 1)
                if (k + 1) % 10 == 0 or k + 1 == len(todo):
                    log(f"capture: {k + 1}/{len(todo)} poses, ETA {eta:.0f} s")
    return CaptureResult(str(out), len(grid), captured, len(done), refused, frames_written, robot.time() - t0)


__all__ = ["SweepPlan", "CaptureResult", "CaptureFile", "capture_sweep", "read_capture", "resume_problem",
           "touch_plane", "touched_reference", "level_plane", "sensor_target", "plane_in_sensor", "lowest_tool_point",
           "refusal_line", "TOUCH_HEIGHT_STD"]
