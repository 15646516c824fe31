"""Frame sources: where frames come from (I2C, serial bridge, file replay, MuJoCo).

A source is the only thing the sensing pipeline knows about hardware or simulation. ``read`` blocks
for at most ``timeout`` seconds and returns the next :class:`~place_safe.sensor.frame.Frame` (with its
``timestamp`` set, seconds on the source's clock, see ``clock_domain``) or raises :class:`~place_safe.exceptions.SensorTimeout`.
A frame that arrived corrupted is still returned; validation happens downstream.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from types import MappingProxyType

from place_safe.exceptions import SensorTimeout
from place_safe.sensor.frame import Frame


class FrameSource(ABC):
    """Base class of every frame source. Use as a context manager to open/close the device."""

    #: Nominal frame rate (Hz) of the source.
    rate_hz: float = 30.0
    #: Clock of ``Frame.timestamp``: ``"monotonic"`` = the host's ``time.monotonic()`` seconds (hardware,
    #: replay); ``"robot"`` = the robot's clock (sources advanced by the simulation in lockstep). Sources
    #: on the robot's clock are polled by the placement loop; the others are read by a thread.
    clock_domain: str = "monotonic"
    #: Counters of what happened (frames, faults by kind, retries); sources that count assign a dict.
    stats: Mapping[str, float] = MappingProxyType({})

    @abstractmethod
    def read(self, timeout: float = 1.0) -> Frame:
        """The next frame; raises SensorTimeout if none arrives within ``timeout`` seconds."""

    def close(self) -> None:
        """Release the device. Idempotent."""

    def __enter__(self) -> "FrameSource":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def frames(self, timeout: float = 1.0) -> Iterator[Frame]:
        """Iterate until the source ends (StopIteration) or times out (SensorTimeout propagates)."""
        while True:
            try:
                yield self.read(timeout)
            except StopIteration:
                return


__all__ = ["FrameSource", "SensorTimeout"]
