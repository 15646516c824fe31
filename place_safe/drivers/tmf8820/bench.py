"""The TMF8820 bus benchmark: frame rate, bytes per frame and decode CPU of the driver over the emulator.

Figures (for one bus clock and one publish latency, the time the emulated chip takes after the host
cleared a packet's interrupt before the next packet is in the 0x20 window):

* ``fps``: whole frames per second of emulated time while streaming (after ``warmup`` frames), with the
  emulator's bus timing (:class:`~.emulator.BusTiming`) and device timing; ``fps_limit`` is the bus
  limit ``clock / (9 * 4182)`` of ``docs/tmf8820-protocol.md`` (payload bytes only) and ``of_limit``
  ``fps / fps_limit``. ``host_ceiling_fps``: the most any host could get from this chip,
  ``1 / (9 * 4368 / clock + 31 * latency)`` (the transfer minimum below, and each of the 31 packets
  waits the publish latency with the bus idle): above 188 us at 400 kHz and 76 us at 1 MHz it is below
  90 % of the limit. ``period_ms``: the measurement period the driver settled on (the chip measures once
  per period and overwrites a measurement the host has not read out in time, so the driver fits the
  period to its read-out, in whole milliseconds); ``bus_fps``: frames per second of bus time;
  ``device_fps``: ``1000 / period_ms``.
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


def run(bus_hz: float = 400e3, frames: int = 200, warmup: int = 5, fault_rate: float = 0.0, seed: int = 0,
        period_ms: int = 33, kilo_iterations: int = 4000, decode_frames: int = 300,
        progress: Any = None, publish_latency_s: float | tuple[float, float] = 50e-6) -> dict[str, Any]:
    """Stream ``frames`` frames through the emulator at ``bus_hz`` with the chip publishing each packet
    ``publish_latency_s`` (s, or a (low, high) range) after its release; the figures of the module docstring."""
    feed = random_frames(min(frames + warmup, 64), seed)

    def cycle():
        while True:
            yield from feed

    src = EmulatedTMF8820(cycle(), bus_hz=bus_hz, faults=FaultPlan(rate=fault_rate, seed=seed),
                          driver={"period_ms": period_ms, "kilo_iterations": kilo_iterations},
                          emulator={"publish_latency_s": publish_latency_s})
    emu = src.emulator
    try:
        for _ in range(warmup):
            src.read(5.0)
        t0, b0, d0, n0 = emu.clock(), emu.stats["bytes"], src.driver.stats["decode_seconds"], src.driver.stats["frames"]
        s0 = emu.stats["bus_seconds"]
        for _ in range(frames):
            src.read(5.0)
            if progress is not None:
                progress(1)
        elapsed = emu.clock() - t0
        moved = emu.stats["bytes"] - b0
        busy = emu.stats["bus_seconds"] - s0
        cycle = emu.cycle_seconds
        period_in_use = src.driver.period_in_use_ms
        stats = src.stats
    finally:
        src.close()
    done = stats["frames"] - n0
    lat = publish_latency_s if isinstance(publish_latency_s, (int, float)) else max(publish_latency_s)
    limit = bus_hz / (R.CLOCKS_PER_BYTE * R.MEASUREMENT_BYTES)
    return {"bus_hz": bus_hz, "publish_latency_s": publish_latency_s, "frames": done, "emulated_seconds": elapsed,
            "fps": done / elapsed, "of_limit": done / elapsed / limit,
            "host_ceiling_fps": 1.0 / (R.CLOCKS_PER_BYTE * TRANSFER_MIN_BYTES / bus_hz + (R.HIST_PACKETS + 1) * lat),
            "period_ms": period_in_use, "bus_fps": done / busy, "device_fps": 1.0 / cycle,
            "fps_limit": limit,
            "bytes_per_frame": moved / done, "payload_min": R.MEASUREMENT_BYTES, "transfer_min": TRANSFER_MIN_BYTES,
            "over_payload_min": moved / done / R.MEASUREMENT_BYTES - 1.0,
            "over_transfer_min": moved / done / TRANSFER_MIN_BYTES - 1.0,
            "decode_ms": decode_cpu(decode_frames, seed) * 1e3,
            "driver_decode_ms": (stats["decode_seconds"] - d0) / done * 1e3,
            "faults": {k: v for k, v in stats["injected"].items() if v}, "dropped_frames": stats["dropped_frames"]}


__all__ = ["run", "decode_cpu", "random_frames", "TRANSFER_MIN_BYTES"]
