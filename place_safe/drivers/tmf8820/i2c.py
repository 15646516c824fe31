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

Bus traffic per measurement is kept near the protocol's minimum: after the host clears a packet's
interrupt the next packet is read at once (it is ready within microseconds), checking its transaction id
to notice a packet that was not ready yet; only the first packet of a measurement is waited for, on the
interrupt line (``int_line``, e.g. :class:`GpiodIntLine`) or by polling ENABLE and INT_STATUS.

Time: ``Frame.timestamp`` is the measurement's completion on the host ``clock`` (default
``time.monotonic``; the simulation's clock when given, then ``clock_domain`` is ``"robot"``). It is
the sensor's system ticks (0.2 us) mapped to the host clock by the smallest offset "host time when the
first packet was seen minus tick time" over the last measurements (:mod:`.ticks`): a measurement
seen right when it finished fixes the offset, and the ticks carry it to the others.
``extra["tmf8820"]`` keeps the ticks, result number, temperature and the host detection time.

Faults: NAK / EIO / adapter timeouts (errno 121, 5, 110) are retried with a bounded exponential back-off;
a short read, a missing or out-of-order packet drops that measurement (never a half frame) and the next
result frame resynchronises; a device reset (ENABLE's wake-up bit cleared) re-initialises and resumes
the stream; a bus that keeps failing raises :class:`~place_safe.exceptions.SensorError`. ``stats`` counts
each under its name in :data:`~.registers.FAULT_KINDS` (the emulator injects the same kinds) plus
frames, dropped measurements, retries and re-initialisations.
"""

from __future__ import annotations

import errno
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from place_safe.drivers.tmf8820 import packets as P
from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.hexfile import RamPatch, load_patch
from place_safe.drivers.tmf8820.ticks import TickClock
from place_safe.exceptions import ConfigError, SensorError, SensorTimeout
from place_safe.io.source import FrameSource
from place_safe.sensor.frame import Frame

#: Re-initialisations after device resets without a whole measurement in between before giving up.
MAX_RECOVERIES = 5
_RETRY_ERRNOS = {R.ERRNO_NAK: "nak", R.ERRNO_EIO: "eio", R.ERRNO_TIMEOUT: "timeout", errno.EAGAIN: "timeout"}


class _ProtocolError(Exception):
    """The device answered something the protocol does not allow here (maybe it was reset)."""


class _ChecksumError(_ProtocolError):
    pass


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
            raise ConfigError("the interrupt line needs the 'gpiod' package (libgpiod v2 bindings)") from None
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
    period_ms, kilo_iterations: measurement period (ms) and pulses (thousands); short_range: the
        short-range high-accuracy mode (else long range).
    calibration_dir: where factory calibration files live (``tmf8820-<serial>.json``); loaded at start if present.
    int_line: object with ``wait(timeout) -> bool`` for the INT pin; None polls INT_STATUS.
    clock, sleep: host time (s) and sleep; clock_domain: what ``clock`` is (default "monotonic", or
        "robot" when a clock is given).
    retries, backoff_s: attempts per transfer and the first back-off (doubling). poll_s: poll interval.
    start: bring the sensor up and start measuring now (else at the first ``read``).
    """

    def __init__(self, bus: Any, address: int = R.DEFAULT_ADDRESS, *, patch: str | Path | RamPatch | None = None,
                 period_ms: int = 33, kilo_iterations: int = 4000, short_range: bool = True,
                 calibration_dir: str | Path | None = None, int_line: Any = None,
                 clock: Callable[[], float] | None = None, sleep: Callable[[float], None] | None = None,
                 clock_domain: str | None = None, retries: int = 6, backoff_s: float = 0.0005,
                 poll_s: float = 0.0005, start: bool = True) -> None:
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
        self.rate_hz = 1000.0 / period_ms if period_ms else 30.0
        self.calibration_dir = Path(calibration_dir) if calibration_dir is not None else None
        self.int_line = int_line
        self._clock = clock or time.monotonic
        self._sleep = sleep or time.sleep
        self.clock_domain = clock_domain or ("monotonic" if clock is None else "robot")
        self.retries, self.backoff_s, self.poll_s = max(1, retries), backoff_s, poll_s
        self.stats: dict[str, float] = {"frames": 0, "dropped_frames": 0, "retries": 0, "bad_packet": 0,
                                        "stale_reads": 0, "device_errors": 0, "reinit": 0, "decode_seconds": 0.0,
                                        **{k: 0 for k in R.FAULT_KINDS}}
        self.identity: dict[str, Any] = {}
        self._asm = P.MeasurementAssembler()
        self._ticks = TickClock()
        self._woken = False
        self._running = False
        self._closed = False
        self._expect_next = False
        self._last_tid: int | None = None
        self._first_seen: float | None = None
        self._recoveries = 0
        self._last_activity = self._clock()
        if start:
            try:
                self.start()
            except BaseException:
                if self._owns_bus:
                    self.bus.close()
                raise

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
        """Read ``n`` register bytes, re-reading short reads (harmless outside packet reads)."""
        for _ in range(self.retries):
            data = self._read_raw(reg, n)
            if len(data) == n:
                return data
            self.stats["short_read"] += 1
        raise SensorError(f"TMF8820 at 0x{self.address:02x}: {self.retries} short reads in a row")

    def _write(self, reg: int, data: bytes | list[int]) -> None:
        self._xfer(_msg().write(self.address, [reg, *data]))

    def _enable(self) -> int:
        """Read ENABLE; a cleared wake-up bit after we set it means the device was reset (counted)."""
        value = self._read(R.ENABLE, 1)[0]
        self._note_enable(value)
        return value

    def _note_enable(self, value: int) -> None:
        if self._woken and not value & R.ENABLE_WAKEUP:
            self._woken = False
            self.stats["reset"] += 1
            raise _ProtocolError("the sensor was reset")

    # -- bring-up ------------------------------------------------------------------------------------
    def _power_up(self) -> None:
        value = self._read(R.ENABLE, 1)[0]
        if not (self._woken and value & R.ENABLE_CPU_READY):
            self._write(R.ENABLE, [value | R.ENABLE_WAKEUP])
            self._woken = True
            self._sleep(0.010)
        deadline = self._clock() + 0.2
        while True:
            value = self._enable()  # the first read after wake-up may be stale: read until ready
            if value & R.ENABLE_CPU_READY:
                return
            if self._clock() > deadline:
                raise SensorError(f"TMF8820 at 0x{self.address:02x}: CPU not ready 200 ms after wake-up "
                                  f"(ENABLE 0x{value:02x})")
            self._sleep(0.001)

    def _bl(self, cmd: int, payload: bytes = b"", reply: int = 0) -> bytes:
        body = bytes([cmd, len(payload)]) + bytes(payload)
        self._write(R.CMD_STAT, body + bytes([R.bl_checksum(body)]))
        deadline = self._clock() + 0.05
        while True:
            r = self._read(R.CMD_STAT, 3 + reply)
            if r[0] != cmd:
                break
            if self._clock() > deadline:
                raise _ProtocolError(f"bootloader command 0x{cmd:02x} still busy after 50 ms")
            self._sleep(0.00005)
        n = r[1]
        if n != reply or r[2 + n] != R.bl_checksum(r[:2 + n]):
            raise _ChecksumError(f"bootloader reply to 0x{cmd:02x} has a bad checksum or length")
        if r[0] != R.BL_STATUS_OK:
            raise _ProtocolError(f"bootloader command 0x{cmd:02x} failed with status 0x{r[0]:02x}")
        return r[2:2 + n]

    def _download(self, patch: RamPatch) -> None:
        for addr, chunk in patch.chunks(R.BL_MAX_CHUNK):
            for _ in range(self.retries):
                try:
                    self._bl(R.BL_SET_ADDRESS, addr.to_bytes(2, "little"))
                    self._bl(R.BL_WRITE_RAM, chunk)
                    break
                except _ChecksumError:
                    self.stats["checksum"] += 1
            else:
                raise SensorError(f"TMF8820: RAM patch download failed at 0x{addr:04x} ({self.retries} bad replies)")

    def _start_app(self) -> None:
        appid = self._read(R.APPID, 1)[0]
        if appid == R.APP_BOOTLOADER:
            if self.patch is not None:
                self._download(self.patch)
                body = bytes([R.BL_START_RAM_APP, 0])
            else:
                body = bytes([R.BL_START_ROM_APP, 0])
            self._write(R.CMD_STAT, body + bytes([R.bl_checksum(body)]))
            deadline = self._clock() + 0.5
            while (appid := self._read(R.APPID, 1)[0]) != R.APP_MEASUREMENT:
                if self._clock() > deadline:
                    status = self._read(R.CMD_STAT, 1)[0]
                    if self.patch is not None and status not in (body[0], R.BL_STATUS_OK):
                        raise SensorError(f"TMF8820 rejected the RAM patch (bootloader status 0x{status:02x}); "
                                          "is it the TMF8820 application patch from ams?")
                    raise _ProtocolError(f"application did not start (APPID 0x{appid:02x})")
                self._enable()
                self._sleep(0.001)
        elif appid != R.APP_MEASUREMENT:
            raise _ProtocolError(f"unexpected APPID 0x{appid:02x} (expected 0x80 bootloader or 0x03 application)")

    def _command(self, cmd: int, timeout: float = 0.1, ok: tuple[int, ...] = (R.STAT_OK,)) -> None:
        self._write(R.CMD_STAT, [cmd])
        deadline = self._clock() + timeout
        while (status := self._read(R.CMD_STAT, 1)[0]) >= R.STAT_BUSY_MIN:
            if self._clock() > deadline:
                self._enable()
                raise _ProtocolError(f"command 0x{cmd:02x} not done after {timeout:g} s")
            self._sleep(min(0.0002, timeout / 20))
        if status not in ok:
            self._enable()
            raise _ProtocolError(f"command 0x{cmd:02x} failed with status 0x{status:02x}")

    def _load_page(self, cmd: int) -> bytearray:
        self._command(cmd)
        page = bytearray(self._read(R.PAGE, R.PAGE_END - R.PAGE))
        if page[0] != cmd:
            self._enable()
            raise _ProtocolError(f"page 0x{cmd:02x} did not load (page id 0x{page[0]:02x})")
        return page

    def _configure(self) -> None:
        self._command(R.CMD_SHORT_RANGE if self.short_range else R.CMD_LONG_RANGE)
        page = self._load_page(R.CMD_LOAD_CONFIG_COMMON)

        def put(reg: int, value: int, n: int = 1) -> None:
            page[reg - R.PAGE:reg - R.PAGE + n] = value.to_bytes(n, "little")

        put(R.CFG_PERIOD_MS, self.period_ms, 2)
        put(R.CFG_KILO_ITERATIONS, self.kilo_iterations, 2)
        put(R.CFG_SPAD_MAP_ID, R.SPAD_MAP_3X3)
        put(R.CFG_ALG_SETTING, page[R.CFG_ALG_SETTING - R.PAGE] | R.ALG_REPORT_DISTANCES)
        put(R.CFG_HISTOGRAM_DUMP, R.HIST_DUMP_RAW)
        first, last = R.CFG_PERIOD_MS, R.CFG_HISTOGRAM_DUMP + 1
        self._write(first, page[first - R.PAGE:last - R.PAGE])
        self._command(R.CMD_WRITE_CONFIG)
        cal = self.calibration_file()
        if cal is not None and cal.is_file():
            data = self._calibration_page(cal)
            self._load_page(R.CMD_LOAD_FACTORY_CALIBRATION)
            self._write(R.PAGE + R.HEADER_SIZE, data)
            self._command(R.CMD_WRITE_CONFIG)
            self.identity["calibration"] = str(cal)

    def _initialise(self) -> None:
        self._power_up()
        self._start_app()
        version = self._read(R.VERSION, 4)
        serial = int.from_bytes(self._read(R.SERIAL_NUMBER, 2), "little")
        mode = self._read(R.MODE, 1)[0]
        if mode != 0x00:
            raise SensorError(f"TMF8820 at 0x{self.address:02x} is in mode 0x{mode:02x}, expected 0x00 (3x3)")
        self.identity = {"address": f"0x{self.address:02x}", "app_version": ".".join(str(v) for v in version),
                         "serial": f"{serial:04x}", "application": "RAM patch" if self.patch else "ROM"}
        self._configure()
        self.identity["active_range"] = ("short (high accuracy)" if self._read(R.ACTIVE_RANGE, 1)[0] == R.CMD_SHORT_RANGE
                                         else "long")
        self._write(R.INT_ENAB, [R.INT_MEASUREMENT])
        self._write(R.INT_STATUS, [0xFF])

    def _bring_up(self) -> None:
        last: Exception | None = None
        for _ in range(4):
            try:
                self._initialise()
                return
            except _ProtocolError as exc:
                last = exc
                self.stats["reinit"] += 1
        raise SensorError(f"TMF8820 at 0x{self.address:02x} could not be initialised: {last}")

    def start(self) -> None:
        """Bring the sensor up (if needed) and start measuring."""
        if self._closed:
            raise SensorError("the TMF8820 source is closed")
        for _ in range(4):
            if not self._woken:
                self._bring_up()
            try:
                self._asm.discard()
                self._ticks.reset()
                self._expect_next = False
                self._last_tid = None
                self._command(R.CMD_MEASURE, ok=(R.STAT_ACCEPTED, R.STAT_OK))
                self._running = True
                self._last_activity = self._clock()
                return
            except _ProtocolError:
                self._woken = False
        raise SensorError(f"TMF8820 at 0x{self.address:02x} does not start measuring")

    def stop(self) -> None:
        """Stop measuring (the sensor stays configured)."""
        if self._running:
            self._running = False
            try:
                self._command(R.CMD_STOP)
                self._write(R.INT_STATUS, [R.INT_MEASUREMENT])
            except _ProtocolError:
                self._woken = False

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
        if not self._woken:
            self._bring_up()
        was_running = self._running
        self.stop()
        try:
            self._command(R.CMD_FACTORY_CALIBRATION, timeout=timeout)
            page = self._load_page(R.CMD_LOAD_FACTORY_CALIBRATION)
        except _ProtocolError as exc:
            raise SensorError(f"factory calibration failed: {exc}") from None
        path = self.calibration_file()
        assert path is not None
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"serial": self.identity["serial"], "app_version": self.identity["app_version"],
                                    "page": bytes(page[R.HEADER_SIZE:]).hex()}, indent=1) + "\n")
        if was_running:
            self.start()
        return path

    # -- streaming -----------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """Identity, versions, mode and configuration (brings the sensor up if needed)."""
        if not self._woken:
            self._bring_up()
        return {**self.identity, "mode": "3x3", "period_ms": self.period_ms,
                "kilo_iterations": self.kilo_iterations, "histograms": "raw", "clock_domain": self.clock_domain}

    def _wait_interrupt(self, deadline: float) -> bool:
        """Wait until a measurement interrupt is pending; False at the deadline. Detects resets."""
        silence = max(0.25, 4.0 / self.rate_hz)
        while True:
            now = self._clock()
            if self.int_line is not None:
                if self.int_line.wait(max(0.0, min(deadline - now, silence))):
                    return True
                if self._clock() - self._last_activity > silence:
                    self._enable()
                    self._last_activity = self._clock()
            else:
                enable, status = self._read(R.ENABLE, 2)
                self._note_enable(enable)
                if status & R.INT_ERROR:
                    self.stats["device_errors"] += 1
                    self._write(R.INT_STATUS, [R.INT_ERROR])
                if status & R.INT_MEASUREMENT:
                    return True
            if self._clock() >= deadline:
                return False
            self._sleep(self.poll_s if self.int_line is None else 0.0)

    def _recover(self) -> None:
        """After a reset: forget the measurement in progress (counting what it already showed), initialise
        again, measure again."""
        for reason in self._asm.abandon():
            self.stats[reason] += 1
        self._woken = False
        self.stats["reinit"] += 1
        self.start()

    def read(self, timeout: float = 1.0) -> Frame:
        """The next whole measurement; SensorTimeout if none within ``timeout`` s (on ``clock``)."""
        if self._closed:
            raise SensorError("the TMF8820 source is closed")
        if not self._running:
            self.start()
        deadline = self._clock() + max(timeout, 0.0)
        while True:
            try:
                frame = self._next_packet(deadline)
            except _ProtocolError as exc:
                self._recoveries += 1
                if self._recoveries > MAX_RECOVERIES:
                    raise SensorError(f"TMF8820 at 0x{self.address:02x} keeps resetting: {self._recoveries - 1} "
                                      f"re-initialisations without a whole measurement ({exc})") from None
                self._recover()
                continue
            if frame is not None:
                self._recoveries = 0
                return frame

    def _next_packet(self, deadline: float) -> Frame | None:
        """Read and handle one packet; a Frame when it closed a whole measurement."""
        buf = None
        if self._expect_next:
            self._expect_next = False
            buf = self._read_raw(R.PAGE, R.HIST_PACKET_SIZE)
            if len(buf) == R.HIST_PACKET_SIZE and buf[1] == self._last_tid:
                self.stats["stale_reads"] += 1
                buf = None
        if buf is None:
            if not self._wait_interrupt(deadline):
                raise SensorTimeout(f"no TMF8820 measurement within the timeout "
                                    f"({self._asm.started and 'measurement in progress' or 'waiting for one'})")
            seen = self._clock()
            buf = self._read_raw(R.PAGE, R.HIST_PACKET_SIZE)
            if not self._asm.started:
                self._first_seen = seen
        elif not self._asm.started:
            self._first_seen = self._clock()
        self._last_activity = self._clock()
        return self._handle(buf)

    def _handle(self, buf: bytes) -> Frame | None:
        cid = buf[0] if buf else None
        size = R.RESULT_SIZE if cid == R.CID_RESULT else R.HIST_PACKET_SIZE
        if len(buf) < max(R.HEADER_SIZE, size if cid in (R.CID_RESULT, R.CID_RAW_HISTOGRAM) else 0):
            self.stats["short_read"] += 1
            self._asm.mark("short_read")
            return None  # the interrupt stays pending: the packet is read again, whole, next time
        if len(buf) < R.HIST_PACKET_SIZE:  # fewer bytes than asked for, yet the whole packet (a result is shorter)
            self.stats["short_read"] += 1
        if cid == R.CID_RAW_HISTOGRAM:
            t0 = time.perf_counter()
            try:
                number, data = P.decode_histogram_packet(buf)
            except P.PacketError:
                self.stats["bad_packet"] += 1
                self._asm.mark("bad_packet")
            else:
                self._asm.add_histogram(number, data)
            self.stats["decode_seconds"] += time.perf_counter() - t0
            self._last_tid = buf[1]
            self._write(R.INT_STATUS, [R.INT_RAW_HISTOGRAM])
            self._expect_next = True
            return None
        if cid == R.CID_RESULT:
            self._last_tid = buf[1]
            self._write(R.INT_STATUS, [R.INT_RESULT])
            t0 = time.perf_counter()
            try:
                res = P.decode_result(buf)
            except P.PacketError:
                self.stats["bad_packet"] += 1
                self._asm.mark("bad_packet")
                res = P.Result()
            seen = self._first_seen if self._first_seen is not None else self._clock()
            self._first_seen = None
            frame = self._asm.add_result(res, host_seen=seen)
            self.stats["decode_seconds"] += time.perf_counter() - t0
            if frame is None:
                for reason in self._asm.drops:
                    if reason in ("missing_packet", "out_of_order"):
                        self.stats[reason] += 1
                self.stats["dropped_frames"] += 1
                return None
            frame.timestamp = self._ticks.stamp(res.sys_ticks, seen) if res.ticks_valid else seen
            self.stats["frames"] += 1
            return frame
        # neither a histogram nor a result: a reset device reads zeros; otherwise skip it
        self._enable()
        self.stats["bad_packet"] += 1
        self._asm.mark("bad_packet")
        self._write(R.INT_STATUS, [R.INT_MEASUREMENT])
        return None

    def close(self) -> None:
        if self._closed:
            return
        try:
            if self._running:
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
