"""The Arduino bridge: TMF8820 measurements as ``#Raw`` / ``#Obj`` text lines over USB serial or from a log.

Line format (``docs/tmf8820-protocol.md``)::

    #Raw,<i2c_address>,<packet_number>,<d0>,...,<d127>          131 fields, one per histogram packet
    #Obj,<i2c_address>,<result_number>,<temperature>,<valid_results>,<ticks>,<distance_mm>,<confidence>,...
                                                                 78 fields: 36 (distance, confidence) pairs

Pairs 0..17 are the first object per channel (0..8 = zones 1..9), 18..35 the second. A measurement is
30 ``#Raw`` lines and then one ``#Obj`` line; it is assembled by the same
:class:`~.packets.MeasurementAssembler` as the I2C path, so the frames are identical for identical
data. Other lines (``#Vers``, ``#Err,...``, status text) are counted in ``stats["other_lines"]``.
Malformed lines (bad numbers, values out of range, too many fields), partial lines (too few fields:
the line was cut) and interleaved lines (a second ``#`` record inside a line) are skipped and counted;
the measurement they belonged to is then incomplete and dropped (never a half frame).

Timestamps: the sensor's ticks mapped to the host clock (:mod:`.ticks`) from the time each
measurement's first line arrived (``clock``, default ``time.monotonic``).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from place_safe.drivers.tmf8820 import packets as P
from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.ticks import TickClock
from place_safe.exceptions import ConfigError, SensorError, SensorTimeout
from place_safe.io.source import FrameSource
from place_safe.sensor.frame import Frame
from place_safe.io.input_file import MAX_FRAME_FILE_BYTES, check_input_file

RAW_FIELDS = 3 + R.HIST_DATA_SIZE                  # 131
OBJ_FIELDS = 6 + 4 * R.RESULT_CHANNELS             # 78
#: Line faults counted in ``stats`` (besides "other_lines").
LINE_FAULTS = ("malformed_lines", "partial_lines", "interleaved_lines")


class LineError(ValueError):
    """A bridge line that cannot be used; ``kind`` is one of :data:`LINE_FAULTS`."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


@dataclass
class RawLine:
    address: int
    number: int
    data: bytes


@dataclass
class ObjLine:
    address: int
    result: P.Result


def _ints(fields: list[str], line_kind: str) -> list[int]:
    try:
        return [int(f) for f in fields]
    except ValueError:
        raise LineError("malformed_lines", f"{line_kind} line has a field that is not a whole number") from None


def parse_line(line: str) -> RawLine | ObjLine | None:
    """Decode one line: a RawLine, an ObjLine, None for other text; :class:`LineError` if unusable."""
    text = line.strip()
    if not text.startswith(("#Raw", "#Obj")):
        if "#Raw" in text or "#Obj" in text:
            raise LineError("interleaved_lines", "a #Raw/#Obj record starts inside another line")
        return None
    if text.find("#", 1) >= 0:
        raise LineError("interleaved_lines", "two records in one line")
    fields = text.split(",")
    kind, rest = fields[0], fields[1:]
    if rest and rest[-1] == "":
        rest = rest[:-1]  # a trailing comma
    want = (RAW_FIELDS if kind == "#Raw" else OBJ_FIELDS) - 1
    if kind not in ("#Raw", "#Obj"):
        raise LineError("malformed_lines", f"unknown record {kind!r}")
    if len(rest) < want:
        raise LineError("partial_lines", f"{kind} line has {len(rest) + 1} fields, expected {want + 1}")
    if len(rest) > want:
        raise LineError("malformed_lines", f"{kind} line has {len(rest) + 1} fields, expected {want + 1}")
    v = _ints(rest, kind)
    if not 0 <= v[0] <= 0x7F:
        raise LineError("malformed_lines", f"I2C address {v[0]} out of range")
    if kind == "#Raw":
        number, data = v[1], v[2:]
        if not 0 <= number < R.HIST_PACKETS or any(not 0 <= d <= 0xFF for d in data):
            raise LineError("malformed_lines", "#Raw packet number or byte out of range")
        return RawLine(v[0], number, bytes(data))
    num, temp, valid, ticks = v[1:5]
    pairs = v[5:]
    dist, conf = pairs[0::2], pairs[1::2]
    if not (0 <= num <= 0xFF and -128 <= temp <= 127 and 0 <= valid <= 0xFF and 0 <= ticks < 1 << 32) \
            or any(not 0 <= d <= 0xFFFF for d in dist) or any(not 0 <= c <= 0xFF for c in conf):
        raise LineError("malformed_lines", "#Obj value out of range")
    n = R.RESULT_CHANNELS
    res = P.Result(num, temp, valid, 0, 0, 0, ticks, conf[:n], dist[:n], conf[n:], dist[n:])
    return ObjLine(v[0], res)


def format_raw(address: int, number: int, data: bytes) -> str:
    """The ``#Raw`` line of one histogram packet (what the bridge prints)."""
    return "#Raw," + ",".join(str(x) for x in (address, number, *data))


def format_obj(address: int, res: P.Result) -> str:
    """The ``#Obj`` line of one result frame."""
    pairs = [x for d, c in zip(res.distance_mm + res.distance_mm_2, res.confidence + res.confidence_2) for x in (d, c)]
    return "#Obj," + ",".join(str(x) for x in (address, res.result_number, res.temperature, res.valid_results,
                                               res.sys_ticks, *pairs))


def format_measurement(address: int, blocks: list[bytes], res: P.Result) -> list[str]:
    """The 31 lines of one measurement (30 ``#Raw`` in packet order, then ``#Obj``)."""
    return [format_raw(address, k, b) for k, b in enumerate(blocks)] + [format_obj(address, res)]


class BridgeSource(FrameSource):
    """Frames from ``#Raw`` / ``#Obj`` lines (see module docstring).

    lines: ``readline(timeout) -> str | None`` (None: nothing within the timeout; "" at the end of input).
    address: only lines of this I2C address are used (default: the first address seen).
    """

    def __init__(self, readline: Callable[[float], str | None], address: int | None = None,
                 clock: Callable[[], float] = time.monotonic, name: str = "serial bridge",
                 closer: Callable[[], None] | None = None) -> None:
        self._readline = readline
        self.address = address
        self._clock = clock
        self.name = name
        self._closer = closer
        self._asm = P.MeasurementAssembler()
        self._ticks = TickClock()
        self._first_seen: float | None = None
        self.rate_hz = 4.5
        self.stats: dict[str, int] = {"frames": 0, "dropped_frames": 0, "lines": 0, "other_lines": 0,
                                      "other_address": 0, **{k: 0 for k in P.PACKET_DROP_REASONS},
                                      **{k: 0 for k in LINE_FAULTS}}

    @classmethod
    def open_serial(cls, port: str, baud: int = 115200, address: int | None = None, **kw: Any) -> "BridgeSource":
        """The Arduino on a serial port (pyserial)."""
        try:
            import serial
        except ImportError:
            raise ConfigError("the serial bridge needs pyserial (pip install 'place-safe[hw]')") from None
        try:
            port_ = serial.Serial(port, baud, timeout=0.05)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise SensorError(f"cannot open serial port {port}: {str(exc).splitlines()[0]}") from None

        pending = bytearray()

        def readline(timeout: float) -> str | None:
            port_.timeout = max(timeout, 0.001)
            raw = port_.readline()
            pending.extend(raw)
            if not pending.endswith(b"\n"):  # nothing, or a line still arriving: keep it for the next call
                return None
            line = pending.decode("ascii", errors="replace")
            pending.clear()
            return line

        return cls(readline, address, name=f"serial {port}", closer=port_.close, **kw)

    @classmethod
    def open_log(cls, path: str | Path, address: int | None = None, **kw: Any) -> "BridgeSource":
        """A recorded bridge log (text file, one line per record); the end of the file ends the source."""
        p = check_input_file(path, "bridge log", ConfigError, MAX_FRAME_FILE_BYTES)  # never a FIFO or a device
        try:
            fh = open(p, encoding="ascii", errors="replace", newline="")
        except OSError as exc:
            raise ConfigError(f"cannot open bridge log {p}: {exc.strerror}") from None
        return cls(lambda _t: fh.readline(), address, name=f"log {p.name}", closer=fh.close, **kw)

    @classmethod
    def from_lines(cls, lines: Iterable[str], address: int | None = None, **kw: Any) -> "BridgeSource":
        it: Iterator[str] = iter(lines)
        return cls(lambda _t: next(it, ""), address, name="lines", **kw)

    def read(self, timeout: float = 1.0) -> Frame:
        deadline = self._clock() + max(timeout, 0.0)
        while True:
            line = self._readline(max(0.0, deadline - self._clock()))
            if line == "":
                raise StopIteration
            if line is None:
                if self._clock() >= deadline:
                    raise SensorTimeout(f"no measurement from the {self.name} within {timeout:g} s")
                continue
            frame = self.feed(line)
            if frame is not None:
                return frame

    def feed(self, line: str) -> Frame | None:
        """Handle one line; the Frame when it completed a whole measurement."""
        if not line.strip():
            return None
        self.stats["lines"] += 1
        try:
            rec = parse_line(line)
        except LineError as exc:
            self.stats[exc.kind] += 1
            if self._asm.packets >= R.HIST_PACKETS:  # it was the #Obj line closing a measurement
                self._asm.discard()
                self.stats["dropped_frames"] += 1
            else:  # the measurement it belonged to is dropped at its #Obj line
                self._asm.mark(exc.kind)
            return None
        if rec is None:
            self.stats["other_lines"] += 1
            return None
        if self.address is None:
            self.address = rec.address
        if rec.address != self.address:
            self.stats["other_address"] += 1
            return None
        if not self._asm.started:
            self._first_seen = self._clock()
        if isinstance(rec, RawLine):
            if self._asm.add_histogram(rec.number, rec.data) is not None:  # a new measurement began: drop the last
                P.count_drops(self.stats, self._asm.drops)
                self._first_seen = self._clock()
            return None
        seen = self._first_seen if self._first_seen is not None else self._clock()
        self._first_seen = None
        frame = self._asm.add_result(rec.result)
        if frame is None:
            P.count_drops(self.stats, self._asm.drops)
            return None
        frame.timestamp = self._ticks.stamp(rec.result.sys_ticks, seen) if rec.result.ticks_valid else seen
        self.stats["frames"] += 1
        return frame

    def info(self) -> dict[str, Any]:
        return {"source": self.name, "address": None if self.address is None else f"0x{self.address:02x}",
                "clock_domain": self.clock_domain}

    def close(self) -> None:
        if self._closer is not None:
            self._closer()
            self._closer = None


__all__ = ["BridgeSource", "LineError", "RawLine", "ObjLine", "parse_line", "format_raw", "format_obj",
           "format_measurement", "LINE_FAULTS", "RAW_FIELDS", "OBJ_FIELDS"]
