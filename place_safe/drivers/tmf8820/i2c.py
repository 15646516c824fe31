"""The TMF8820 driver over Linux I2C: a :class:`~place_safe.io.source.FrameSource` on an smbus2 bus.

Concept
-------
:class:`TMF8820Source` speaks the host protocol of ``docs/tmf8820-protocol.md`` through any object with
smbus2's ``i2c_rdwr`` (``smbus2.SMBus`` on ``/dev/i2c-N``, or the register-level emulator in
:mod:`.emulator`). Whole packets move in one combined write-register / read transaction (SMBus block
reads stop at 32 bytes). Bring-up: power up through ENABLE, start the ROM application or download a
user-supplied Intel HEX RAM patch through the bootloader (checksummed commands), check identity and
version, short-range high-accuracy mode, config page (period, kilo-iterations, 3x3 SPAD map, distances,
raw-histogram dump), factory calibration loaded from a file keyed by the sensor's serial number, then
measure. Each measurement's 30 histogram packets and result frame become one Frame
(:class:`~.packets.MeasurementAssembler`).

Reading a measurement (``docs/tmf8820-protocol.md``, host discipline). The chip fills the 0x20 window
with the next packet only after the host released the current one by clearing its interrupt, and that
takes time (the publish latency: tens of microseconds, nothing guarantees zero); a read that races it
returns the old packet or a mix of old and new bytes. So the driver reads a packet only once its interrupt
says it is there (the INT line, ``int_line`` e.g. :class:`GpiodIntLine`, or polling the one-byte
INT_STATUS register), reads it whole in one transaction, clears that interrupt bit, and waits again. When
polling, the first poll after a clear is held back by a tracked quantile of the publish latency (about one
first poll in twenty misses, :data:`POLL_MISS_TARGET`), so the bus carries data and about one poll a
packet. The clear is its own transaction: the packet is checked (stale, cut by an open bus) before the chip
is allowed to replace it. A packet whose cid, transaction id and packet number are those of the packet read last
is stale (an interrupt with nothing new behind it): counted in ``stale_reads``, and from then on short
header reads, never whole packets, tell when a new one is there. In a measurement, an interrupt overdue by
:data:`LOST_INT_S` is looked for in the window's header (a lost interrupt, ``lost_interrupts``). A chip
that takes a packet as released when it has been read, not when its interrupt is cleared (the other
interrupt-clear order), raises the next packet's interrupt before the host's clear, which then wipes it.
After two lost interrupts in a row the driver checks once whether the chip replaces a packet it has read
but not cleared (:meth:`TMF8820Source._probe_clear_order`; the protocol's chip never does): if it does,
the driver clears each interrupt before reading its packet from then on (which on such a chip cannot
release it, nor wipe the next one), else it polls the window's 5-byte header (cid, tid, packet number)
instead of INT_STATUS within a measurement. A packet read that needed a second look (cut, or a 0xFF
tail) is kept only if the window's header still shows it afterwards (:meth:`TMF8820Source._still_there`:
always on the protocol's chip; on the other order the second look may mix two packets, and the measurement
is dropped, ``unverified``).

Validation: headers (cid, payload length 131 / 128), packet numbers 0..29, sub-headers (payload size and
config id the same in all 30 packets), the result frame (valid results at most 18, a result number other
than the last one). A read whose last byte is 0xFF is checked against a second read of its tail (an open
bus reads 0xFF when the chip stops driving it mid-read, whatever length the adapter reports). A broken
measurement is dropped with its reason counted (``bad_packet``, ``short_read``, ``missing_packet``,
``out_of_order``, ``overwritten``): never a half or mixed frame. At most one measurement is in assembly
(:class:`~.packets.MeasurementAssembler`); a packet 0 after a packet 0 means the chip moved on.

Measurement period: the chip measures once per period and overwrites a measurement the host has not read
out in time, so a period shorter than the read-out (about 100 ms at 400 kHz, 40 ms at 1 MHz) gives no
frames at all. ``period_ms`` is the shortest period wanted; the driver fits the period in use
(:attr:`TMF8820Source.period_in_use_ms`, ``info()["period_ms"]``) to the bus (:mod:`.period`): first from
the timing of two bring-up reads, then, after the first whole measurement, the shortest whole-ms period
that 31 measured packet-to-packet intervals plus a queue margin fit in; an overwritten measurement
lengthens it, and after a run without overwrites it is shortened again to what the timings say (with a
doubling wait after a shortening that did not hold). Each change is written to the chip at the next read
(``period_changes``).

Time: ``Frame.timestamp`` is the measurement's completion on the host ``clock`` (default
``time.monotonic``; the simulation's clock when given, then ``clock_domain`` is ``"robot"``). It is
the sensor's system ticks (0.2 us) mapped to the host clock by the smallest offset "host time when the
first packet was seen minus tick time" over the last measurements (:mod:`.ticks`): a measurement
seen right when it finished fixes the offset, and the ticks carry it to the others.
``extra["tmf8820"]`` keeps the ticks, result number, temperature and the host detection time.

Faults: NAK / EIO / adapter timeouts (errno 121, 5, 110) are retried with a bounded exponential back-off;
a bus that keeps failing raises :class:`~place_safe.exceptions.SensorError`. Resets: ENABLE's wake-up or
CPU-ready bit found clear (read twice: the first read after a change may be stale, so a fresh start is
not a reset) or APPID no longer 0x03 (a CPU reset back into the bootloader, 0x80, keeps the wake-up bit;
checked after :data:`ALIVE_S` without interrupts, or on a packet that is neither histogram nor result):
counted in ``reset``, then the application is restarted (ROM or the RAM patch again), the configuration
and factory calibration restored and the measurement restarted (``reinit``), at the period in use.
:data:`MAX_RECOVERIES` re-initialisations without a whole measurement in between are a SensorError (the
next read tries again). ``read(timeout)`` always ends within its timeout plus the transfer in progress
(waits, polls, retries and bring-up steps all stop at the deadline; a bring-up cut short goes on at the
next read). ``stats`` counts each fault under its name in :data:`~.registers.FAULT_KINDS` (the emulator
injects the same kinds) plus frames, dropped measurements, retries and re-initialisations.
"""

from __future__ import annotations

import errno
import json
import math
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

from place_safe.drivers.tmf8820 import packets as P
from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.hexfile import RamPatch, load_patch
from place_safe.drivers.tmf8820.period import PeriodFit, need_ms
from place_safe.drivers.tmf8820.ticks import TickClock
from place_safe.exceptions import ConfigError, SensorError, SensorTimeout
from place_safe.io.source import FrameSource
from place_safe.sensor.frame import Frame

#: Re-initialisations after device resets without a whole measurement in between before giving up.
MAX_RECOVERIES = 5
#: In a measurement, the next packet's interrupt is overdue after this (s; the publish latency is tens of
#: microseconds): check APPID and peek at the window's header for a packet whose interrupt was lost.
LOST_INT_S = 0.002
#: Without any interrupt for this long (s), check that the application still runs (APPID) and peek.
ALIVE_S = 0.02
#: Publish latency (s) assumed per packet when the period is first fitted to the bus (then measured).
PUBLISH_GUESS_S = 100e-6
#: Share of first polls after a clear that may find the packet not yet published (the first poll's hold-off
#: is tracked to it: a miss costs one more poll, a hit a little waiting).
POLL_MISS_TARGET = 0.05
#: Packet timings kept for the period model (10 measurements).
TIMING_WINDOW = 10 * R.HIST_PACKETS
_KEY = R.HEADER_SIZE + 1  # cid, tid, length (2), packet or result number: a packet's identity
_RETRY_ERRNOS = {R.ERRNO_NAK: "nak", R.ERRNO_EIO: "eio", R.ERRNO_TIMEOUT: "timeout", errno.EAGAIN: "timeout"}


class _ProtocolError(Exception):
    """The device answered something the protocol does not allow here (maybe it was reset)."""


class _ChecksumError(_ProtocolError):
    pass


class _Deadline(Exception):
    """The caller's deadline passed inside a wait (the state is kept; the next call goes on from it)."""


def _msg():
    from smbus2 import i2c_msg

    return i2c_msg


class GpiodIntLine:
    """The INT pin through libgpiod (``gpiod`` v2): ``wait(timeout)`` returns True while INT is low."""

    def __init__(self, chip: str, offset: int) -> None:
        try:
            import gpiod
            from gpiod.line import Bias, Edge
        except ImportError:
            raise ConfigError(f"the INT line {chip}:{offset} needs the gpiod package, version 2 (libgpiod v2 "
                              "bindings), which is not installed: pip install \"place-safe[hw]\"") from None
        self._gpiod = gpiod
        self.offset = offset
        try:
            self._req = gpiod.request_lines(chip, consumer="place-safe-tmf8820", config={
                offset: gpiod.LineSettings(edge_detection=Edge.FALLING, bias=Bias.PULL_UP)})
        except OSError as exc:
            raise SensorError(f"cannot request INT line {offset} on {chip}: {exc.strerror or exc}") from None

    def wait(self, timeout: float) -> bool:
        from gpiod.line import Value

        if self._req.get_value(self.offset) == Value.INACTIVE:  # open drain, low while pending
            return True
        if self._req.wait_edge_events(max(timeout, 0.0)):
            self._req.read_edge_events()
            return True
        return False

    def close(self) -> None:
        self._req.release()


class TMF8820Source(FrameSource):
    """A TMF8820 on an I2C bus (see module docstring).

    bus: an object with smbus2's ``i2c_rdwr`` (e.g. ``smbus2.SMBus(1)``, the emulator), or a bus number /
        device path to open with smbus2. address: the sensor's 7-bit address.
    patch: Intel HEX RAM patch (path or :class:`RamPatch`) to download; None starts the ROM application.
    period_ms: the shortest measurement period wanted (ms); the driver lengthens it when the bus cannot read
        a measurement out within it (see module docstring; the period in use is :attr:`period_in_use_ms`).
    kilo_iterations: pulses (thousands); short_range: the short-range high-accuracy mode (else long range).
    calibration_dir: where factory calibration files live (``tmf8820-<serial>.json``); loaded at start if present.
    int_line: object with ``wait(timeout) -> bool`` for the INT pin; None polls INT_STATUS.
    clock, sleep: host time (s) and sleep; clock_domain: what ``clock`` is (default "monotonic", or
        "robot" when a clock is given).
    retries, backoff_s: attempts per transfer and the first back-off (doubling). poll_s: poll interval while
        no packet is due. start: bring the sensor up and start measuring now (else at the first ``read``);
        start_timeout: seconds the bring-up may take before it is a SensorError.
    """

    def __init__(self, bus: Any, address: int = R.DEFAULT_ADDRESS, *, patch: str | Path | RamPatch | None = None,
                 period_ms: int = 33, kilo_iterations: int = 4000, short_range: bool = True,
                 calibration_dir: str | Path | None = None, int_line: Any = None,
                 clock: Callable[[], float] | None = None, sleep: Callable[[float], None] | None = None,
                 clock_domain: str | None = None, retries: int = 6, backoff_s: float = 0.0005,
                 poll_s: float = 0.0005, start: bool = True, start_timeout: float = 5.0) -> None:
        if not 0 <= address <= 0x7F:
            raise ConfigError(f"I2C address 0x{address:x} is not a 7-bit address")
        if not (0 <= period_ms <= 0xFFFF and 1 <= kilo_iterations <= 0xFFFF):
            raise ConfigError(f"period_ms must be 0..65535 and kilo_iterations 1..65535, "
                              f"got {period_ms} and {kilo_iterations}")
        self._owns_bus = not hasattr(bus, "i2c_rdwr")
        if self._owns_bus:
            try:
                from smbus2 import SMBus
            except ImportError:
                raise ConfigError("the I2C driver needs smbus2 (pip install 'place-safe[hw]')") from None
            try:
                bus = SMBus(bus)
            except (OSError, FileNotFoundError) as exc:
                raise SensorError(f"cannot open I2C bus {bus}: {exc.strerror or exc}") from None
        self.bus = bus
        self.address = address
        self.patch = load_patch(patch) if isinstance(patch, (str, Path)) else patch
        self.period_ms, self.kilo_iterations, self.short_range = int(period_ms), int(kilo_iterations), short_range
        self._period = PeriodFit(self.period_ms)
        self._device_period: int | None = None  # the period written to the chip since its last initialisation
        self.rate_hz = 1000.0 / period_ms if period_ms else 30.0
        self.calibration_dir = Path(calibration_dir) if calibration_dir is not None else None
        if self.calibration_dir is not None and self.calibration_dir.exists() and not self.calibration_dir.is_dir():
            raise ConfigError(f"factory calibration folder {self.calibration_dir} is a file, not a folder (it holds "
                              "tmf8820-<serial>.json files; --calibration-dir names the folder)")
        self.int_line = int_line
        self._clock = clock or time.monotonic
        self._sleep = sleep or time.sleep
        self.clock_domain = clock_domain or ("monotonic" if clock is None else "robot")
        self.retries, self.backoff_s, self.poll_s = max(1, retries), backoff_s, poll_s
        self.start_timeout = float(start_timeout)
        self.stats: dict[str, float] = {"frames": 0, "dropped_frames": 0, "retries": 0, "bad_packet": 0,
                                        "stale_reads": 0, "lost_interrupts": 0, "overwritten": 0, "unverified": 0,
                                        "period_changes": 0, "device_errors": 0, "reinit": 0,
                                        "decode_seconds": 0.0, **{k: 0 for k in R.FAULT_KINDS}}
        self.identity: dict[str, Any] = {}
        self._asm = P.MeasurementAssembler()
        self._ticks = TickClock()
        self._initialised = False   # configured since the last reset
        self._measuring = False     # told to measure since the last (re)initialisation
        self._running = False       # the user wants frames (start() / read())
        self._closed = False
        self._recoveries = 0
        self._deadline = math.inf   # of the call in progress (read, start, ...): waits and retries stop there
        self._free_look = False
        self._app_up = False        # the application ran during the bring-up in progress
        self._lost_in_a_row = 0     # packets in a row found by a header read after their interrupt was overdue
        self._peek_polls = False    # then poll the window's header, not INT_STATUS, within a measurement
        self._order_probe = False   # check once whether the chip replaces a packet without our clear
        self._reread = False        # the read in progress needed a second look (see _still_there)
        self._clear_first = False   # it does (it releases a packet once read): clear before reading, not after
        self._forget_stream()
        self._pre_poll = 0.0        # host wait between clearing an interrupt and the first poll (s, adaptive)
        self._poll_cost = 0.0       # duration of one INT_STATUS poll (s, running mean)
        # packet-to-packet times and transfers (detection to the end of the clear) of the last measurements (s)
        self._intervals: deque[float] = deque(maxlen=TIMING_WINDOW)
        self._transfers: deque[float] = deque(maxlen=TIMING_WINDOW)
        if start:
            try:
                self.start()
            except BaseException:
                if self._owns_bus:
                    self.bus.close()
                raise

    def _forget_stream(self) -> None:
        self._asm.discard()
        self._ticks.reset()
        self._last_key: bytes | None = None  # cid, tid and packet / result number of the last packet read
        self._last_result: int | None = None
        self._first_seen: float | None = None
        self._prev_seen: float | None = None
        self._stale_since: float | None = None
        self._next_due: float | None = None

    # -- bus primitives ------------------------------------------------------------------------------
    def _xfer(self, *msgs: Any) -> None:
        delay = self.backoff_s
        for attempt in range(self.retries):
            try:
                self.bus.i2c_rdwr(*msgs)
                return
            except OSError as exc:
                kind = _RETRY_ERRNOS.get(exc.errno)
                if kind is None:
                    raise SensorError(f"TMF8820 at 0x{self.address:02x}: I2C failed: {exc.strerror or exc}") from None
                self.stats[kind] += 1
                if attempt + 1 < self.retries:
                    if self._clock() + delay > self._deadline:
                        raise _Deadline from None
                    self.stats["retries"] += 1
                    self._sleep(delay)
                    delay *= 2
        raise SensorError(f"TMF8820 at 0x{self.address:02x} does not answer: {self.retries} I2C transfers "
                          f"failed in a row (dead bus or sensor unpowered)")

    def _read_raw(self, reg: int, n: int) -> bytes:
        m = _msg()
        r = m.read(self.address, n)
        self._xfer(m.write(self.address, [reg]), r)
        return bytes(r)

    def _read(self, reg: int, n: int) -> bytes:
        """Read ``n`` register bytes, whole and not cut short by an open bus.

        A read that comes back short is read again. A read whose last byte is 0xFF may have been cut short by a
        device that stopped driving the bus (the rest reads 0xFF, whatever the length says). Its trailing run of
        0xFF bytes is read again (usually one byte), from the run's first byte: all 0xFF again, and the first read
        holds the register bytes (a cut could only have put 0xFF where 0xFF was; a read cut again still starts
        true). A read that is 0xFF throughout is read again whole. When they differ it is read again until a read
        does not end in 0xFF or two reads agree (two whole reads cut alike would agree: before 2026-11-29 reads of
        16 bytes or fewer were checked that way, and two identical cuts of a header got through). Only ever used where
        a second read sees the same bytes (registers, a packet whose interrupt is still pending). Counted as
        ``short_read``.
        """
        prev: bytes | None = None
        tail: bytes | None = None
        tail_at = n
        bad = 0
        for attempt in range(self.retries + 1):
            if attempt:
                self._due()
                self._reread = True
            data = self._read_raw(reg, n)
            if len(data) != n:
                self.stats["short_read"] += 1
                continue
            if prev is None and tail is None and n >= 2 and data[-1] == 0xFF and data.rstrip(b"\xff"):
                tail_at = len(data.rstrip(b"\xff"))
                self._reread = True
                tail = self._read_raw((reg + tail_at) & 0xFF, n - tail_at)
                if tail == data[tail_at:]:
                    return data  # the bytes really end in 0xFF
            if n < 2 or data[-1] != 0xFF or data == prev:
                if prev is not None and prev != data:
                    bad += 1
                if tail is not None and tail != data[tail_at:]:
                    bad += 1  # the tail read itself was cut
                self.stats["short_read"] += bad
                return data
            if prev is not None:
                bad += 1
            prev = data
        raise SensorError(f"TMF8820 at 0x{self.address:02x}: {self.retries} cut or unstable reads in a row")

    def _write(self, reg: int, data: bytes | list[int]) -> None:
        self._xfer(_msg().write(self.address, [reg, *data]))

    def _nap(self, seconds: float, deadline: float) -> None:
        """Sleep ``seconds`` but not past ``deadline`` (then :class:`_Deadline`)."""
        now = self._clock()
        if now >= deadline:
            raise _Deadline
        self._sleep(max(0.0, min(seconds, deadline - now)))

    def _enable_settled(self) -> int:
        """ENABLE read twice (the first read after a change may return the old value): the second."""
        self._read(R.ENABLE, 1)
        return self._read(R.ENABLE, 1)[0]

    # -- bring-up ------------------------------------------------------------------------------------
    def _power_up(self, deadline: float) -> None:
        value = self._enable_settled()
        if value & R.ENABLE_WAKEUP and value & R.ENABLE_CPU_READY:
            return
        if not value & R.ENABLE_WAKEUP:
            self._write(R.ENABLE, [value | R.ENABLE_WAKEUP])
            self._nap(0.010, deadline)
        limit = self._clock() + 0.2
        while True:
            value = self._enable_settled()
            if value & R.ENABLE_CPU_READY and value & R.ENABLE_WAKEUP:
                return
            if self._clock() > limit:
                raise SensorError(f"TMF8820 at 0x{self.address:02x}: CPU not ready 200 ms after wake-up "
                                  f"(ENABLE 0x{value:02x})")
            self._nap(0.001, deadline)

    def _bl(self, cmd: int, deadline: float, payload: bytes = b"", reply: int = 0) -> bytes:
        body = bytes([cmd, len(payload)]) + bytes(payload)
        self._due()
        self._write(R.CMD_STAT, body + bytes([R.bl_checksum(body)]))
        limit = self._clock() + 0.05
        while True:
            r = self._read(R.CMD_STAT, 3 + reply)
            if r[0] != cmd:
                break
            if self._clock() > limit:
                raise _ProtocolError(f"bootloader command 0x{cmd:02x} still busy after 50 ms")
            self._nap(0.00005, deadline)
        n = r[1]
        if n != reply or r[2 + n] != R.bl_checksum(r[:2 + n]):
            raise _ChecksumError(f"bootloader reply to 0x{cmd:02x} has a bad checksum or length")
        if r[0] != R.BL_STATUS_OK:
            raise _ProtocolError(f"bootloader command 0x{cmd:02x} failed with status 0x{r[0]:02x}")
        return r[2:2 + n]

    def _download(self, patch: RamPatch, deadline: float) -> None:
        for addr, chunk in patch.chunks(R.BL_MAX_CHUNK):
            for _ in range(self.retries):
                try:
                    self._bl(R.BL_SET_ADDRESS, deadline, addr.to_bytes(2, "little"))
                    self._bl(R.BL_WRITE_RAM, deadline, chunk)
                    break
                except _ChecksumError:
                    self.stats["checksum"] += 1
            else:
                raise SensorError(f"TMF8820: RAM patch download failed at 0x{addr:04x} ({self.retries} bad replies)")

    def _start_app(self, deadline: float) -> None:
        appid = self._read(R.APPID, 1)[0]
        if appid == R.APP_BOOTLOADER:
            if self.patch is not None:
                self._download(self.patch, deadline)
                body = bytes([R.BL_START_RAM_APP, 0])
            else:
                body = bytes([R.BL_START_ROM_APP, 0])
            self._write(R.CMD_STAT, body + bytes([R.bl_checksum(body)]))
            limit = self._clock() + 0.5
            while (appid := self._read(R.APPID, 1)[0]) != R.APP_MEASUREMENT:
                if self._clock() > limit:
                    status = self._read(R.CMD_STAT, 1)[0]
                    if self.patch is not None and status not in (body[0], R.BL_STATUS_OK):
                        raise SensorError(f"TMF8820 rejected the RAM patch (bootloader status 0x{status:02x}); "
                                          "is it the TMF8820 application patch from ams?")
                    raise _ProtocolError(f"application did not start (APPID 0x{appid:02x})")
                enable = self._enable_settled()
                if not (enable & R.ENABLE_WAKEUP and enable & R.ENABLE_CPU_READY):
                    self._reset_seen(f"ENABLE 0x{enable:02x} while its application started")
                self._nap(0.001, deadline)
        elif appid == R.APP_MEASUREMENT:  # already running (e.g. a previous session): stop what it does
            self._command(R.CMD_STOP, deadline)
            self._write(R.INT_STATUS, [0xFF])
        else:
            raise _ProtocolError(f"unexpected APPID 0x{appid:02x} (expected 0x80 bootloader or 0x03 application)")

    def _command(self, cmd: int, deadline: float, timeout: float = 0.1,
                 ok: tuple[int, ...] = (R.STAT_OK,)) -> None:
        self._due()
        self._write(R.CMD_STAT, [cmd])
        limit = self._clock() + timeout
        while (status := self._read(R.CMD_STAT, 1)[0]) >= R.STAT_BUSY_MIN:
            if self._clock() > limit:
                raise _ProtocolError(f"command 0x{cmd:02x} not done after {timeout:g} s")
            self._nap(min(0.0002, timeout / 20), deadline)
        if status not in ok:
            raise _ProtocolError(f"command 0x{cmd:02x} failed with status 0x{status:02x}")

    def _load_page(self, cmd: int, deadline: float) -> bytearray:
        self._command(cmd, deadline)
        page = bytearray(self._read(R.PAGE, R.PAGE_END - R.PAGE))
        if page[0] != cmd:
            raise _ProtocolError(f"page 0x{cmd:02x} did not load (page id 0x{page[0]:02x})")
        return page

    def _configure(self, deadline: float) -> None:
        self._command(R.CMD_SHORT_RANGE if self.short_range else R.CMD_LONG_RANGE, deadline)
        self._command(R.CMD_LOAD_CONFIG_COMMON, deadline)
        self._due()
        t0 = self._clock()
        self._read(R.ACTIVE_RANGE, 1)
        t1 = self._clock()
        page = bytearray(self._read(R.PAGE, R.PAGE_END - R.PAGE))
        t2 = self._clock()
        if page[0] != R.CMD_LOAD_CONFIG_COMMON:
            raise _ProtocolError(f"the config page did not load (page id 0x{page[0]:02x})")
        if not self._period.fitted:  # the bus's speed from a 1-byte and a 192-byte read
            self._period_from_bus(t1 - t0, t2 - t1)

        def put(reg: int, value: int, n: int = 1) -> None:
            page[reg - R.PAGE:reg - R.PAGE + n] = value.to_bytes(n, "little")

        put(R.CFG_PERIOD_MS, self.period_in_use_ms, 2)
        put(R.CFG_KILO_ITERATIONS, self.kilo_iterations, 2)
        put(R.CFG_SPAD_MAP_ID, R.SPAD_MAP_3X3)
        put(R.CFG_ALG_SETTING, page[R.CFG_ALG_SETTING - R.PAGE] | R.ALG_REPORT_DISTANCES)
        put(R.CFG_HISTOGRAM_DUMP, R.HIST_DUMP_RAW)
        first, last = R.CFG_PERIOD_MS, R.CFG_HISTOGRAM_DUMP + 1
        self._write(first, page[first - R.PAGE:last - R.PAGE])
        self._command(R.CMD_WRITE_CONFIG, deadline)
        self._device_period = self.period_in_use_ms
        cal = self.calibration_file()
        if cal is not None and cal.is_file():
            data = self._calibration_page(cal)
            self._load_page(R.CMD_LOAD_FACTORY_CALIBRATION, deadline)
            self._write(R.PAGE + R.HEADER_SIZE, data)
            self._command(R.CMD_WRITE_CONFIG, deadline)
            self.identity["calibration"] = str(cal)
        elif cal is not None:  # a directory without this unit's file (another unit's, or none yet): said, not hidden
            self.identity["calibration"] = (f"none: no {cal.name} in {cal.parent} (make it with 'place-safe sensor "
                                            "info URI --calibration-dir DIR --factory-calibrate')")

    def _was_reset(self) -> bool:
        try:
            enable = self._enable_settled()
            return not (enable & R.ENABLE_WAKEUP and enable & R.ENABLE_CPU_READY) \
                or self._read(R.APPID, 1)[0] != R.APP_MEASUREMENT
        except _Deadline:
            return False

    def _initialise(self, deadline: float) -> None:
        self._app_up = False
        self._power_up(deadline)
        self._start_app(deadline)
        self._app_up = True
        version = self._read(R.VERSION, 4)
        serial = int.from_bytes(self._read(R.SERIAL_NUMBER, 2), "little")
        mode = self._read(R.MODE, 1)[0]
        if version[0] != R.APP_MEASUREMENT:
            raise _ProtocolError(f"APPID 0x{version[0]:02x} after the application started")
        if mode != 0x00:
            raise SensorError(f"TMF8820 at 0x{self.address:02x} is in mode 0x{mode:02x}, expected 0x00 (3x3)")
        self.identity = {"address": f"0x{self.address:02x}", "app_version": ".".join(str(v) for v in version),
                         "serial": f"{serial:04x}", "application": "RAM patch" if self.patch else "ROM"}
        self._configure(deadline)
        self.identity["active_range"] = ("short (high accuracy)" if self._read(R.ACTIVE_RANGE, 1)[0] == R.CMD_SHORT_RANGE
                                         else "long")
        self._write(R.INT_ENAB, [R.INT_MEASUREMENT])
        self._write(R.INT_STATUS, [0xFF])
        self._initialised = True

    def _bring_up(self, deadline: float) -> None:
        last: Exception | None = None
        for _ in range(4):
            try:
                self._initialise(deadline)
                return
            except _ProtocolError as exc:
                last = exc
                self._initialised = False
                self.stats["reinit"] += 1
                if self._app_up and self._was_reset():  # the application ran, and the chip restarted since
                    self.stats["reset"] += 1
        raise SensorError(f"TMF8820 at 0x{self.address:02x} could not be initialised: {last}")

    def _start_measuring(self, deadline: float) -> None:
        """Initialise if needed and start measuring (resumable: a deadline leaves it to the next call)."""
        if not self._initialised:
            self._bring_up(deadline)
        self._forget_stream()
        self._command(R.CMD_MEASURE, deadline, ok=(R.STAT_ACCEPTED, R.STAT_OK))
        self._measuring = True

    def start(self) -> None:
        """Bring the sensor up (if needed) and start measuring."""
        if self._closed:
            raise SensorError("the TMF8820 source is closed")
        self._running = True
        deadline = self._deadline = self._clock() + self.start_timeout
        for _ in range(4):
            try:
                self._start_measuring(deadline)
                return
            except _Deadline:
                break
            except _ProtocolError:
                self._initialised = self._measuring = False
        raise SensorError(f"TMF8820 at 0x{self.address:02x} does not start measuring "
                          f"(not streaming {self.start_timeout:g} s after the start)")

    def stop(self) -> None:
        """Stop measuring (the sensor stays configured)."""
        self._running = False
        if self._measuring:
            self._measuring = False
            try:
                deadline = self._deadline = self._clock() + 1.0
                self._command(R.CMD_STOP, deadline)
                self._write(R.INT_STATUS, [R.INT_MEASUREMENT])
            except (_ProtocolError, _Deadline):
                self._initialised = False

    # -- measurement period --------------------------------------------------------------------------
    @property
    def period_in_use_ms(self) -> int:
        """The measurement period in use (ms): ``period_ms`` or longer, fitted to the read-out (:mod:`.period`)."""
        return self._period.period_ms

    def _period_from_bus(self, t_small: float, t_page: float) -> None:
        """Before the first measurement: a period the bus can carry, from the timing of a 1-byte read (5 bytes
        on the wire) and of the 192-byte page read (195), assuming :data:`PUBLISH_GUESS_S` per packet."""
        per_byte = max(0.0, (t_page - t_small) / 190.0)
        per_xfer = max(0.0, t_small - 5 * per_byte)
        per_packet = 3 * per_xfer + (R.HIST_PACKET_SIZE + 3 + 3 + 4) * per_byte + PUBLISH_GUESS_S
        self._period.guess(math.ceil((R.HIST_PACKETS + 1) * per_packet * 1000.0))
        self.rate_hz = 1000.0 / self.period_in_use_ms if self.period_in_use_ms else 30.0

    def _need(self) -> int | None:
        """The shortest period (ms) the measured read-out holds (:func:`.period.need_ms`)."""
        return need_ms(self._intervals, self._transfers)

    def _write_period(self, deadline: float) -> None:
        """Put the period in use on the chip: stop, rewrite the config page's period, (re)start at the next step
        (resumable: a deadline in the middle leaves it to the next read)."""
        self._measuring = False
        self._command(R.CMD_STOP, deadline)
        self._write(R.INT_STATUS, [R.INT_MEASUREMENT])
        self._command(R.CMD_LOAD_CONFIG_COMMON, deadline)
        ms = self.period_in_use_ms
        self._write(R.CFG_PERIOD_MS, ms.to_bytes(2, "little"))
        self._command(R.CMD_WRITE_CONFIG, deadline)
        self._device_period = ms
        self.rate_hz = 1000.0 / ms if ms else 30.0
        self.stats["period_changes"] += 1

    # -- calibration ---------------------------------------------------------------------------------
    def calibration_file(self) -> Path | None:
        """Factory calibration file of this sensor (by serial number), or None without a directory."""
        if self.calibration_dir is None or "serial" not in self.identity:
            return None
        return self.calibration_dir / f"tmf8820-{self.identity['serial']}.json"

    def _calibration_page(self, path: Path) -> bytes:
        try:
            from place_safe.io.input_file import read_input_bytes

            d = json.loads(read_input_bytes(path, "factory calibration", ConfigError))
            data = bytes.fromhex(d["page"])
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"factory calibration {path} is unreadable: {exc}") from None
        if d.get("serial") != self.identity.get("serial") or len(data) != R.PAGE_END - R.PAGE - R.HEADER_SIZE:
            raise ConfigError(f"factory calibration {path} is not for sensor {self.identity.get('serial')}")
        return data

    def factory_calibrate(self, timeout: float = 5.0) -> Path:
        """Run the sensor's factory calibration (no target within 40 cm, dark) and save its page."""
        if self.calibration_dir is None:
            raise ConfigError("factory calibration needs a calibration directory")
        deadline = self._deadline = self._clock() + self.start_timeout + timeout
        try:
            if not self._initialised:
                self._bring_up(deadline)
            was_running = self._running
            self.stop()
            self._command(R.CMD_FACTORY_CALIBRATION, deadline, timeout=timeout)
            page = self._load_page(R.CMD_LOAD_FACTORY_CALIBRATION, deadline)
        except (_ProtocolError, _Deadline) as exc:
            raise SensorError(f"factory calibration failed: {exc or 'it did not finish in time'}") from None
        path = self.calibration_file()
        assert path is not None
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"serial": self.identity["serial"], "app_version": self.identity["app_version"],
                                    "page": bytes(page[R.HEADER_SIZE:]).hex()}, indent=1) + "\n")
        self.identity["calibration"] = str(path)  # (the chip holds the page it just made)
        if was_running:
            self.start()
        return path

    # -- streaming -----------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """Identity, versions, mode and configuration (brings the sensor up if needed)."""
        if not self._initialised:
            try:
                self._deadline = self._clock() + self.start_timeout
                self._bring_up(self._deadline)
            except _Deadline:
                raise SensorError(f"TMF8820 at 0x{self.address:02x} not up {self.start_timeout:g} s "
                                  "after the start") from None
        return {**self.identity, "mode": "3x3", "period_ms": self.period_in_use_ms,
                "requested_period_ms": self.period_ms, "kilo_iterations": self.kilo_iterations,
                "histograms": "raw", "clock_domain": self.clock_domain}

    def read(self, timeout: float = 1.0) -> Frame:
        """The next whole measurement; SensorTimeout if none within ``timeout`` s (on ``clock``), whatever the
        device does (the call returns at most one bus transfer after the deadline); SensorError if the bus
        is dead or the sensor keeps resetting."""
        if self._closed:
            raise SensorError("the TMF8820 source is closed")
        self._running = True
        deadline = self._deadline = self._clock() + max(timeout, 0.0)
        self._free_look = True  # a read with no time to wait still takes a packet that is there
        while True:
            try:
                if self._initialised and self._device_period != self.period_in_use_ms:
                    self._write_period(deadline)
                if not self._measuring:
                    self._start_measuring(deadline)
                frame = self._step(deadline)
            except _Deadline:
                state = "measurement in progress" if self._asm.started else "waiting for one"
                if not self._measuring:
                    state = "sensor restarting"
                raise SensorTimeout(f"no TMF8820 measurement within {timeout:g} s ({state})") from None
            except _ProtocolError as exc:
                self._recoveries += 1
                if self._recoveries > MAX_RECOVERIES:
                    self._recoveries = 0  # the next read tries again
                    self._lost_device()
                    raise SensorError(f"TMF8820 at 0x{self.address:02x} keeps resetting: {MAX_RECOVERIES} "
                                      f"re-initialisations without a whole measurement ({exc})") from None
                self._lost_device()
                continue
            if frame is not None:
                self._recoveries = 0
                return frame

    @property
    def measurement_in_progress(self) -> bool:
        """Some packets of a measurement have been read, not yet its result frame."""
        return self._asm.started

    @property
    def streaming(self) -> bool:
        """Initialised and told to measure (False after a reset until the bring-up is done again)."""
        return self._measuring

    def _lost_device(self) -> None:
        """After a reset (or answers the protocol does not allow): forget the measurement in progress
        (counting what it already showed) and initialise again."""
        for reason in self._asm.abandon():
            self.stats[reason] += 1
        self._forget_stream()
        self._initialised = self._measuring = False
        self.stats["reinit"] += 1

    def _reset_seen(self, why: str) -> None:
        self.stats["reset"] += 1
        raise _ProtocolError(f"the sensor was reset ({why})")

    def _check_enable(self, value: int) -> None:
        """A wake-up or CPU-ready bit that is clear (read again: the first read may be stale) is a reset."""
        if value & R.ENABLE_WAKEUP and value & R.ENABLE_CPU_READY:
            return
        again = self._read(R.ENABLE, 1)[0]
        if not (again & R.ENABLE_WAKEUP and again & R.ENABLE_CPU_READY):
            self._reset_seen(f"ENABLE 0x{again:02x}")

    def _check_app(self) -> None:
        """APPID must still be the measurement application (0x80: the chip restarted into its bootloader,
        which a CPU reset does without touching ENABLE's wake-up bit)."""
        appid = self._read(R.APPID, 1)[0]
        if appid != R.APP_MEASUREMENT:
            again = self._read(R.APPID, 1)[0]
            if again != R.APP_MEASUREMENT:
                self._reset_seen(f"APPID 0x{again:02x}")

    def _is_old(self, head: bytes) -> bool:
        """Do these first bytes of the window show the packet we read last (cid, tid, packet number)?"""
        return head[0] in (R.CID_RAW_HISTOGRAM, R.CID_RESULT) and head[:_KEY] == self._last_key

    def _window_has_new(self) -> bool:
        """A short header read: does the 0x20 window hold a packet we have not read (an interrupt lost)?"""
        self._due()
        h = self._read(R.PAGE, _KEY)
        return h[0] in (R.CID_RAW_HISTOGRAM, R.CID_RESULT) and self._last_key is not None and not self._is_old(h)

    def _due(self) -> None:
        if self._clock() >= self._deadline:
            raise _Deadline

    def _wait_packet(self, deadline: float) -> int:
        """Wait until a packet is in the window: its interrupt (line or INT_STATUS), or a header read after
        an overdue interrupt. Detects resets (ENABLE, APPID). Returns the pending interrupt bits."""
        start = self._clock()
        mid = self._asm.started
        check = start + (LOST_INT_S if mid else ALIVE_S)
        if mid and self._pre_poll > 0.0 and self.int_line is None:
            self._nap(self._pre_poll, deadline)
        polls = 0
        while True:
            if polls or not self._free_look:  # one look per read, even with no time to wait
                self._due()
            self._free_look = False
            polls += 1
            if mid and self._peek_polls:  # interrupts get lost on this chip: poll the window's header
                if self._window_has_new():
                    return R.INT_MEASUREMENT
            elif self.int_line is not None:
                t = self._clock()
                if self.int_line.wait(max(0.0, min(deadline, check) - t)):
                    return R.INT_MEASUREMENT
                if self._clock() <= t:  # a line that cannot wait on this clock
                    self._nap(self.poll_s, max(deadline, t + 1e-9))
            else:
                t_poll = self._clock()
                status = self._read(R.INT_STATUS, 1)[0]
                self._poll_cost += (self._clock() - t_poll - self._poll_cost) / 8
                if status & R.INT_ERROR:
                    self.stats["device_errors"] += 1
                    self._write(R.INT_STATUS, [R.INT_ERROR])
                if status & R.INT_MEASUREMENT:
                    self._lost_in_a_row = 0
                    if mid:
                        self._hold_first_poll(missed=polls > 1)
                    return status
            now = self._clock()
            if now >= check:
                self._due()
                self._check_enable(self._read(R.ENABLE, 1)[0])
                self._due()
                self._check_app()
                if self._window_has_new():
                    self.stats["lost_interrupts"] += 1
                    self._lost_in_a_row += 1
                    if self._lost_in_a_row >= 2 and not (self._peek_polls or self._clear_first):
                        self._order_probe = True
                    return R.INT_MEASUREMENT
                check = now + ALIVE_S
                mid = False
            if now >= deadline:
                raise _Deadline
            due = self._next_due is not None and now >= self._next_due - 0.001
            if mid and self._peek_polls:
                continue
            if self.int_line is None and not mid and not due:
                self._nap(min(self.poll_s, check - now), deadline)

    def _hold_first_poll(self, missed: bool) -> None:
        """Aim the first poll after a clear at the publish latency: a quantile tracker of the hold-off (up by an
        eighth of a poll when the first poll missed, down by a share that makes :data:`POLL_MISS_TARGET` of
        first polls miss), so the bus carries data and about one poll a packet."""
        step = self._poll_cost / 8
        if missed:
            self._pre_poll = min(LOST_INT_S / 4, self._pre_poll + step)
        else:
            self._pre_poll = max(0.0, self._pre_poll - step * POLL_MISS_TARGET / (1.0 - POLL_MISS_TARGET))

    def _step(self, deadline: float) -> Frame | None:
        """Wait for one packet, read it, handle it; a Frame when it closed a whole measurement."""
        bits = self._wait_packet(deadline)
        seen = self._clock()
        if self._stale_since is not None:  # the last read found no new packet: check the header first
            self._due()
            if self._is_old(self._read(R.PAGE, _KEY)):
                if seen - self._stale_since > LOST_INT_S:  # an interrupt with nothing behind it: release it
                    self._write(R.INT_STATUS, [bits & R.INT_MEASUREMENT])
                    self._stale_since = seen
                self._nap(self.poll_s, deadline)
                return None
        if self._clear_first:  # a chip that releases on read: the clear cannot wipe the next interrupt now
            self._write(R.INT_STATUS, [bits & R.INT_MEASUREMENT or R.INT_MEASUREMENT])
        self._reread = False
        buf = self._read(R.PAGE, R.HIST_PACKET_SIZE)
        if self._reread and not self._still_there(buf):
            return None
        if self._order_probe and buf[0] == R.CID_RAW_HISTOGRAM and not self._is_old(buf):
            self._probe_clear_order(buf, deadline)
        return self._handle(buf, bits, seen, deadline)

    def _still_there(self, buf: bytes) -> bool:
        """After a packet read that needed a second look (cut, or a 0xFF tail): is the packet still in the
        window (header read)? A chip that releases a packet once it has been read may have replaced it
        meanwhile, and then the second look may hold a mix of two packets: the packet is dropped (its
        measurement with it, ``unverified``). The protocol's chip keeps it until its clear: always there."""
        self._due()
        head = self._read(R.PAGE, _KEY)
        if head == bytes(buf[:_KEY]):
            return True
        self.stats["unverified"] += 1
        self._asm.mark("short_read")
        return False

    def _probe_clear_order(self, buf: bytes, deadline: float) -> None:
        """Interrupts got lost twice in a row: does the chip replace a packet that was read but not cleared?
        Wait :data:`LOST_INT_S` (far above any publish latency) and look at the window's header. A new packet
        there is proof that the chip releases a packet once it has been read (the protocol's chip never
        replaces a packet before its clear): from then on the interrupt is cleared before the read, which
        cannot wipe the next packet's. Otherwise the driver polls the window's header within a measurement."""
        self._order_probe = False
        self._nap(LOST_INT_S, deadline)
        head = self._read(R.PAGE, _KEY)
        if head[0] in (R.CID_RAW_HISTOGRAM, R.CID_RESULT) and head != buf[:_KEY]:
            self._clear_first = True
            self._lost_in_a_row = 0
        else:
            self._peek_polls = True

    def _handle(self, buf: bytes, bits: int, seen: float, deadline: float) -> Frame | None:
        cid = buf[0]
        if self._is_old(buf):
            self.stats["stale_reads"] += 1  # the packet we already have: no new one behind this interrupt
            if self._stale_since is None:
                self._stale_since = seen
            return None
        self._stale_since = None
        if cid == R.CID_RAW_HISTOGRAM:
            t0 = time.perf_counter()
            self._last_key = bytes(buf[:_KEY])
            if not self._clear_first:
                self._write(R.INT_STATUS, [R.INT_RAW_HISTOGRAM])
            self._transfers.append(self._clock() - seen)
            try:
                number, data = P.decode_histogram_packet(buf)
            except P.PacketError:
                self.stats["bad_packet"] += 1
                self._asm.mark("bad_packet")
                return None
            fresh = not self._asm.started
            dropped = self._asm.add_histogram(number, data, tag=(buf[5], buf[6]))
            if dropped is not None:
                P.count_drops(self.stats, self._asm.drops)
            if fresh or dropped is not None:
                self._first_seen = seen
                self._next_due = seen + self.period_in_use_ms / 1000.0
            elif self._prev_seen is not None:
                self._intervals.append(seen - self._prev_seen)
            self._prev_seen = seen
            self.stats["decode_seconds"] += time.perf_counter() - t0
            if dropped == "overwritten":  # applied at once: the read loop rewrites the period
                self._period.overwritten(self._need)
            return None
        if cid == R.CID_RESULT:
            self._last_key = bytes(buf[:_KEY])
            if not self._clear_first:
                self._write(R.INT_STATUS, [R.INT_RESULT])
            self._transfers.append(self._clock() - seen)
            t0 = time.perf_counter()
            if self._prev_seen is not None and self._asm.started:
                self._intervals.append(seen - self._prev_seen)
            self._prev_seen = None
            try:
                res = P.decode_result(buf)
                if res.valid_results > R.RESULT_CHANNELS or res.result_number == self._last_result:
                    raise P.PacketError("implausible result frame")
            except P.PacketError:
                self.stats["bad_packet"] += 1
                self._asm.mark("bad_packet")
                res = P.Result()
            else:
                self._last_result = res.result_number
            first = self._first_seen if self._first_seen is not None else seen
            self._first_seen = None
            frame = self._asm.add_result(res)
            self.stats["decode_seconds"] += time.perf_counter() - t0
            if frame is None:
                P.count_drops(self.stats, self._asm.drops)
                return None
            frame.timestamp = self._ticks.stamp(res.sys_ticks, first) if res.ticks_valid else first
            self.stats["frames"] += 1
            # the first fit, or a shorter period after a long run without overwrites: written at the next read
            self._period.frame(self._need)
            return frame
        # neither a histogram packet nor a result frame: a reset chip reads zeros; else drop the measurement
        self._check_app()
        self.stats["bad_packet"] += 1
        self._asm.mark("bad_packet")
        self._write(R.INT_STATUS, [bits & R.INT_MEASUREMENT or R.INT_MEASUREMENT])
        return None

    def close(self) -> None:
        if self._closed:
            return
        try:
            if self._measuring:
                self.stop()
        except (SensorError, OSError):
            pass
        finally:
            self._closed = True
            if self.int_line is not None and hasattr(self.int_line, "close"):
                self.int_line.close()
            if self._owns_bus:
                self.bus.close()


__all__ = ["TMF8820Source", "GpiodIntLine"]
