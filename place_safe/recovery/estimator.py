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


def checked(est: PlaneEstimate) -> PlaneEstimate:
    """``est`` unless its plane is not finite or lies behind the sensor (then no plane, with the reason)."""
    p = est.plane
    if p is not None and not (np.all(np.isfinite(p.normal)) and np.isfinite(p.offset) and p.offset > 0):
        return PlaneEstimate(None, reason=f"recovered plane is not in front of the sensor (offset {p.offset:.4g} m)",
                             seconds=est.seconds)
    if est.albedo is not None and not np.isfinite(est.albedo):
        est.albedo = None
    return est


class Estimator(ABC):
    """Base class: subclasses implement :meth:`_estimate`; :meth:`estimate` adds checks and timing."""

    #: CLI name of the method (``peak``, ``diff``, ...).
    name: str = "base"
    #: Whether the method needs the histograms (False: only the on-sensor distances).
    needs_histograms: bool = True

    def estimate(self, frame: Frame) -> PlaneEstimate:
        """Recover the plane of one frame; never raises for bad data, never returns a NaN plane or a
        plane behind the sensor (``offset <= 0``): such frames get ``plane=None`` and a reason."""
        t0 = time.perf_counter()
        try:
            if not isinstance(frame, Frame):
                raise FrameError(f"expected a Frame, got {type(frame).__name__}")
            if self.needs_histograms:
                frame.validate()
            est = checked(self._estimate(frame))
        except (FrameError, NoPlaneError) as exc:
            est = PlaneEstimate(None, reason=str(exc))
        except (ArithmeticError, np.linalg.LinAlgError) as exc:
            est = PlaneEstimate(None, reason=f"numerical failure: {exc}")
        except (ValueError, TypeError, IndexError, RuntimeError) as exc:  # data no check above foresaw
            est = PlaneEstimate(None, reason=f"unusable data: {type(exc).__name__}: {str(exc)[:200]}")
        est.seconds = time.perf_counter() - t0
        return est

    def estimate_many(self, frames: list[Frame]) -> list[PlaneEstimate]:
        """Recover many frames (subclasses may batch)."""
        return [self.estimate(f) for f in frames]

    @abstractmethod
    def _estimate(self, frame: Frame) -> PlaneEstimate:
        """Recover one validated frame; may raise FrameError or NoPlaneError."""
