"""What one TMF8820 measurement looks like on the wire, both ways: result frames, raw-histogram packets,
and their assembly into one :class:`~place_safe.sensor.frame.Frame`.

Conventions
-----------
* A measurement is 30 raw-histogram packets then one result frame (``docs/tmf8820-protocol.md``).
  Packet ``k`` carries byte plane ``k // 10`` (0 least significant) of channel ``k % 10``; channel 0
  is the reference histogram, channels 1..9 the zones 1..9. Bins are 24-bit counts.
* The result frame is the delimiter: a measurement is whatever histogram packets arrived since the
  previous result frame, or since a packet 0 that followed a packet 0 (the device overwrote the rest of
  the previous measurement). It becomes a Frame only if exactly the 30 packets arrived, in order, each
  whole, with the same sub-header; otherwise the measurement is dropped and the fault is reported (never
  a half frame). At most one measurement is held, whatever arrives.
* In the Frame, on-sensor distances are metres (the wire carries millimetres), confidences 0..255.
  ``extra["tmf8820"]`` keeps the result number, temperature (deg C), valid results, system ticks
  (units of 0.2 us) and the second objects.

The I2C driver and the Arduino bridge both build frames with :class:`MeasurementAssembler`, so the
two paths give identical frames for identical data. The encoders exist for the emulator and tests.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from place_safe.drivers.tmf8820 import registers as R
from place_safe.sensor.frame import Frame
from place_safe.sensor.histogram import COUNT_MAX
from place_safe.sensor.zones import N_BINS, N_ZONES

assert R.HIST_DATA_SIZE == N_BINS and R.HIST_CHANNELS == N_ZONES + 1

_HEADER = struct.Struct("<BBH")
_RESULT_FIXED = struct.Struct("<BbBBIIII")  # result number .. system ticks (20 bytes)
_RESULT_PAYLOAD = R.RESULT_SIZE - R.HEADER_SIZE  # 128
_HIST_PAYLOAD = R.HIST_PACKET_SIZE - R.HEADER_SIZE  # 131


class PacketError(ValueError):
    """A packet cannot be decoded (too short, wrong id or length)."""


@dataclass
class Header:
    cid: int
    tid: int
    length: int


def decode_header(buf: bytes) -> Header:
    if len(buf) < R.HEADER_SIZE:
        raise PacketError(f"packet of {len(buf)} bytes has no header")
    return Header(*_HEADER.unpack_from(buf, 0))


@dataclass
class Result:
    """A decoded result frame: the sensor's own distances (mm) and housekeeping."""

    result_number: int = 0
    temperature: int = 0          # deg C
    valid_results: int = 0
    ambient: int = 0
    photon_count: int = 0
    reference_photon_count: int = 0
    sys_ticks: int = 0            # units of 0.2 us, LSB set when valid
    confidence: list[int] = field(default_factory=lambda: [0] * R.RESULT_CHANNELS)
    distance_mm: list[int] = field(default_factory=lambda: [0] * R.RESULT_CHANNELS)
    confidence_2: list[int] = field(default_factory=lambda: [0] * R.RESULT_CHANNELS)
    distance_mm_2: list[int] = field(default_factory=lambda: [0] * R.RESULT_CHANNELS)

    @property
    def ticks_valid(self) -> bool:
        return bool(self.sys_ticks & 1)


def encode_result(res: Result, tid: int = 0) -> bytes:
    """The 132-byte result frame of ``res`` (header included)."""
    body = bytearray(_RESULT_FIXED.pack(res.result_number & 0xFF, res.temperature, res.valid_results, 0,
                                        res.ambient, res.photon_count, res.reference_photon_count, res.sys_ticks))
    for conf, dist in ((res.confidence, res.distance_mm), (res.confidence_2, res.distance_mm_2)):
        for c, d in zip(conf, dist):
            body += struct.pack("<BH", c, d)
    assert len(body) == _RESULT_PAYLOAD
    return _HEADER.pack(R.CID_RESULT, tid & 0xFF, _RESULT_PAYLOAD) + bytes(body)


def decode_result(buf: bytes) -> Result:
    """Decode a result frame; :class:`PacketError` if it is not a whole one."""
    h = decode_header(buf)
    if h.cid != R.CID_RESULT:
        raise PacketError(f"cid_rid 0x{h.cid:02x} is not a result frame")
    if h.length != _RESULT_PAYLOAD or len(buf) < R.RESULT_SIZE:
        raise PacketError(f"result frame of {len(buf)} bytes (payload length {h.length}), expected {R.RESULT_SIZE}")
    num, temp, valid, _, amb, ph, ref, ticks = _RESULT_FIXED.unpack_from(buf, R.HEADER_SIZE)
    pairs = np.frombuffer(bytes(buf[R.HEADER_SIZE + _RESULT_FIXED.size:R.RESULT_SIZE]),
                          dtype=np.dtype([("c", "u1"), ("d", "<u2")]))
    n = R.RESULT_CHANNELS
    return Result(num, temp, valid, amb, ph, ref, ticks, pairs["c"][:n].tolist(), pairs["d"][:n].tolist(),
                  pairs["c"][n:].tolist(), pairs["d"][n:].tolist())


def encode_histogram_packet(number: int, data: bytes, tid: int = 0, config_id: int = 0) -> bytes:
    """The 135-byte raw-histogram packet ``number`` (0..29) carrying the 128 bytes ``data``."""
    if len(data) != R.HIST_DATA_SIZE:
        raise PacketError(f"histogram packet data must be {R.HIST_DATA_SIZE} bytes, got {len(data)}")
    return (_HEADER.pack(R.CID_RAW_HISTOGRAM, tid & 0xFF, _HIST_PAYLOAD)
            + bytes([number, R.HIST_DATA_SIZE, config_id]) + bytes(data))


def decode_histogram_packet(buf: bytes) -> tuple[int, bytes]:
    """(packet number, 128 data bytes) of a raw-histogram packet; :class:`PacketError` if not a whole one."""
    h = decode_header(buf)
    if h.cid != R.CID_RAW_HISTOGRAM:
        raise PacketError(f"cid_rid 0x{h.cid:02x} is not a raw-histogram packet")
    if h.length != _HIST_PAYLOAD or len(buf) < R.HIST_PACKET_SIZE:
        raise PacketError(f"histogram packet of {len(buf)} bytes (payload length {h.length}), "
                          f"expected {R.HIST_PACKET_SIZE}")
    number = buf[R.HEADER_SIZE]
    if number >= R.HIST_PACKETS:
        raise PacketError(f"histogram packet number {number} is not 0..{R.HIST_PACKETS - 1}")
    start = R.HEADER_SIZE + R.HIST_SUBHEADER_SIZE
    return number, bytes(buf[start:start + R.HIST_DATA_SIZE])


def split_channels(channels: np.ndarray) -> list[bytes]:
    """(10, 128) counts -> the 30 packet data blocks (packet k: plane k // 10 of channel k % 10).

    Counts are rounded and clipped to the sensor's 24-bit range.
    """
    c = np.clip(np.rint(np.asarray(channels, dtype=float)), 0, COUNT_MAX).astype(np.uint32)
    if c.shape != (R.HIST_CHANNELS, R.HIST_DATA_SIZE):
        raise PacketError(f"channels have shape {c.shape}, expected ({R.HIST_CHANNELS}, {R.HIST_DATA_SIZE})")
    planes = [((c >> (8 * p)) & 0xFF).astype(np.uint8) for p in range(R.HIST_PLANES)]
    return [planes[k // R.HIST_CHANNELS][k % R.HIST_CHANNELS].tobytes() for k in range(R.HIST_PACKETS)]


def join_channels(blocks: list[bytes]) -> np.ndarray:
    """The 30 packet data blocks in packet order -> (10, 128) counts (int64)."""
    raw = np.frombuffer(b"".join(blocks), dtype=np.uint8)
    if raw.size != R.HIST_PACKETS * R.HIST_DATA_SIZE:
        raise PacketError(f"{raw.size} histogram bytes, expected {R.HIST_PACKETS * R.HIST_DATA_SIZE}")
    p = raw.reshape(R.HIST_PLANES, R.HIST_CHANNELS, R.HIST_DATA_SIZE).astype(np.int64)
    return p[0] | (p[1] << 8) | (p[2] << 16)


def result_from_frame(frame: Frame, result_number: int = 0, sys_ticks: int = 1, temperature: int = 25) -> Result:
    """The result frame a sensor would report for ``frame`` (distances rounded to mm; for the emulator)."""
    res = Result(result_number=result_number & 0xFF, temperature=temperature, sys_ticks=sys_ticks & 0xFFFFFFFF)
    if frame.distances is not None:
        mm = np.clip(np.rint(np.nan_to_num(np.asarray(frame.distances, dtype=float)) * 1000.0), 0, 0xFFFF)
        res.distance_mm[:N_ZONES] = [int(v) for v in mm]
    if frame.confidences is not None:
        cf = np.clip(np.rint(np.nan_to_num(np.asarray(frame.confidences, dtype=float))), 0, 255)
        res.confidence[:N_ZONES] = [int(v) for v in cf]
    res.valid_results = sum(1 for c, d in zip(res.confidence[:N_ZONES], res.distance_mm[:N_ZONES]) if c and d)
    return res


def frame_channels(frame: Frame) -> np.ndarray:
    """(10, 128) channels of ``frame``: its reference (zeros when it has none) then its nine zones."""
    ref = np.zeros(N_BINS) if frame.reference is None else np.asarray(frame.reference, dtype=float)
    return np.vstack([np.nan_to_num(ref)[None], np.nan_to_num(np.asarray(frame.hists, dtype=float))])


def build_frame(channels: np.ndarray, res: Result, timestamp: float | None = None, **extra) -> Frame:
    """A Frame from assembled channels and its result frame (see module conventions)."""
    ch = np.asarray(channels, dtype=float)
    dist = np.asarray(res.distance_mm[:N_ZONES], dtype=float) / 1000.0
    conf = np.asarray(res.confidence[:N_ZONES], dtype=float)
    info = {"result_number": res.result_number, "temperature": res.temperature,
            "valid_results": res.valid_results, "sys_ticks": res.sys_ticks,
            "distances_2_mm": list(res.distance_mm_2[:N_ZONES]), "confidences_2": list(res.confidence_2[:N_ZONES])}
    info.update(extra)
    return Frame(ch[1:].copy(), ch[0].copy(), dist, conf, timestamp, extra={"tmf8820": info})


class MeasurementAssembler:
    """Collects the histogram packets of ONE measurement until a result frame closes it.

    Memory is bounded whatever arrives: at most one measurement is held (30 data blocks and a few
    counters), never a list that grows while the device misbehaves.

    ``add_histogram`` returns None, or the reason the measurement in progress was dropped when this packet
    started a new one. The chip sends each packet of a measurement once, so a packet whose number the
    measurement already holds, or a packet 0 arriving after any packet numbered 2 or more (a swap of
    neighbouring packets moves packet 0 behind packet 1 only), means the device moved on to its next
    measurement (``"overwritten"``: the host was too slow, or the rest, e.g. the result frame, was lost);
    this packet then starts the new measurement (which may begin with packet 1 when its first two were
    swapped; a packet 1 after packets 1, 0 keeps that 0 as the new measurement's first, the 1 before it a stray),
    and ``drops`` lists what the dropped one showed. So a measurement never holds a packet
    twice and at most 30 packets are ever counted (a 31st would drop it as ``"missing_packet"``: a guard).
    ``add_result`` returns a Frame, or None with
    ``drops`` saying why: the reason given to :meth:`mark` (e.g. ``"short_read"``, ``"bad_packet"``),
    else ``"missing_packet"`` if packets were missing and/or ``"out_of_order"`` if the packets that
    arrived did not come in increasing order; ``last_drop`` is the first of them.
    ``discard()`` forgets the current measurement without counting it. ``tag`` (e.g. the sub-header's
    payload size and config id) must be the same for every packet of a measurement, else it is marked
    ``"bad_packet"``.
    """

    def __init__(self) -> None:
        self._blocks: dict[int, bytes] = {}  # packet number -> data; each number at most once
        self._last: int | None = None
        self._disorder = False
        self._tag: object = None
        self._short: str | bool = False
        self.last_drop: str | None = None
        self.drops: list[str] = []

    @property
    def started(self) -> bool:
        return bool(self._blocks) or bool(self._short)

    @property
    def packets(self) -> int:
        """Histogram packets received for the current measurement."""
        return len(self._blocks)

    def discard(self) -> None:
        self._blocks, self._last, self._disorder, self._tag = {}, None, False, None
        self._short = False

    def abandon(self) -> list[str]:
        """Forget the measurement in progress (a device reset ended it) and return the faults it already
        showed: ``"out_of_order"`` if its packets so far were not strictly increasing. Faults it had not
        shown yet (a packet still to come, a gap) are lost with it."""
        disorder = self._disorder
        self.discard()
        return ["out_of_order"] if disorder else []

    def mark(self, reason: str) -> None:
        """Something of this measurement arrived broken (e.g. ``"short_read"``): it will be dropped."""
        if not self._short:
            self._short = reason

    def add_histogram(self, number: int, data: bytes, tag: object = None) -> str | None:
        dropped = None
        # the chip sends each packet of a measurement once: a number already held belongs to the next one
        moved_on = number in self._blocks or (number == 0 and any(k > 1 for k in self._blocks))
        # a packet 1 after packets 1, 0: not a swapped first pair, but a stray packet 1 (the rest of its measurement
        # overwritten) and then the next measurement's packet 0, which this 1 follows
        carry = moved_on and number == 1 and not self._short and self._last == 0 and set(self._blocks) == {0, 1}
        if moved_on or len(self._blocks) >= R.HIST_PACKETS:
            dropped = str(self._short) if self._short else "overwritten" if moved_on else "missing_packet"
            # what it showed: its reason, and disorder among the packets that came (not the ones that did not)
            self.drops = [dropped] + (["out_of_order"] if self._disorder and not carry else [])
            self.last_drop = dropped
            first, first_tag = self._blocks.get(0), self._tag
            self.discard()
            if carry:
                self._blocks, self._last, self._tag = {0: first}, 0, first_tag
        if self._blocks and tag != self._tag:
            self.mark("bad_packet")
        self._tag = tag
        if self._last is not None and number <= self._last:
            self._disorder = True
        self._last = number
        self._blocks[number] = data
        return dropped

    def add_result(self, res: Result, timestamp: float | None = None, **extra) -> Frame | None:
        """Close the measurement: the Frame if it is whole, else None with ``last_drop`` set."""
        blocks, short, disorder = self._blocks, self._short, self._disorder
        self.discard()
        self.drops = []
        if short:
            self.drops.append(str(short))
        # every fault of the measurement is reported, also when an earlier one already condemned it
        if len(blocks) < R.HIST_PACKETS:
            self.drops.append("missing_packet")
        if disorder:
            self.drops.append("out_of_order")
        self.last_drop = self.drops[0] if self.drops else None
        if self.drops:
            return None
        return build_frame(join_channels([blocks[k] for k in range(R.HIST_PACKETS)]), res, timestamp, **extra)


#: The reasons a dropped measurement is counted under in a source's ``stats`` (:func:`count_drops`); the others
#: (``short_read``, ``bad_packet``) are counted where the transfer failed.
PACKET_DROP_REASONS = ("missing_packet", "out_of_order", "overwritten")


def count_drops(stats: dict[str, int], reasons: list[str]) -> None:
    """A dropped measurement (``MeasurementAssembler.drops``): counted once in ``stats["dropped_frames"]`` and
    under each of its packet-level reasons (:data:`PACKET_DROP_REASONS`)."""
    for reason in reasons:
        if reason in PACKET_DROP_REASONS:
            stats[reason] += 1
    stats["dropped_frames"] += 1


__all__ = ["PacketError", "Header", "Result", "decode_header", "encode_result", "decode_result",
           "encode_histogram_packet", "decode_histogram_packet", "split_channels", "join_channels",
           "result_from_frame", "frame_channels", "build_frame", "MeasurementAssembler", "PACKET_DROP_REASONS",
           "count_drops"]
