"""Test doubles for the placement loop: a kinematic robot over a table and a sensor that reports the true
plane (the loop's plumbing is under test here, not the estimators).

``KinematicRobot`` implements :class:`place_safe.robot.interface.Robot`: the TCP moves at the commanded
speedL velocity (no dynamics), the surface is the plane ``z = surface_z`` of the base frame, and the cup
stops on it with ``contact`` newtons. ``TruthSource`` measures the plane below the sensor from the robot's
pose at the measurement time and delivers the frame ``latency`` seconds later, stamped on the robot clock
(or on a host clock for the threaded path). Its histograms hold one pulse per zone at the bin the built-in
peak mapping gives for the zone's range to the table (what the surface map reads), or none where the zone's
centre ray lands in ``hole`` (a base-frame region without table: an edge), nearer where it lands on something
``raised`` above the table. ``TruthEstimator`` returns the
frame's ``truth`` with a stated covariance.
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np

from place_safe.exceptions import RobotFault, SensorTimeout
from place_safe.geometry import Plane
from place_safe.io.source import FrameSource
from place_safe.evaluation.contact import TRUTH_SIGMA, TruthEstimator  # noqa: F401 (the fakes' estimator)
from place_safe.recovery.points import PeakParams
from place_safe.robot.interface import Robot, RobotLimits
from place_safe.robot.tool import ToolFrames
from place_safe.sensor.frame import Frame


def start_pose(height: float, tool: ToolFrames) -> np.ndarray:
    """base_T_tcp with the cup bottom ``height`` above z = 0, tool axis pointing down."""
    base_T_cup = np.eye(4)
    base_T_cup[:3, 3] = (0.4, 0.1, height)
    return base_T_cup @ np.linalg.inv(tool.tcp_T_cup)


class KinematicRobot(Robot):
    def __init__(self, height: float = 0.15, surface_z: float = 0.0, obstacle_z: float | None = None,
                 contact: float = 20.0) -> None:
        self.limits = RobotLimits()
        self.T = start_pose(height, self.tool)
        self.v = np.zeros(3)
        self.t = 0.0
        self.surface_z = surface_z
        self.obstacle_z = obstacle_z  # an object under the cup, above the surface the sensor sees
        self.contact = contact
        self.opened = False
        self.opened_at: float | None = None
        self._fault: str | None = None
        self.fail_speed = False
        self.connected = False
        self.commands: list[str] = []

    def connect(self) -> None:
        self.connected = True

    def disconnect(self) -> None:
        self.connected = False

    def cup_z(self) -> float:
        return float((self.T @ self.tool.tcp_T_cup)[2, 3])

    def _floor(self) -> float:
        return self.surface_z if self.obstacle_z is None else max(self.surface_z, self.obstacle_z)

    def joint_positions(self) -> np.ndarray:
        return np.zeros(6)

    def tcp_pose(self) -> np.ndarray:
        return self.T.copy()

    def tcp_twist(self) -> np.ndarray:
        return np.r_[self.v, 0.0, 0.0, 0.0]

    def contact_force(self) -> float:
        return self.contact if self.cup_z() <= self._floor() + 1e-9 else 0.0

    def time(self) -> float:
        return self.t

    def move_linear(self, pose: Any, speed: float = 0.05, accel: float = 0.2, asynchronous: bool = False) -> None:
        raise NotImplementedError

    def speed_linear(self, twist: Any, accel: float = 0.5, duration: float | None = None) -> None:
        if self._fault:
            raise RobotFault(self._fault)
        if self.fail_speed:
            raise RobotFault("controller rejected speedL")
        self.commands.append("speed")
        self.v = np.asarray(twist, dtype=float)[:3].copy()

    def stop(self, decel: float = 1.0, asynchronous: bool = False) -> None:
        if self._fault:
            raise RobotFault(self._fault)
        self.commands.append("stop")
        self.v = np.zeros(3)

    def is_moving(self) -> bool:
        return bool(np.any(self.v))

    def step(self, dt: float) -> None:
        self.t += dt
        self.T[:3, 3] += self.v * dt
        floor = self._floor()
        if self.cup_z() < floor:
            self.T[2, 3] += floor - self.cup_z()

    def gripper(self, open: bool) -> None:
        self.commands.append("open" if open else "close")
        if open and not self.opened:
            self.opened_at = self.cup_z()  # m, cup bottom height when the gripper opened
        self.opened = self.opened or open

    def fault(self) -> str | None:
        return self._fault

    def clear_fault(self) -> None:
        self._fault = None


class TruthSource(FrameSource):
    """Frames carrying the true table plane in the sensor frame (see module docstring).

    ``freeze_after``: robot time after which the sensor repeats its last frame (same stamp) forever.
    ``clock``: None stamps on the robot clock (clock_domain "robot"); a callable stamps with it
    (clock_domain "monotonic", host time = ``clock()``).
    """

    def __init__(self, robot: KinematicRobot, rate_hz: float = 30.0, latency: float = 0.05,
                 freeze_after: float | None = None, clock=None, error_after: float | None = None,
                 hole=None, raised=None) -> None:
        self.hole = hole  # callable (x, y) base frame -> True where there is no table
        self.raised = raised  # callable (x, y) base frame -> height (m) of something on the table there
        self.robot = robot
        self.rate_hz = rate_hz
        self.latency = latency
        self.freeze_after = freeze_after
        self.error_after = error_after
        self.clock = clock
        self.clock_domain = "robot" if clock is None else "monotonic"
        self._next = 0.0
        self._pending: deque[tuple[float, Frame]] = deque()
        self._last: Frame | None = None

    def _measure(self, t: float) -> Frame:
        base_T_sensor = self.robot.tcp_pose() @ self.robot.tool.tcp_T_sensor
        R, p = base_T_sensor[:3, :3], base_T_sensor[:3, 3]
        n_base = np.array([0.0, 0.0, 1.0])
        d_base = self.robot.surface_z
        n = -(R.T @ n_base)  # sensor-frame normal pointing away from the sensor
        d = -(d_base - n_base @ p)  # n . x = d in the sensor frame
        stamp = t if self.clock is None else self.clock() - (self.robot.t - t)
        return Frame(self._hists(n, d, base_T_sensor), np.ones(128), timestamp=stamp, truth=Plane(n, d))

    def _hists(self, n: np.ndarray, d: float, base_T_sensor: np.ndarray) -> np.ndarray:
        params = PeakParams.default_peak()
        dirs = params.directions()
        ranges = d / (dirs @ n)
        reading = params.expected_readings(n[None], np.array([d]))[0]
        bins = np.arange(128, dtype=float)
        h = np.full((9, 128), 20.0)
        for z in range(9):
            hit = base_T_sensor[:3, :3] @ (ranges[z] * dirs[z]) + base_T_sensor[:3, 3]
            if self.hole is not None and self.hole(hit[0], hit[1]):
                continue
            at = reading[z]
            top = float(self.raised(hit[0], hit[1])) if self.raised is not None else 0.0
            if top > 0:  # the zone's centre ray meets a box standing on the table: a nearer surface
                at = params.expected_readings(n[None], np.array([d - top]))[0][z]
            h[z] += 5000.0 * np.exp(-0.5 * ((bins - at) / 1.5) ** 2)
        return h

    def read(self, timeout: float = 1.0) -> Frame:
        t = self.robot.t
        if self.error_after is not None and t >= self.error_after:
            raise OSError(121, "Remote I/O error")
        while self._next <= t:
            self._pending.append((self._next + self.latency, self._measure(self._next)))
            self._next += 1.0 / self.rate_hz
        if self.freeze_after is not None and t >= self.freeze_after and self._last is not None:
            return self._last
        ready = None
        while self._pending and self._pending[0][0] <= t:
            ready = self._pending.popleft()[1]
        if ready is None:
            raise SensorTimeout("no frame ready")
        self._last = ready
        return ready


def tilted(robot: KinematicRobot, deg: float) -> None:
    """Tilt the robot's reported pose by ``deg`` about x (the sensor then sees a tilted table)."""
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    Rx = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])
    robot.T[:3, :3] = Rx @ robot.T[:3, :3]
