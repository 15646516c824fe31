"""The real driver over the register-level emulator, as one :class:`~place_safe.io.source.FrameSource`.

Concept
-------
:class:`EmulatedTMF8820` wires a :class:`~.i2c.TMF8820Source` to a :class:`~.emulator.TMF8820Emulator`
fed by frames (a frame file, a list, any source, or a callable such as the simulated sensor), so every
frame goes through the protocol, the bus and the decoder exactly as on hardware. It is what ``emu:``
URIs open (:mod:`place_safe.sources`).

Clocks (``clock_domain``):

* ``"emulator"`` (default): virtual time; frames come as fast as the CPU allows while their timestamps and
  the reported frame rate follow the emulated bus (used by tests and ``place-safe bench sensor``);
* ``"monotonic"`` (``realtime=True``): the host's clock; the bus takes real time (live commands);
* ``"robot"`` (``clock=`` the simulation's time): the emulator follows the simulation. The host's bus
  transfers and waits run ahead of the simulation on the emulator's bus cursor; a frame is handed out
  only once the simulation has reached the time its last byte crossed the bus, and no new transfer
  starts while the bus is still busy, so frames arrive with the bus latency a real sensor has. The
  content of a measurement is the simulation state when the device presents it (at most one
  measurement cycle after its completion time, which is its timestamp).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from place_safe.drivers.tmf8820.emulator import FaultPlan, TMF8820Emulator
from place_safe.drivers.tmf8820.hexfile import RamPatch
from place_safe.drivers.tmf8820.i2c import TMF8820Source
from place_safe.exceptions import SensorTimeout
from place_safe.io.source import FrameSource
from place_safe.sensor.frame import Frame


class EmulatedTMF8820(FrameSource):
    """The TMF8820 driver reading an emulated sensor fed by ``feed`` (see module docstring).

    feed: frames for the emulator (FrameSource, iterable of Frames, or ``callable(t) -> Frame``).
    bus_hz: emulated bus clock. realtime / clock: see the module docstring. patch: a RAM patch the
    emulator accepts and the driver downloads (None: the ROM application). faults: a
    :class:`~.emulator.FaultPlan`. record: keep every presented measurement (``emulator.presented``).
    int_line: the driver waits on the emulator's INT pin (:class:`~.emulator.EmulatedIntLine`) instead of
    polling INT_STATUS (virtual or real time, not an external clock).
    driver: extra keyword arguments of :class:`~.i2c.TMF8820Source` (period_ms, kilo_iterations, ...).
    emulator: extra keyword arguments of :class:`~.emulator.TMF8820Emulator`.
    """

    def __init__(self, feed: Any, *, bus_hz: float = 400e3, realtime: bool = False,
                 clock: Callable[[], float] | None = None, patch: RamPatch | None = None,
                 faults: FaultPlan | None = None, record: bool = False, start: bool = True,
                 int_line: bool = False, driver: dict | None = None, emulator: dict | None = None) -> None:
        self.emulator = emu = TMF8820Emulator(feed, bus_hz=bus_hz, realtime=realtime and clock is None, clock=clock,
                                              patch=patch, faults=faults, record=record, **(emulator or {}))
        self._external = clock
        if clock is not None:
            host_clock, sleep, domain = emu.now, self._idle, "robot"
        elif realtime:
            import time

            host_clock, sleep, domain = time.monotonic, time.sleep, "monotonic"
        else:
            host_clock, sleep, domain = emu.clock, emu.clock.sleep, "emulator"
        self.clock_domain = domain
        self._held: Frame | None = None
        self._held_until = 0.0
        if int_line and clock is not None:
            raise ValueError("the emulated INT line cannot wait on an external clock")
        self.driver = TMF8820Source(emu, clock=host_clock, sleep=sleep, clock_domain=domain,
                                    **{"start": start, "patch": patch, "int_line": emu.int_line if int_line else None,
                                       **(driver or {})})
        self.rate_hz = self.driver.rate_hz

    def _idle(self, seconds: float) -> None:
        """The host waits (external clock): its time runs ahead on the bus cursor."""
        if seconds > 0:
            self.emulator._bus_t = self.emulator.now() + seconds

    @property
    def stats(self) -> dict[str, Any]:  # type: ignore[override]
        e = self.emulator.stats
        return {**self.driver.stats, "bus_bytes": e["bytes"], "bus_transfers": e["transfers"],
                "bus_seconds": e["bus_seconds"], "measurements": e["measurements"], "skipped": e["skipped"],
                "injected": dict(e["injected"])}

    def info(self) -> dict[str, Any]:
        return {**self.driver.info(), "bus": "emulated", "bus_hz": self.emulator.timing.clock_hz}

    def read(self, timeout: float = 1.0) -> Frame:
        if self._external is not None:
            now = self._external()
            if self._held is not None:
                if now + 1e-12 >= self._held_until:
                    frame, self._held = self._held, None
                    return frame
                raise SensorTimeout("the emulated bus is still carrying the last measurement")
            if self.emulator.bus_time > now + 1e-12:
                raise SensorTimeout("the emulated bus is busy")
        if self._external is not None and (self.driver.measurement_in_progress or not self.driver.streaming):
            # the host runs ahead on the bus cursor: a measurement under way is read out whole (or the sensor
            # brought up again) in one call, and the frame is held until the simulation reaches its bus time
            timeout = max(timeout, 0.25)
        try:
            frame = self.driver.read(timeout)
        except SensorTimeout:
            emu = self.emulator
            if emu.feed_ended and emu._current is None and not emu._queue:
                raise StopIteration from None
            raise
        if self._external is not None and self.emulator.bus_time > self._external() + 1e-12:
            self._held, self._held_until = frame, self.emulator.bus_time
            raise SensorTimeout("the emulated bus is still carrying the measurement")
        return frame

    def close(self) -> None:
        self.driver.close()
        self.emulator.close()


__all__ = ["EmulatedTMF8820"]
