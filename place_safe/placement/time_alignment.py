"""Putting a frame in time on the robot: its stamp on the robot's clock (:class:`ClockMap`) and the robot's pose
when it was measured (:class:`PoseHistory`). The placement loop uses both for every frame: a frame is read
~0.1 s after it was measured (8 mm of travel at approach speed), so it is placed at the pose of its stamp,
not at the pose of its arrival.

Conventions: seconds; poses are base-frame 4x4 homogeneous transforms (see :mod:`place_safe.robot.interface`).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: Poses kept for stamp lookup (2 s at the 125 Hz control rate; frames are ~0.1 s old).
POSE_HISTORY = 250
#: s: how far outside the recorded span a pose may be asked for (half of the 8 ms control period).
POSE_TOLERANCE = 0.004
#: Clock-offset samples kept by :class:`ClockMap`.
CLOCK_SAMPLES = 64


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
        try:
            off = float(robot_time) - float(host_time)
        except (TypeError, ValueError, OverflowError):  # a clock that gave no number says nothing
            return
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
        except (TypeError, ValueError, OverflowError):
            return math.nan
        return s + self.offset


class PoseHistory:
    """Poses recorded at increasing times; :meth:`at` interpolates (linear position, slerp rotation).

    A sample at a time not later than the newest one replaces it (a frozen clock keeps one entry).
    """

    def __init__(self, maxlen: int = POSE_HISTORY, tolerance: float = POSE_TOLERANCE) -> None:
        self._t: deque[float] = deque(maxlen=maxlen)
        self._T: deque[np.ndarray] = deque(maxlen=maxlen)
        self.tolerance = tolerance

    def add(self, t: float, T: Any) -> None:
        try:
            T = np.asarray(T, dtype=float)
            t = float(t)
        except (TypeError, ValueError, OverflowError):
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
        t0, t1 = ts[i - 1], ts[i]
        A, B = self._T[i - 1], self._T[i]
        s = (t - t0) / (t1 - t0)
        T = np.eye(4)
        T[:3, 3] = (1 - s) * A[:3, 3] + s * B[:3, 3]
        T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([A[:3, :3], B[:3, :3]])))([s]).as_matrix()[0]
        return T


__all__ = ["ClockMap", "PoseHistory", "POSE_HISTORY", "POSE_TOLERANCE", "CLOCK_SAMPLES"]
