"""Sensor time to host time: the TMF8820's 32-bit system ticks (0.2 us) mapped onto a host clock.

Each measurement gives one observation: the host time at which its first packet (or line) was seen,
which is never before the measurement completed. ``seen - tick_seconds`` over-estimates the clock
offset by the detection delay, so the smallest value over the last :data:`OFFSET_WINDOW` measurements
is the best estimate (a measurement seen right when it finished fixes it; the window follows drift).
The timestamp of a measurement is its tick time plus that offset. Tick wrap-around (every 859 s) is
unwrapped; ticks going backwards otherwise mean the sensor restarted, and the estimate starts over.
"""

from __future__ import annotations

from collections import deque

from place_safe.drivers.tmf8820.registers import TICK_SECONDS

#: Measurements over which the tick -> host clock offset is the minimum.
OFFSET_WINDOW = 64
_TICK_WRAP = 1 << 32


class TickClock:
    """Maps the sensor's 32-bit system ticks to host time (see module docstring)."""

    def __init__(self, window: int = OFFSET_WINDOW) -> None:
        self._offsets: deque[float] = deque(maxlen=window)
        self._last: int | None = None
        self._wraps = 0

    def reset(self) -> None:
        self._offsets.clear()
        self._last, self._wraps = None, 0

    def stamp(self, ticks: int, seen_at: float) -> float:
        if self._last is not None and ticks < self._last:
            if self._last - ticks > _TICK_WRAP // 2:
                self._wraps += 1
            else:  # ticks went back: the device restarted its clock
                self.reset()
        self._last = ticks
        seconds = (ticks + self._wraps * _TICK_WRAP) * TICK_SECONDS
        self._offsets.append(seen_at - seconds)
        return seconds + min(self._offsets)


__all__ = ["TickClock", "OFFSET_WINDOW"]
