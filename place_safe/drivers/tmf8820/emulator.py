"""A register-level TMF8820 on an emulated I2C bus: the same subset of ``smbus2.SMBus`` the driver uses.

Concept
-------
:class:`TMF8820Emulator` answers ``i2c_rdwr`` (with ``smbus2.i2c_msg`` messages) and the byte / block
calls as a TMF8820 at one address would (``docs/tmf8820-protocol.md``): power-up through ENABLE, the
bootloader with checksums (set address, write / read RAM, start the RAM patch or the ROM application),
the application registers, command / status, the config and factory-calibration pages, short / long
range, and measurements whose 30 raw-histogram packets and result frame carry frames taken from a feed
(any :class:`~place_safe.io.source.FrameSource`, a list of frames, or a callable ``t -> Frame`` such as
the simulated sensor). The driver in :mod:`.i2c` runs on it unchanged: it is how CI and the simulated
placement go through the real code path (``emu:`` sources, :mod:`place_safe.sources`).

Time
----
Three clocks are supported. *Virtual* (the default, :class:`VirtualClock`): time only moves when the bus
carries bytes or the host sleeps, so a benchmark of minutes runs in seconds and its frame rate is the
one a real bus would give. *Real time* (``realtime=True``): the host's ``time.monotonic``; transfers
sleep for their bus time. *External* (``clock=`` a callable, e.g. the simulation's time): the device
follows that clock; transfers run ahead of it on a bus cursor (:attr:`bus_time`), which the caller uses
to hold data until its transfer would have finished.

Bus timing model: a transfer of ``m`` messages moving ``b`` bytes (each message: its address byte plus
its data bytes) takes ``(9 b + m + 1) / clock_hz`` s (9 clocks a byte, one per START / repeated START,
one for the STOP) plus :attr:`BusTiming.host_overhead_s`. A write takes effect when its last byte has
crossed the bus; a read samples each byte as it crosses it.

Device timing model (assumptions where the protocol notes give no figure, all attributes; the defaults
are the pessimistic ones, so that a driver that works here does not rely on a kind chip):

* A measurement integrates ``kilo_iterations * 1000 / pulse_rate_hz`` s plus ``processing_s`` and
  repeats every ``max(period, that)``; the device measures while the host reads the previous one out.
* Publish latency: after the host clears a packet's interrupt (releases it), the next packet is put in
  the 0x20 window, and its interrupt raised, ``publish_latency_s`` later (default uniform 50-100 us per
  packet; a number for a fixed latency). A read that overlaps that moment returns the old packet's bytes
  up to it and the new packet's after (``stats["racing_reads"]``).
* Overwriting (``overwrite``, default on): when a measurement completes while the host has not read the
  previous one out, the rest of the previous one is lost (``stats["overwritten"]``; the packet in the
  window stays until released) and the new one is published next: a host slower than the period gets
  no whole measurement. Measurements that complete while another is waiting are skipped
  (``stats["skipped"]``). Off: the newest finished measurement is presented when the output is free.
  Feed frames are only taken for presented measurements, and a measurement that never got out whole
  (overwritten, or cut by a stop command) hands its feed frame to the next, so a fed frame list comes
  out in order.
* ``release_on_read`` (default off): the other interrupt-clear order, a chip that takes a packet as
  released once its last byte was read, not when its interrupt is cleared; with a short publish latency
  the host's clear then also clears the next packet's interrupt (a lost interrupt).
* ENABLE: the first read after a change returns the old value (the protocol notes allow it).

Faults on demand (:class:`FaultPlan`): each kind in :data:`FAULT_KINDS` is armed at a transfer index or
at random with a per-transfer probability, and fires at its next applicable moment: ``nak`` / ``eio`` /
``timeout`` (an ``OSError`` with errno 121 / 5 / 110; a timeout first stalls the bus for ``stall_s``),
``short_read`` (a read of 2 or more bytes is cut: with probability ``short_fill``, default 0.5, the rest
reads 0xFF at full length, as an open bus does, else fewer bytes come back), ``reset`` (the device loses
RAM, patch, configuration and measurement; with probability ``reset_keeps_wake``, default 0.5, the
wake-up bit survives and the chip restarts into its bootloader by itself, APPID 0x80, else it drops to
standby), a planned ``reset`` fires while the chip measures (:meth:`TMF8820Emulator.reset` resets it at any
other moment); ``checksum`` (a bootloader response with a wrong checksum), ``out_of_order`` (two neighbouring
histogram packets swapped), ``missing_packet`` (one histogram packet never sent); ``dead_after`` makes
every later transfer fail (a dead bus). :meth:`TMF8820Emulator.reset` resets at any moment a test wants.
``stats["injected"]`` counts what fired.
"""

from __future__ import annotations

import ctypes
import math
import random
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from place_safe.drivers.tmf8820 import packets as P
from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.hexfile import RamPatch
from place_safe.sensor.frame import Frame
from place_safe.exceptions import FrameFileError
from place_safe.io.replay import parse_error
from place_safe.io.source import FrameSource

#: Fault kinds the emulator injects and the driver counts under the same names.
FAULT_KINDS = R.FAULT_KINDS
_ERRNO = {"nak": R.ERRNO_NAK, "eio": R.ERRNO_EIO, "timeout": R.ERRNO_TIMEOUT}
_BL_BAD_CHECKSUM = 0x02   # bootloader status for a command with a wrong checksum or length (emulator's code)
_BL_BAD_COMMAND = 0x03    # unknown command, bad address, or no valid RAM image to start
_APP_BAD_COMMAND = 0x03
_CONFIG_DEFAULTS = {R.CFG_PERIOD_MS: (33, 2), R.CFG_KILO_ITERATIONS: (537, 2), R.CFG_CONFIDENCE_THRESHOLD: (6, 1),
                    R.CFG_SPAD_MAP_ID: (R.SPAD_MAP_3X3, 1), R.CFG_ALG_SETTING: (R.ALG_REPORT_DISTANCES, 1),
                    R.CFG_HISTOGRAM_DUMP: (0, 1)}


class VirtualClock:
    """Seconds that pass only when something advances them (the emulator's bus, the host's sleep)."""

    def __init__(self, start: float = 0.0) -> None:
        self.t = float(start)

    def __call__(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            self.t += seconds

    def advance_to(self, t: float) -> None:
        if t > self.t:
            self.t = t


@dataclass
class BusTiming:
    """I2C timing: ``clock_hz`` bus clock, 9 clocks a byte, one clock per START and for the STOP."""

    clock_hz: float = 400e3
    host_overhead_s: float = 0.0  # per i2c_rdwr call (driver and kernel), not counted by default

    def duration(self, nbytes: int, nmessages: int) -> float:
        return (R.CLOCKS_PER_BYTE * nbytes + nmessages + 1) / self.clock_hz + self.host_overhead_s


class FaultPlan:
    """Which faults to inject and when (see module docstring).

    events: (transfer index, kind) pairs; the fault is armed at that transfer and fires at the first
        applicable moment from then on.
    rate: probability per transfer of arming a random kind among ``kinds`` that can apply now.
    dead_after: transfer index from which every transfer fails with a NAK.
    """

    def __init__(self, events: Iterable[tuple[int, str]] = (), rate: float = 0.0,
                 kinds: Iterable[str] = FAULT_KINDS, seed: int = 0, dead_after: int | None = None) -> None:
        self.events = sorted((int(i), str(k)) for i, k in events)
        for _, k in self.events:
            if k not in FAULT_KINDS:
                raise ValueError(f"unknown fault kind {k!r}; expected one of {', '.join(FAULT_KINDS)}")
        self.kinds = tuple(kinds)
        if not 0.0 <= rate <= 1.0:
            raise ValueError(f"fault rate must be in [0, 1], got {rate}")
        self.rate = float(rate)
        self.seed = seed
        self.rng = random.Random(seed)
        self.dead_after = dead_after
        self.armed: list[str] = []

    def tick(self, index: int, applicable: Callable[[str], bool]) -> None:
        while self.events and self.events[0][0] <= index:
            self.armed.append(self.events.pop(0)[1])
        if self.rate and self.rng.random() < self.rate:
            options = [k for k in self.kinds if applicable(k)]
            if options:
                self.armed.append(self.rng.choice(options))

    def take(self, kind: str) -> bool:
        if kind in self.armed:
            self.armed.remove(kind)
            return True
        return False


def _feed_name(feed: FrameSource) -> str:
    """The file a source feeding the emulator reads (its ``path``), or its class's name."""
    path = getattr(feed, "path", None)
    return getattr(path, "name", None) or str(path or type(feed).__name__)


def _feed_iter(feed: Any) -> Callable[[float], Frame | None]:
    """Normalise a feed to ``next(t) -> Frame | None`` (None: the feed has ended). A source's entries a file could
    not parse are skipped; a source that ends without a frame after skipping some raises
    :class:`~place_safe.exceptions.FrameFileError` (a file without one readable entry, not a sensor that stopped)."""
    if isinstance(feed, FrameSource):
        given = False               # whether the feed gave a frame yet
        unreadable: list[str] = []  # why the entries skipped before it were (an end without one says so)

        def from_source(_t: float) -> Frame | None:
            nonlocal given
            while True:  # entries a file could not parse cannot come from a sensor: skip them
                try:
                    frame = feed.read(10.0)
                except StopIteration:
                    if not given and unreadable:  # not a sensor that ended before its first frame: a bad file
                        n = len(unreadable)
                        raise FrameFileError(f"no readable frame in {_feed_name(feed)}: {n} unreadable "
                                             f"entr{'y' if n == 1 else 'ies'} (the first: {unreadable[0]})") from None
                    return None
                if (why := parse_error(frame)) is None:
                    given = True
                    return frame
                if not given:
                    unreadable.append(why)
        return from_source
    if callable(feed) and not isinstance(feed, (list, tuple)):
        return feed
    it: Iterator[Frame] = iter(feed)
    return lambda _t: next(it, None)


class TMF8820Emulator:
    """A TMF8820 on an emulated I2C bus (see module docstring).

    feed: where measurements come from (FrameSource, iterable of Frames, or ``callable(t) -> Frame``).
    address: the device's 7-bit address; transfers to any other address are not acknowledged (errno 121).
    bus_hz: bus clock (Hz). clock: external time source (s); default a :class:`VirtualClock`.
    realtime: follow ``time.monotonic`` and make transfers take real time.
    patch: the RAM patch the device accepts; starting RAM (0x11) fails unless exactly it was downloaded.
    serial: the 16-bit serial number; rom_version / patch_version: the 4 version bytes of each application.
    faults: a :class:`FaultPlan`. record: keep every presented measurement in :attr:`presented`.
    publish_latency_s, overwrite, reset_keeps_wake, short_fill, release_on_read: the device behaviours of the
    module docstring (seconds or a (low, high) range; a switch; two probabilities; a switch).
    """

    def __init__(self, feed: Any = (), *, address: int = R.DEFAULT_ADDRESS, bus_hz: float = 400e3,
                 clock: Callable[[], float] | None = None, realtime: bool = False, patch: RamPatch | None = None,
                 serial: int = 0x2A17, rom_version: tuple[int, int, int, int] = (3, 4, 12, 0),
                 patch_version: tuple[int, int, int, int] = (3, 4, 27, 1), faults: FaultPlan | None = None,
                 record: bool = False, pulse_rate_hz: float = 100e6, processing_s: float = 1e-3,
                 publish_latency_s: float | tuple[float, float] = (50e-6, 100e-6), overwrite: bool = True,
                 reset_keeps_wake: float = 0.5, short_fill: float = 0.5, release_on_read: bool = False,
                 command_s: float = 100e-6,
                 calibration_s: float = 0.3, wake_s: float = 1e-3, boot_s: float = 3e-3, stall_s: float = 0.025,
                 host_overhead_s: float = 0.0, tick_origin: int = 0x1234567) -> None:
        if not (bus_hz > 0 and math.isfinite(bus_hz)):
            raise ValueError(f"bus_hz must be a positive clock rate, got {bus_hz}")
        self.address = address
        self.timing = BusTiming(bus_hz, host_overhead_s)
        self.realtime = realtime
        if clock is not None:
            self.clock, self._advance = clock, None
        elif realtime:
            self.clock, self._advance = time.monotonic, self._sleep_until
        else:
            vc = VirtualClock()
            self.clock, self._advance = vc, vc.advance_to
        self.virtual = self.clock if isinstance(self.clock, VirtualClock) else None
        self._bus_t = self.clock()
        self._dev_t = self._bus_t  # the time the device has been advanced to (within a transfer)
        self._next = _feed_iter(feed)
        self.feed_ended = False
        self.expected_patch = patch
        self.serial = serial & 0xFFFF
        self.rom_version, self.patch_version = tuple(rom_version), tuple(patch_version)
        self.faults = faults or FaultPlan()
        self.record = record
        self.presented: list[tuple[int, np.ndarray, P.Result]] = []
        self.pulse_rate_hz, self.processing_s = pulse_rate_hz, processing_s
        lat = (publish_latency_s, publish_latency_s) if isinstance(publish_latency_s, (int, float)) \
            else tuple(publish_latency_s)
        if len(lat) != 2 or not 0.0 <= lat[0] <= lat[1] or not math.isfinite(lat[1]):
            raise ValueError(f"publish_latency_s must be seconds >= 0 or a (low, high) range, got {publish_latency_s}")
        self.publish_latency_s: tuple[float, float] = (float(lat[0]), float(lat[1]))
        self.overwrite = bool(overwrite)
        self.release_on_read = bool(release_on_read)
        if not (0.0 <= reset_keeps_wake <= 1.0 and 0.0 <= short_fill <= 1.0):
            raise ValueError("reset_keeps_wake and short_fill are probabilities in [0, 1]")
        self.reset_keeps_wake, self.short_fill = float(reset_keeps_wake), float(short_fill)
        self._rng = random.Random(0x7EF8820 ^ self.faults.seed)
        self.command_s, self.calibration_s, self.wake_s, self.boot_s = command_s, calibration_s, wake_s, boot_s
        self.stall_s = stall_s
        self.tick_origin = tick_origin
        self.transfers = 0
        self.stats: dict[str, Any] = {"transfers": 0, "bytes": 0, "bus_seconds": 0.0, "measurements": 0,
                                      "skipped": 0, "overwritten": 0, "racing_reads": 0,
                                      "injected": {k: 0 for k in FAULT_KINDS}}
        self.int_line = EmulatedIntLine(self)
        self._ptr = 0
        self._power_off()

    # -- state ---------------------------------------------------------------------------------------
    def _power_off(self) -> None:
        self.regs = bytearray(256)
        self.awake = False
        self._ready_at: float | None = None
        self._enable_stale = 0
        self._enable_old = 0
        self._boot_at: float | None = None
        self._boot_version: tuple[int, ...] = ()
        self.appid = 0
        self.ram = bytearray(0x10000)
        self._bl_addr = 0
        self._bl_cmd = 0
        self._bl_done_at = 0.0
        self._bl_response = b""
        self._cmd_done_at: float | None = None
        self._cmd_status = R.STAT_OK
        self.config = bytearray(R.PAGE_END - R.PAGE - R.HEADER_SIZE)
        for reg, (value, n) in _CONFIG_DEFAULTS.items():
            self.config[reg - R.PAGE - R.HEADER_SIZE:reg - R.PAGE - R.HEADER_SIZE + n] = value.to_bytes(n, "little")
        self.calibration = bytearray(len(self.config))
        self.active_range = R.CMD_LONG_RANGE
        self.measuring = False
        self._meas_t0 = 0.0
        self._cycle = 1.0
        self._last_done = 0
        self._queue: list[bytes] = []
        self._meas_frame: Frame | None = None  # the feed frame of the measurement being published
        self._carry: Frame | None = None       # a feed frame whose measurement never got out whole
        self._evidence: dict[str, int] = {}    # injected packet faults -> publish position that shows them
        self._published = 0                    # packets of the current measurement put in the window
        self._current: bytes | None = None
        self._current_bit = 0
        self._next_at: float | None = None
        self._tid = 0
        self._result_number = 0

    @property
    def bus_time(self) -> float:
        """Time at which the last transfer ended on the emulated bus (s, on :attr:`clock`)."""
        return self._bus_t

    def now(self) -> float:
        return max(self.clock(), self._bus_t, self._dev_t)

    def _sleep_until(self, t: float) -> None:
        debt = t - time.monotonic()
        if debt > 0.002:
            time.sleep(debt)

    @property
    def cycle_seconds(self) -> float:
        """Measurement repetition time (s) of the current config (see the device timing model)."""
        period = int.from_bytes(self._cfg(R.CFG_PERIOD_MS, 2), "little") / 1000.0
        kilo = int.from_bytes(self._cfg(R.CFG_KILO_ITERATIONS, 2), "little")
        return max(period, kilo * 1000.0 / self.pulse_rate_hz + self.processing_s)

    def _cfg(self, reg: int, n: int) -> bytes:
        o = reg - R.PAGE - R.HEADER_SIZE
        return bytes(self.config[o:o + n])

    def _applicable(self, kind: str) -> bool:
        if kind == "reset":  # while measuring: a chip being brought up is reset by tests through reset()
            return self.awake and self.appid == R.APP_MEASUREMENT and self.measuring
        if kind == "checksum":
            return self.awake and self.appid == R.APP_BOOTLOADER
        if kind in ("out_of_order", "missing_packet"):
            return self.measuring
        return True

    def _inject(self, kind: str) -> bool:
        if self.faults.take(kind):
            self.stats["injected"][kind] += 1
            return True
        return False

    def _set_enable(self, value: int) -> None:
        """ENABLE changes; the first read after a change returns the old value (the protocol notes allow it)."""
        if value != self.regs[R.ENABLE]:
            self._enable_old, self._enable_stale = self.regs[R.ENABLE], 1
            self.regs[R.ENABLE] = value

    def reset(self, keep_wake: bool | None = None) -> None:
        """A spontaneous device reset: RAM, patch, configuration and measurement lost. The wake-up bit either
        survives (a CPU reset: the chip restarts into its bootloader, APPID 0x80, by itself) or not (a power
        loss: standby until the host wakes it). ``keep_wake`` None: at random (``reset_keeps_wake``)."""
        if keep_wake is None:
            keep_wake = self._rng.random() < self.reset_keeps_wake
        old, stale = self.regs[R.ENABLE], self._enable_stale
        self._power_off()
        self.regs[R.ENABLE] = old
        self._enable_stale = stale
        if keep_wake:
            self.awake = True
            self._set_enable(R.ENABLE_WAKEUP)
            self._ready_at = self.now() + self.wake_s
        else:
            self._set_enable(0)

    # -- smbus2 subset -------------------------------------------------------------------------------
    def i2c_rdwr(self, *msgs: Any) -> None:
        """Perform the messages as one combined transaction (writes set the register pointer)."""
        index = self.transfers
        self.transfers += 1
        start = self.now()
        self.faults.tick(index, self._applicable)
        nbytes = sum(1 + m.len for m in msgs)
        end = start + self.timing.duration(nbytes, len(msgs))
        dead = self.faults.dead_after is not None and index >= self.faults.dead_after
        if dead or any(m.addr != self.address for m in msgs):
            self._finish(start + self.timing.duration(1, 1), 1)
            raise OSError(R.ERRNO_NAK, "Remote I/O error")
        for kind in ("nak", "eio", "timeout"):
            if self._inject(kind):
                stall = self.stall_s if kind == "timeout" else 0.0
                self._finish(start + self.timing.duration(1, 1) + stall, 1)
                raise OSError(_ERRNO[kind], {"nak": "Remote I/O error", "eio": "Input/output error",
                                             "timeout": "Connection timed out"}[kind])
        if self._applicable("reset") and self._inject("reset"):
            self.reset()
        t = start
        hz = self.timing.clock_hz
        for m in msgs:
            t_end = t + (R.CLOCKS_PER_BYTE * (1 + m.len) + 1) / hz
            if m.flags & 1:  # I2C_M_RD
                n = m.len
                data = self._read_timed(n, t)
                if n >= 2 and self._inject("short_read"):
                    k = self.faults.rng.randint(1, n - 1)
                    if self._rng.random() < self.short_fill:  # an open bus: the rest reads 0xFF
                        filled = data[:k] + b"\xff" * (n - k)
                        if filled == data:  # indistinguishable from the truth: not a fault yet
                            self.faults.armed.append("short_read")
                            self.stats["injected"]["short_read"] -= 1
                        data = filled
                    else:
                        data, n = data[:k], k
                ctypes.memmove(m.buf, bytes(data[:n]), n)
                m.len = n
            else:
                self._update(t_end)  # a write takes effect when its last byte has arrived
                buf = bytes(m)
                if buf:
                    self._ptr = buf[0]
                    if len(buf) > 1:
                        self._write(self._ptr, buf[1:])
            t = t_end
        self._finish(end, nbytes)

    def _read_timed(self, n: int, t0: float) -> bytes:
        """Read ``n`` bytes in a message starting at ``t0``: byte i is sampled when it crosses the bus, so a
        read that overlaps the publication of the next packet returns old bytes then new ones."""
        hz = self.timing.clock_hz
        self._update(t0)
        first = t0 + (R.CLOCKS_PER_BYTE + 1) / hz  # after the address byte
        last = first + R.CLOCKS_PER_BYTE * n / hz
        pub = self._next_at
        if self.release_on_read and self._current is not None and self._ptr <= R.PAGE \
                and self._ptr + n >= R.PAGE + len(self._current):
            done = first + R.CLOCKS_PER_BYTE * (R.PAGE + len(self._current) - self._ptr) / hz
            data = self._read(n)  # the whole packet went out: released when its last byte has
            self._release(done)
            return data
        if pub is None or not first < pub < last or not (R.PAGE <= self._ptr < R.PAGE_END):
            return self._read(n)
        k = min(n, max(0, int((pub - first) * hz / R.CLOCKS_PER_BYTE)))
        start = self._ptr
        old = self._read(k) if k else b""
        self._update(pub)
        self.stats["racing_reads"] += 1
        data = old + self._read(n - k)
        if self.release_on_read and self._current is not None and start <= R.PAGE \
                and start + n >= R.PAGE + len(self._current):  # the new packet's last byte went out too
            self._release(first + R.CLOCKS_PER_BYTE * (R.PAGE + len(self._current) - start) / hz)
        return data

    def _finish(self, end: float, nbytes: int) -> None:
        self.stats["transfers"] += 1
        self.stats["bytes"] += nbytes
        self.stats["bus_seconds"] += end - max(self.clock(), self._bus_t)
        self._bus_t = end
        if self._advance is not None:
            self._advance(end)

    def read_byte_data(self, addr: int, reg: int) -> int:
        from smbus2 import i2c_msg

        r = i2c_msg.read(addr, 1)
        self.i2c_rdwr(i2c_msg.write(addr, [reg]), r)
        return list(r)[0]

    def write_byte_data(self, addr: int, reg: int, value: int) -> None:
        from smbus2 import i2c_msg

        self.i2c_rdwr(i2c_msg.write(addr, [reg, value & 0xFF]))

    def read_i2c_block_data(self, addr: int, reg: int, length: int) -> list[int]:
        from smbus2 import i2c_msg

        if not 0 < length <= 32:
            raise ValueError("SMBus block transfers carry 1..32 bytes")
        r = i2c_msg.read(addr, length)
        self.i2c_rdwr(i2c_msg.write(addr, [reg]), r)
        return list(r)

    def write_i2c_block_data(self, addr: int, reg: int, data: list[int]) -> None:
        from smbus2 import i2c_msg

        if not 0 < len(data) <= 32:
            raise ValueError("SMBus block transfers carry 1..32 bytes")
        self.i2c_rdwr(i2c_msg.write(addr, [reg, *data]))

    def close(self) -> None:
        """Nothing to release (an SMBus has ``close``)."""

    def __enter__(self) -> "TMF8820Emulator":
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    # -- registers -----------------------------------------------------------------------------------
    def _read(self, n: int) -> bytes:
        start = self._ptr
        if self.awake and self.appid == R.APP_MEASUREMENT and start >= R.PAGE and start + n <= R.ENABLE:
            self._ptr = (start + n) & 0xFF  # plain memory: no register with side effects in range
            return bytes(self.regs[start:start + n])
        out = bytearray()
        for i in range(n):
            reg = (self._ptr + i) & 0xFF
            out.append(self._reg_value(reg))
        self._ptr = (self._ptr + n) & 0xFF
        return bytes(out)

    def _reg_value(self, reg: int) -> int:
        if reg == R.ENABLE:
            if self._enable_stale > 0:
                self._enable_stale -= 1
                return self._enable_old
            return self.regs[R.ENABLE]
        if not self.awake:
            return 0
        if self.appid == R.APP_BOOTLOADER and R.CMD_STAT <= reg < R.CMD_STAT + 3 + R.BL_MAX_CHUNK:
            return self._bl_status_byte(reg - R.CMD_STAT)
        return self.regs[reg]

    def _write(self, reg: int, data: bytes) -> None:
        if reg == R.ENABLE:
            self._write_enable(data[0])
            return
        if not self.awake:
            return
        if reg == R.INT_STATUS:
            self._clear_int(data[0])
        elif reg == R.INT_ENAB:
            self.regs[R.INT_ENAB] = data[0]
        elif reg == R.CMD_STAT and self.appid == R.APP_BOOTLOADER:
            self._bl_command(data)
        elif reg == R.CMD_STAT and self.appid == R.APP_MEASUREMENT:
            self._app_command(data[0])
            if len(data) > 1:
                self._store(reg + 1, data[1:])
        elif self.appid == R.APP_MEASUREMENT and R.PAGE <= reg < R.PAGE_END:
            self._store(reg, data)

    def _store(self, reg: int, data: bytes) -> None:
        end = min(R.PAGE_END, reg + len(data))
        if reg < end:
            self.regs[reg:end] = data[:end - reg]

    def _write_enable(self, value: int) -> None:
        if value & R.ENABLE_WAKEUP and not self.awake:
            self.awake = True
            self._ready_at = self.now() + self.wake_s
            self._set_enable(R.ENABLE_WAKEUP)
        elif not value & R.ENABLE_WAKEUP and self.awake:
            self._power_off()

    def _latency(self) -> float:
        lo, hi = self.publish_latency_s
        return lo if hi <= lo else self._rng.uniform(lo, hi)

    def _clear_int(self, bits: int) -> None:
        self.regs[R.INT_STATUS] &= ~bits & 0xFF
        if self._current is not None and bits & self._current_bit and not self.release_on_read:
            self._release(self.now())

    def _release(self, t: float) -> None:
        self._current = None  # released: the next packet is published after the publish latency
        self._next_at = t + self._latency() if self._queue else None

    # -- bootloader ----------------------------------------------------------------------------------
    def _bl_status_byte(self, offset: int) -> int:
        if self.now() < self._bl_done_at or not self._bl_response:
            return self._bl_cmd if offset == 0 else 0
        resp = self._bl_response
        if offset == len(resp) - 1 and self._bl_cmd in (R.BL_SET_ADDRESS, R.BL_WRITE_RAM, R.BL_READ_RAM) \
                and self._inject("checksum"):
            return resp[offset] ^ 0x5A
        return resp[offset] if offset < len(resp) else 0

    def _bl_respond(self, status: int, payload: bytes = b"") -> None:
        body = bytes([status, len(payload)]) + payload
        self._bl_response = body + bytes([R.bl_checksum(body)])
        self._bl_done_at = self.now() + self.command_s

    def _bl_command(self, data: bytes) -> None:
        self._bl_cmd = data[0]
        if len(data) < 3 or len(data) != 3 + data[1] or R.bl_checksum(data[:-1]) != data[-1]:
            self._bl_respond(_BL_BAD_CHECKSUM)
            return
        cmd, payload = data[0], data[2:-1]
        if cmd == R.BL_SET_ADDRESS and len(payload) == 2:
            self._bl_addr = int.from_bytes(payload, "little")
            self._bl_respond(R.BL_STATUS_OK)
        elif cmd == R.BL_WRITE_RAM and 0 < len(payload) <= R.BL_MAX_CHUNK and self._bl_addr + len(payload) <= 0x10000:
            self.ram[self._bl_addr:self._bl_addr + len(payload)] = payload
            self._bl_addr += len(payload)
            self._bl_respond(R.BL_STATUS_OK)
        elif cmd == R.BL_READ_RAM and len(payload) == 1 and 0 < payload[0] <= R.BL_MAX_CHUNK:
            n = payload[0]
            self._bl_respond(R.BL_STATUS_OK, bytes(self.ram[self._bl_addr:self._bl_addr + n]))
            self._bl_addr += n
        elif cmd == R.BL_START_ROM_APP and not payload:
            self._boot(self.rom_version)
        elif cmd == R.BL_START_RAM_APP and not payload:
            p = self.expected_patch
            if p is not None and bytes(self.ram[p.address:p.address + len(p.data)]) == p.data:
                self._boot(self.patch_version)
            else:
                self._bl_respond(_BL_BAD_COMMAND)
        else:
            self._bl_respond(_BL_BAD_COMMAND)

    def _boot(self, version: tuple[int, ...]) -> None:
        self._bl_response = b""
        self._boot_at = self.now() + self.boot_s
        self._boot_version = version

    # -- application ---------------------------------------------------------------------------------
    def _app_command(self, cmd: int) -> None:
        t = self.now()
        status, delay = R.STAT_OK, self.command_s
        if cmd == R.CMD_MEASURE:
            self.measuring = True
            self._meas_t0 = t
            self._cycle = self.cycle_seconds
            self._last_done = 0
            status = R.STAT_ACCEPTED
        elif cmd == R.CMD_STOP:
            self.measuring = False
            if self._queue or self._current is not None:  # a measurement cut short keeps its feed frame
                self._carry = self._carry or self._meas_frame
                # (a packet in the window that the host has not released is wiped unread: not seen either)
                self._unseen_faults(unread=int(self._current is not None))
            self._queue, self._current, self._next_at = [], None, None
            self.regs[R.INT_STATUS] &= ~R.INT_MEASUREMENT & 0xFF
        elif cmd in (R.CMD_LOAD_CONFIG_COMMON, R.CMD_LOAD_FACTORY_CALIBRATION, R.CMD_LOAD_SPAD_1, R.CMD_LOAD_SPAD_2):
            body = {R.CMD_LOAD_CONFIG_COMMON: self.config,
                    R.CMD_LOAD_FACTORY_CALIBRATION: self.calibration}.get(cmd, bytearray(len(self.config)))
            self.regs[R.PAGE:R.PAGE_END] = bytes([cmd, 0]) + len(body).to_bytes(2, "little") + bytes(body)
        elif cmd == R.CMD_WRITE_CONFIG:
            kind = self.regs[R.PAGE]
            body = self.regs[R.PAGE + R.HEADER_SIZE:R.PAGE_END]
            if kind == R.CMD_LOAD_CONFIG_COMMON:
                self.config[:] = body
            elif kind == R.CMD_LOAD_FACTORY_CALIBRATION:
                self.calibration[:] = body
            elif kind not in (R.CMD_LOAD_SPAD_1, R.CMD_LOAD_SPAD_2):
                status = _APP_BAD_COMMAND
        elif cmd == R.CMD_FACTORY_CALIBRATION:
            rng = np.random.default_rng(self.serial)
            self.calibration[:] = rng.integers(0, 256, len(self.calibration), dtype=np.uint8).tobytes()
            delay = self.calibration_s
        elif cmd in (R.CMD_SHORT_RANGE, R.CMD_LONG_RANGE):
            self.active_range = cmd
            self.regs[R.ACTIVE_RANGE] = cmd
        else:
            status = _APP_BAD_COMMAND
        self.regs[R.CMD_STAT] = cmd
        self._cmd_status = status
        self._cmd_done_at = t + delay

    def _update(self, t: float) -> None:
        """Advance the device to time ``t``: wake-up, boot, commands, measurements, next packet."""
        if t > self._dev_t:
            self._dev_t = t
        if self._ready_at is not None and t >= self._ready_at:
            self._ready_at = None
            self._set_enable(R.ENABLE_WAKEUP | R.ENABLE_CPU_READY)
            self.appid = R.APP_BOOTLOADER
            self.regs[R.APPID] = R.APP_BOOTLOADER
        if self._boot_at is not None and t >= self._boot_at:
            self._boot_at = None
            self.appid = R.APP_MEASUREMENT
            self.regs[R.VERSION:R.VERSION + 4] = bytes(self._boot_version)
            self.regs[R.CMD_STAT] = R.STAT_OK
            self.regs[R.MODE] = 0x00
            self.regs[R.ACTIVE_RANGE] = self.active_range
            self.regs[R.SERIAL_NUMBER:R.SERIAL_NUMBER + 2] = self.serial.to_bytes(2, "little")
        if self._cmd_done_at is not None and t >= self._cmd_done_at:
            self._cmd_done_at = None
            self.regs[R.CMD_STAT] = self._cmd_status
        if not self.measuring:
            return
        free = self._current is None and not self._queue
        if free or self.overwrite:
            done = int((t - self._meas_t0) / self._cycle + 1e-9)
            if done > self._last_done and not self.feed_ended:
                self.stats["skipped"] += done - self._last_done - 1
                self._last_done = done
                if not free and self._queue:  # the host is too slow: the rest of the old one is lost
                    self.stats["overwritten"] += 1
                    self._unseen_faults()
                    self._carry = self._meas_frame  # (its feed frame is not: the next measurement shows it)
                self._present(self._meas_t0 + done * self._cycle)
        if self._current is None and self._queue and self._next_at is not None and t >= self._next_at:
            self._place(self._queue.pop(0))

    def _present(self, t_done: float) -> None:
        frame, self._carry = (self._carry, None) if self._carry is not None else (self._next(t_done), None)
        if frame is None:
            self.feed_ended = True
            return
        self._meas_frame = frame
        ticks = (self.tick_origin + int(round(t_done / R.TICK_SECONDS))) & 0xFFFFFFFF | 1
        channels = np.clip(np.rint(P.frame_channels(frame)), 0, P.COUNT_MAX).astype(np.int64)
        res = P.result_from_frame(frame, self._result_number, ticks,
                                  int(frame.extra.get("temperature", 25)) if isinstance(frame.extra, dict) else 25)
        self._result_number = (self._result_number + 1) & 0xFF
        self.stats["measurements"] += 1
        if self.record:
            self.presented.append((ticks, channels, res))
        blocks = P.split_channels(channels)
        order = list(range(R.HIST_PACKETS))
        evidence: dict[str, int] = {}
        swapped: tuple[int, ...] = ()
        if self._inject("out_of_order"):
            k = self.faults.rng.randrange(R.HIST_PACKETS - 1)
            order[k], order[k + 1] = order[k + 1], order[k]
            swapped = (k, k + 1)
            evidence["out_of_order"] = k + 1  # the host sees it when the second of the pair arrives
        if self._inject("missing_packet"):  # never one of a swapped pair: both faults stay visible
            order.pop(self.faults.rng.choice([i for i in range(len(order)) if i not in swapped]))
            evidence["missing_packet"] = len(order)  # counted when the result frame closes the measurement
        self._evidence, self._published = evidence, 0
        queue = []
        for k in order:
            queue.append(P.encode_histogram_packet(k, blocks[k], self._tid, R.CMD_LOAD_CONFIG_COMMON))
            self._tid = (self._tid + 1) & 0xFF
        queue.append(P.encode_result(res, self._tid))
        self._tid = (self._tid + 1) & 0xFF
        self._queue = queue
        if self._current is None and self._next_at is None:
            self._place(self._queue.pop(0))
        elif self._current is None:  # the window was released: the new packet 0 is published next
            self._next_at = min(self._next_at, t_done + self._latency())

    def pending_faults(self) -> dict[str, int]:
        """Packet faults (``out_of_order``, ``missing_packet``) injected into the measurement still going out, which a
        host counts only when that measurement closes (its result frame) or is dropped: none once its result frame
        has been released."""
        if not self._queue and self._current is None:
            return {}
        return {kind: 1 for kind in self._evidence}

    def _unseen_faults(self, unread: int = 0) -> None:
        """The current measurement will not get out whole: packet faults the host never got to see in it
        are not counted as injected (``unread``: packets published that the host will not read)."""
        for kind, at in self._evidence.items():
            if self._published - unread <= at:
                self.stats["injected"][kind] -= 1
        self._evidence = {}

    def _place(self, packet: bytes) -> None:
        self._published += 1
        self.regs[R.PAGE:R.PAGE + len(packet)] = packet
        self._current = packet
        self._current_bit = R.INT_RESULT if packet[0] == R.CID_RESULT else R.INT_RAW_HISTOGRAM
        self._next_at = None
        self.regs[R.INT_STATUS] |= self._current_bit

    def next_event(self) -> float | None:
        """When the device will next change by itself (s), or None."""
        times = [t for t in (self._ready_at, self._boot_at, self._cmd_done_at, self._next_at) if t is not None]
        if self.measuring and (self.overwrite or (self._current is None and not self._queue)) \
                and not self.feed_ended:
            times.append(self._meas_t0 + (self._last_done + 1) * self._cycle)
        return min(times) if times else None

    @property
    def interrupt(self) -> bool:
        """The INT line is asserted (low): an enabled interrupt is pending."""
        return bool(self.regs[R.INT_STATUS] & self.regs[R.INT_ENAB])


class EmulatedIntLine:
    """The emulator's INT pin with the driver's interrupt-line interface: ``wait(timeout) -> bool``."""

    def __init__(self, emu: TMF8820Emulator) -> None:
        self.emu = emu

    def wait(self, timeout: float) -> bool:
        emu = self.emu
        deadline = emu.now() + max(timeout, 0.0)
        while True:
            t = emu.now()
            emu._update(t)
            if emu.interrupt:
                return True
            if t >= deadline:
                return False
            nxt = emu.next_event()
            target = deadline if nxt is None else min(max(nxt, t + 1e-9), deadline)
            if emu.virtual is not None:
                emu.virtual.advance_to(target)
            elif emu.realtime:
                time.sleep(max(0.0, min(target - t, 0.002)) or 0.0002)
            else:
                return False  # external clock: the caller advances time

    def close(self) -> None:
        pass


__all__ = ["TMF8820Emulator", "FaultPlan", "BusTiming", "VirtualClock", "EmulatedIntLine", "FAULT_KINDS"]
