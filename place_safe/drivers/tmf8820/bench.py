"""The TMF8820 bus benchmark: frame rate, bytes per frame and decode CPU of the driver over the emulator.

Figures (for one bus clock, one publish latency, the time the emulated chip takes after the host
cleared a packet's interrupt before the next packet is in the 0x20 window, and one way of waiting for a
packet: the INT line or polling INT_STATUS):

* ``fps``: whole frames per second of emulated time while streaming (after ``warmup`` frames), with the
  emulator's bus timing (:class:`~.emulator.BusTiming`) and device timing; ``fps_limit`` is the bus
  limit ``clock / (9 * 4182)`` of ``docs/tmf8820-protocol.md`` (payload bytes only) and ``of_limit``
  ``fps / fps_limit``. ``period_ms``: the measurement period the driver settled on (the chip measures
  once per period and overwrites a measurement the host has not read out in time, so the driver fits the
  period to its read-out, in whole milliseconds); ``bus_fps``: frames per second of bus time;
  ``device_fps``: ``1000 / period_ms``.
* ``host_ceiling_fps`` (:func:`ceiling`): the most any host that keeps the protocol's discipline can get
  from this chip, ``of_ceiling`` = ``fps / host_ceiling_fps``. The chip puts a packet in the window only
  after the host released the previous one by clearing its interrupt, plus the publish latency ``L``;
  the host may clear it only after reading (and checking) it. So the bus carries, per measurement, 31
  times: one combined write-register / read transaction and one interrupt clear (4368 bytes, 9 clocks a
  byte, plus 5 START / repeated START / STOP conditions a packet), then ``L`` of idle bus. A host that
  waits on the INT line needs nothing else; a polling host also needs one INT_STATUS poll a packet (4
  bytes, 39 clocks), of which the 19 clocks before its status byte is sampled can overlap the latency. A
  measurement whose read-out ran late delays the next one's packet 0 by one publish latency, so only a
  period of at least all 31 latencies drains a backlog. The period is whole milliseconds and at least
  the chip's own measurement time (4000 kilo-iterations: 41 ms in the emulator), so
  ``host_ceiling_fps = 1 / max(ceil_ms(9 * 4368 / clock + 155 / clock + 31 * idle), measurement time)``
  with ``idle = L`` (INT line) or ``max(L, 19 / clock) + 20 / clock`` (polling). ``bytes_ceiling_fps``
  is the looser ``1 / (9 * 4368 / clock + 31 * L)`` (bytes and latencies only): above 188 us at 400 kHz
  and 76 us at 1 MHz it is below 90 % of the limit, whatever the host.
* What no legal host discipline buys: clearing the interrupt in the same transaction as the data read
  saves one START/STOP a packet (31 clocks a measurement) but releases the packet before the host has
  checked it (a read cut by an open bus shows only as a 0xFF tail, and a second look after the release
  races the next packet); reading any part of the packet after the clear races the publication (a mix of
  old and new bytes), and nothing guarantees the latency; a chip that releases a packet once it is read
  (not when its interrupt is cleared) overlaps its latency with the host's clear, which the driver then
  gets for free.
* ``bytes_per_frame``: everything the driver moved on the bus per frame (address bytes, register
  bytes, interrupt clears, polls, payload), against two minimums: ``payload_min`` = 4182 (30 x 135 +
  132, the protocol doc's figure, which leaves out addressing) and ``transfer_min`` = 4182 + 31 x 6 =
  4368, the least any host can move: each of the 31 packets needs one combined transaction (device
  address + register, device address again: 3 bytes) and one interrupt clear (address, register,
  value: 3 bytes) before the device puts the next packet out.
* ``decode_ms``: host CPU (``time.process_time``) to turn one measurement's 31 packets into a Frame
  (packet decoding, 24-bit histogram assembly, Frame construction), averaged over ``decode_frames``.
"""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from place_safe.drivers.tmf8820 import packets as P
from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.emulated import EmulatedTMF8820
from place_safe.drivers.tmf8820.emulator import FaultPlan
from place_safe.sensor.frame import Frame
from place_safe.sensor.histogram import COUNT_MAX
from place_safe.sensor.zones import N_BINS, N_ZONES

#: Bytes per measurement a host cannot avoid (see module docstring).
TRANSFER_MIN_BYTES = R.MEASUREMENT_BYTES + (R.HIST_PACKETS + 1) * 6
_CONDITIONS_PER_PACKET = 5   # START, repeated START, STOP of the read; START, STOP of the clear (a clock each)
_POLL_CLOCKS = R.CLOCKS_PER_BYTE * 4 + 3  # an INT_STATUS poll: [address, register][address, status]
_POLL_SAMPLE_CLOCKS = R.CLOCKS_PER_BYTE * 2 + 1  # its status byte is sampled when its read message starts


def random_frames(n: int, seed: int = 0) -> list[Frame]:
    """``n`` frames of random 24-bit counts and on-sensor readings (a bit-exact test pattern)."""
    rng = np.random.default_rng(seed)
    return [Frame(rng.integers(0, COUNT_MAX + 1, (N_ZONES, N_BINS)).astype(float),
                  rng.integers(0, COUNT_MAX + 1, N_BINS).astype(float),
                  rng.integers(0, 0xFFFF, N_ZONES) / 1000.0, rng.integers(0, 256, N_ZONES).astype(float))
            for _ in range(n)]


def decode_cpu(frames: int = 300, seed: int = 0) -> float:
    """Host CPU seconds to decode one measurement from its 31 packets (mean over ``frames``)."""
    frame = random_frames(1, seed)[0]
    blocks = P.split_channels(P.frame_channels(frame))
    pkts = [P.encode_histogram_packet(k, b, k) for k, b in enumerate(blocks)]
    result = P.encode_result(P.result_from_frame(frame, 0, 1), 30)
    asm = P.MeasurementAssembler()
    t0 = time.process_time()
    for _ in range(frames):
        for p in pkts:
            asm.add_histogram(*P.decode_histogram_packet(p))
        out = asm.add_result(P.decode_result(result))
        assert out is not None
    return (time.process_time() - t0) / frames


def ceiling(bus_hz: float, latency_s: float, int_line: bool, measurement_s: float = 0.0) -> dict[str, float]:
    """The read-out time (s), whole-ms period and frame rate no host keeping the protocol's discipline can
    beat on a chip with publish latency ``latency_s`` (s) and measurement time ``measurement_s`` (s); and the
    looser bytes-and-latencies figure (see module docstring)."""
    clock = 1.0 / bus_hz
    packets = R.HIST_PACKETS + 1
    idle = latency_s if int_line else max(latency_s, _POLL_SAMPLE_CLOCKS * clock) + \
        (_POLL_CLOCKS - _POLL_SAMPLE_CLOCKS) * clock
    readout = (R.CLOCKS_PER_BYTE * TRANSFER_MIN_BYTES + _CONDITIONS_PER_PACKET * packets) * clock + packets * idle
    period_ms = math.ceil(readout * 1000.0 - 1e-9)
    return {"readout_s": readout, "period_ms": period_ms,
            "fps": 1.0 / max(period_ms / 1000.0, measurement_s),
            "bytes_fps": 1.0 / (R.CLOCKS_PER_BYTE * TRANSFER_MIN_BYTES * clock + packets * latency_s)}


def run(bus_hz: float = 400e3, frames: int = 200, warmup: int = 5, fault_rate: float = 0.0, seed: int = 0,
        period_ms: int = 33, kilo_iterations: int = 4000, decode_frames: int = 300,
        progress: Any = None, publish_latency_s: float | tuple[float, float] = 50e-6,
        int_line: bool = False) -> dict[str, Any]:
    """Stream ``frames`` frames through the emulator at ``bus_hz`` with the chip publishing each packet
    ``publish_latency_s`` (s, or a (low, high) range) after its release, the driver waiting on the INT line
    (``int_line``) or polling INT_STATUS; the figures of the module docstring."""
    feed = random_frames(min(frames + warmup, 64), seed)

    def cycle():
        while True:
            yield from feed

    src = EmulatedTMF8820(cycle(), bus_hz=bus_hz, faults=FaultPlan(rate=fault_rate, seed=seed),
                          driver={"period_ms": period_ms, "kilo_iterations": kilo_iterations},
                          emulator={"publish_latency_s": publish_latency_s}, int_line=int_line)
    emu = src.emulator
    try:
        for _ in range(warmup):
            src.read(5.0)
        t0, b0, d0, n0 = emu.clock(), emu.stats["bytes"], src.driver.stats["decode_seconds"], src.driver.stats["frames"]
        s0, o0, c0 = emu.stats["bus_seconds"], emu.stats["overwritten"], src.driver.stats["period_changes"]
        for _ in range(frames):
            src.read(5.0)
            if progress is not None:
                progress(1)
        elapsed = emu.clock() - t0
        moved = emu.stats["bytes"] - b0
        busy = emu.stats["bus_seconds"] - s0
        cycle = emu.cycle_seconds
        measurement_s = kilo_iterations * 1000.0 / emu.pulse_rate_hz + emu.processing_s
        period_in_use = src.driver.period_in_use_ms
        overwritten, changes = emu.stats["overwritten"] - o0, src.driver.stats["period_changes"] - c0
        stats = src.stats
    finally:
        src.close()
    done = stats["frames"] - n0
    lat = publish_latency_s if isinstance(publish_latency_s, (int, float)) else max(publish_latency_s)
    limit = bus_hz / (R.CLOCKS_PER_BYTE * R.MEASUREMENT_BYTES)
    top = ceiling(bus_hz, lat, int_line, measurement_s)
    return {"bus_hz": bus_hz, "publish_latency_s": publish_latency_s, "wait": "int" if int_line else "poll",
            "frames": done, "emulated_seconds": elapsed, "fps": done / elapsed, "of_limit": done / elapsed / limit,
            "host_ceiling_fps": top["fps"], "of_ceiling": done / elapsed / top["fps"],
            "ceiling_period_ms": top["period_ms"], "bytes_ceiling_fps": top["bytes_fps"],
            "period_ms": period_in_use, "overwritten": overwritten, "period_changes": changes,
            "bus_fps": done / busy, "device_fps": 1.0 / cycle,
            "fps_limit": limit,
            "bytes_per_frame": moved / done, "payload_min": R.MEASUREMENT_BYTES, "transfer_min": TRANSFER_MIN_BYTES,
            "over_payload_min": moved / done / R.MEASUREMENT_BYTES - 1.0,
            "over_transfer_min": moved / done / TRANSFER_MIN_BYTES - 1.0,
            "decode_ms": decode_cpu(decode_frames, seed) * 1e3,
            "driver_decode_ms": (stats["decode_seconds"] - d0) / done * 1e3,
            "faults": {k: v for k, v in stats["injected"].items() if v}, "dropped_frames": stats["dropped_frames"]}


__all__ = ["run", "ceiling", "decode_cpu", "random_frames", "TRANSFER_MIN_BYTES"]
