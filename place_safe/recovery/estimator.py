"""The estimator protocol: a frame in, a plane in the sensor frame (or a reason why not) out.

Every estimator returns a :class:`PlaneEstimate`; none raises on bad frames. A frame from which
no plane can be recovered gives ``plane=None`` and a one-line ``reason``. ``residual`` is the
method's own fit-quality measure (documented per method; smaller is better).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass

import numpy as np

from place_safe.exceptions import FrameError, NoPlaneError
from place_safe.geometry import Plane
from place_safe.sensor.frame import Frame


@dataclass
class PlaneEstimate:
    """Result of one recovery. ``plane`` is None exactly when ``reason`` says why."""

    plane: Plane | None
    albedo: float | None = None
    residual: float | None = None
    reason: str | None = None
    seconds: float = 0.0

    @property
    def ok(self) -> bool:
        return self.plane is not None

    def to_json(self, index: int) -> dict:
        """The ``recover --jsonl`` line of docs/interfaces.md."""
        out: dict = {"index": index}
        if self.plane is not None:
            out["normal"] = [float(v) for v in self.plane.normal]
            out["offset"] = float(self.plane.offset)
        else:
            out["normal"] = None
            out["offset"] = None
        out["albedo"] = None if self.albedo is None or not np.isfinite(self.albedo) else float(self.albedo)
        out["ms"] = round(self.seconds * 1e3, 4)
        if self.residual is not None and np.isfinite(self.residual):
            out["residual"] = float(self.residual)
        if self.reason is not None:
            out["reason"] = self.reason
        return out


class Estimator(ABC):
    """Base class: subclasses implement :meth:`_estimate`; :meth:`estimate` adds checks and timing."""

    #: CLI name of the method (``peak``, ``diff``, ...).
    name: str = "base"
    #: Whether the method needs the histograms (False: only the on-sensor distances).
    needs_histograms: bool = True

    def estimate(self, frame: Frame) -> PlaneEstimate:
        """Recover the plane of one frame; never raises for bad data, never returns a NaN plane."""
        t0 = time.perf_counter()
        try:
            if self.needs_histograms:
                frame.validate()
            est = self._estimate(frame)
        except (FrameError, NoPlaneError) as exc:
            est = PlaneEstimate(None, reason=str(exc))
        except (FloatingPointError, np.linalg.LinAlgError) as exc:
            est = PlaneEstimate(None, reason=f"numerical failure: {exc}")
        est.seconds = time.perf_counter() - t0
        return est

    def estimate_many(self, frames: list[Frame]) -> list[PlaneEstimate]:
        """Recover many frames (subclasses may batch)."""
        return [self.estimate(f) for f in frames]

    @abstractmethod
    def _estimate(self, frame: Frame) -> PlaneEstimate:
        """Recover one validated frame; may raise FrameError or NoPlaneError."""
