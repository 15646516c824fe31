"""The TMF8820 driver against a pessimistic chip (the emulator's simulated clock, no wall-clock timing):
publish latency, overwritten measurements, resets with or without the wake-up bit, 0xFF-filled and short
reads, NAK / EIO / adapter timeouts, reordered and missing packets, host CPU stalls, an interrupt that
stays asserted, packets that never complete. Whatever the device does: no frame that is not bit-exact
with what the emulator measured, every ``read`` ends within its timeout plus one transfer, at most one
measurement in assembly, and streaming resumes after each reset."""

from __future__ import annotations

import random

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from smbus2 import i2c_msg

from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.bench import random_frames
from place_safe.drivers.tmf8820.emulator import FAULT_KINDS, FaultPlan, TMF8820Emulator
from place_safe.drivers.tmf8820.i2c import TMF8820Source
from place_safe.exceptions import SensorError, SensorTimeout

FEED = random_frames(16, seed=11)


def _feed():
    while True:
        yield from FEED


class StallingBus:
    """The emulator behind a host that is sometimes descheduled: before a transfer, with probability
    ``p``, the host's clock jumps by up to ``stall_s`` (the device keeps measuring meanwhile)."""

    def __init__(self, emu: TMF8820Emulator, p: float, stall_s: float, seed: int) -> None:
        self.emu, self.p, self.stall_s, self.rng = emu, p, stall_s, random.Random(seed)
        self.stalled = 0.0  # seconds the host was away (a read cannot return while its host does not run)

    def i2c_rdwr(self, *msgs):
        if self.p and self.rng.random() < self.p:
            away = self.rng.uniform(0.0, self.stall_s)
            self.stalled += away
            self.emu.clock.sleep(away)
        return self.emu.i2c_rdwr(*msgs)


def _one_transfer(emu: TMF8820Emulator) -> float:
    """Longest a transfer the driver starts before its deadline can go on after it: an adapter timeout
    (stall) on a whole-page read, then the packet's interrupt clear and the 0xFF tail check."""
    return emu.stall_s + emu.timing.duration(R.PAGE_END - R.PAGE + 3, 2) + 2 * emu.timing.duration(12, 2)


def _truth(emu: TMF8820Emulator) -> dict:
    return {ticks: (ch, res) for ticks, ch, res in emu.presented}


def _assert_exact(emu: TMF8820Emulator, frame) -> None:
    ch, res = _truth(emu)[frame.extra["tmf8820"]["sys_ticks"]]
    np.testing.assert_array_equal(frame.hists, ch[1:])
    np.testing.assert_array_equal(frame.reference, ch[0])
    np.testing.assert_array_equal(frame.distances, np.asarray(res.distance_mm[:9]) / 1000.0)
    np.testing.assert_array_equal(frame.confidences, res.confidence[:9])


def _drive(emu: TMF8820Emulator, reads: int, timeout: float, *, stall_p: float = 0.0, int_line: bool = False,
           seed: int = 0, resets_at: tuple[float, ...] = ()) -> tuple[TMF8820Source, list, list]:
    """Read ``reads`` times; every frame checked bit-exact, every read's simulated duration checked.
    ``resets_at``: simulated times (s) at which the chip resets by itself (between two transfers)."""
    bus = StallingBus(emu, stall_p, 0.15, seed)
    pending = sorted(resets_at)
    original = bus.i2c_rdwr

    def with_resets(*msgs):
        while pending and emu.clock() >= pending[0]:
            pending.pop(0)
            if emu.awake:
                emu.stats["injected"]["reset"] += 1
                emu.reset()
        return original(*msgs)

    bus.i2c_rdwr = with_resets
    src = TMF8820Source(bus, clock=emu.clock, sleep=emu.clock.sleep, int_line=emu.int_line if int_line else None)
    frames, ends = [], []
    for _ in range(reads):
        t0, away = emu.clock(), bus.stalled
        try:
            f = src.read(timeout)
        except (SensorTimeout, SensorError) as exc:
            assert "\n" not in str(exc)
            ends.append(type(exc).__name__)
            if isinstance(exc, SensorError):
                break
        else:
            _assert_exact(emu, f)
            frames.append((emu.clock(), f))
            ends.append("frame")
        assert emu.clock() - t0 - (bus.stalled - away) <= timeout + _one_transfer(emu), "read past its timeout"
        assert src._asm.packets <= R.HIST_PACKETS and len(src._asm._blocks) <= R.HIST_PACKETS
    return src, frames, ends


CLASSES = {
    **{kind: {"faults": FaultPlan(rate=0.001 if kind == "reset" else 0.004, kinds=(kind,), seed=3)}
       for kind in FAULT_KINDS if kind != "checksum"},
    "reset_keeping_wake_bit": {"faults": FaultPlan(rate=0.001, kinds=("reset",), seed=4),
                               "emulator": {"reset_keeps_wake": 1.0}},
    "reset_losing_wake_bit": {"faults": FaultPlan(rate=0.001, kinds=("reset",), seed=4),
                              "emulator": {"reset_keeps_wake": 0.0}},
    "short_read_0xff_filled": {"faults": FaultPlan(rate=0.01, kinds=("short_read",), seed=5),
                               "emulator": {"short_fill": 1.0}},
    "publish_latency_200us": {"emulator": {"publish_latency_s": 200e-6}},
    "publish_latency_0_to_200us": {"emulator": {"publish_latency_s": (0.0, 200e-6)}},
    "host_cpu_stalls": {"stall_p": 0.003},
    "released_on_read_not_on_clear": {"emulator": {"release_on_read": True, "publish_latency_s": (0.0, 20e-6)}},
    "mixed": {"faults": FaultPlan(rate=0.005, seed=6), "emulator": {"publish_latency_s": (0.0, 200e-6)},
              "stall_p": 0.001},
}


@pytest.mark.parametrize("bus_hz", [400e3, 1e6])
@pytest.mark.parametrize("name", sorted(CLASSES))
def test_each_fault_class_alone_and_mixed(name, bus_hz):
    spec = CLASSES[name]
    emu = TMF8820Emulator(_feed(), bus_hz=bus_hz, record=True, faults=spec.get("faults"), **spec.get("emulator", {}))
    src, frames, ends = _drive(emu, 25, 1.0, stall_p=spec.get("stall_p", 0.0), seed=7)
    assert "SensorError" not in ends
    assert len(frames) >= 15, (ends, src.stats)
    resets = emu.stats["injected"]["reset"]
    assert src.stats["reset"] <= resets
    if resets:
        assert src.stats["reinit"] >= 1 and ends[-1] == "frame"  # streaming again after the resets


@pytest.mark.parametrize("keep_wake", [True, False])
def test_streaming_resumes_after_each_reset_with_calibration_restored(keep_wake, tmp_path):
    emu = TMF8820Emulator(_feed(), record=True, reset_keeps_wake=float(keep_wake))
    src = TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep, calibration_dir=tmp_path)
    src.factory_calibrate()
    page = bytes(emu.calibration)
    for _ in range(3):
        src.read(1.0)
    period = int.from_bytes(emu._cfg(R.CFG_PERIOD_MS, 2), "little")
    for k in range(3):
        emu.reset()
        assert not any(emu.calibration)
        t0 = emu.clock()
        f = src.read(1.0)  # detected, re-initialised and measuring again within one read
        _assert_exact(emu, f)
        assert emu.clock() - t0 < 0.5
        assert src.stats["reset"] == k + 1 and src.stats["reinit"] == k + 1
        assert bytes(emu.calibration) == page  # factory calibration restored
        assert int.from_bytes(emu._cfg(R.CFG_PERIOD_MS, 2), "little") == period  # and the config
        t1 = emu.clock()
        for _ in range(5):
            _assert_exact(emu, src.read(1.0))
        assert (emu.clock() - t1) / 5 <= period / 1000.0 * 1.01 + 1e-3  # back at the full rate


def test_a_fresh_start_is_not_a_reset():
    """The first ENABLE read after a change returns the old value (the emulator does it): no reset counted."""
    emu = TMF8820Emulator(_feed(), record=True)
    src = TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep)
    src.read(1.0)
    assert src.stats["reset"] == 0 and src.stats["reinit"] == 0
    again = TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep)  # a second session on a running chip
    _assert_exact(emu, again.read(1.0))
    assert again.stats["reset"] == 0 and again.stats["reinit"] == 0


def test_packets_that_never_complete_end_in_a_timeout_with_one_measurement_held():
    emu = TMF8820Emulator(_feed(), record=True)
    src = TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep)
    for _ in range(3):
        src.read(1.0)
    while src._asm.packets < 10:  # halfway through a measurement the firmware hangs (window kept, INT quiet)
        src._step(emu.clock() + 1.0)
    emu.measuring = False
    for _ in range(3):
        t0 = emu.clock()
        with pytest.raises(SensorTimeout):
            src.read(0.3)
        assert emu.clock() - t0 <= 0.3 + _one_transfer(emu)
        assert src._asm.packets <= R.HIST_PACKETS


def test_an_interrupt_stuck_on_with_nothing_new_in_the_window_ends_in_a_timeout():
    emu = TMF8820Emulator(_feed(), record=True)
    src = TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep)
    for _ in range(3):
        src.read(1.0)
    emu.measuring = False
    emu.regs[R.INT_STATUS] = R.INT_RAW_HISTOGRAM
    stuck = emu._clear_int
    emu._clear_int = lambda bits: None  # the bit never clears
    bytes_before = emu.stats["bytes"]
    t0 = emu.clock()
    with pytest.raises(SensorTimeout):
        src.read(0.2)
    assert emu.clock() - t0 <= 0.2 + _one_transfer(emu)
    # the old packet is not read whole again and again: short header reads tell it is not new
    assert src.stats["stale_reads"] <= 2
    assert (emu.stats["bytes"] - bytes_before) / 0.2 < 0.6 * emu.timing.clock_hz / 9
    emu._clear_int = stuck


def test_a_chip_that_keeps_resetting_ends_each_read_in_time():
    emu = TMF8820Emulator(_feed(), record=True, faults=FaultPlan(rate=0.05, kinds=("reset",), seed=1))
    _, frames, ends = _drive(emu, 12, 0.25)
    assert set(ends) <= {"frame", "SensorTimeout", "SensorError"}
    assert "SensorError" in ends or "SensorTimeout" in ends


def test_a_read_that_races_the_publication_gets_old_then_new_bytes():
    emu = TMF8820Emulator(_feed(), bus_hz=1e6, publish_latency_s=300e-6)
    TMF8820Source(emu, clock=emu.clock, sleep=emu.clock.sleep)
    assert emu.int_line.wait(1.0)

    def window() -> bytes:
        r = i2c_msg.read(R.DEFAULT_ADDRESS, R.HIST_PACKET_SIZE)
        emu.i2c_rdwr(i2c_msg.write(R.DEFAULT_ADDRESS, [R.PAGE]), r)
        return bytes(r)

    first = window()
    emu.i2c_rdwr(i2c_msg.write(R.DEFAULT_ADDRESS, [R.INT_STATUS, R.INT_RAW_HISTOGRAM]))
    raced = window()  # 1.2 ms long: the next packet appears 300 us into it
    assert emu.stats["racing_reads"] == 1
    assert raced[:R.HEADER_SIZE + 1] == first[:R.HEADER_SIZE + 1]  # the old header and packet number...
    assert emu.int_line.wait(0.0)
    assert raced[-40:] == window()[-40:] != first[-40:]  # ...then the new packet's bytes


@pytest.mark.slow
@settings(max_examples=25, deadline=None)
@given(bus_hz=st.sampled_from([400e3, 1e6]),
       latency=st.tuples(st.floats(0.0, 200e-6), st.floats(0.0, 200e-6)).map(sorted),
       events=st.lists(st.tuples(st.integers(100, 4000), st.sampled_from(FAULT_KINDS)), max_size=6),
       rate=st.sampled_from([0.0, 0.001, 0.01]),
       keep_wake=st.floats(0.0, 1.0), fill=st.floats(0.0, 1.0), stall_p=st.sampled_from([0.0, 0.002]),
       int_line=st.booleans(), overwrite=st.booleans(), timeout=st.sampled_from([0.05, 0.3, 1.0]),
       resets_at=st.lists(st.floats(0.05, 2.0), max_size=3), release_on_read=st.booleans(), seed=st.integers(0, 99))
def test_whatever_the_device_does_reads_end_in_time_and_frames_are_exact(
        bus_hz, latency, events, rate, keep_wake, fill, stall_p, int_line, overwrite, timeout, resets_at,
        release_on_read, seed):
    """Property: any mix of device behaviours; every read ends (frame, SensorTimeout or one-line
    SensorError) within its timeout plus one transfer of simulated time, every frame is bit-exact, the
    assembler never holds more than one measurement, and a device that stops misbehaving streams again."""
    emu = TMF8820Emulator(_feed(), bus_hz=bus_hz, record=True, publish_latency_s=tuple(latency),
                          faults=FaultPlan(events, rate=rate, seed=seed), reset_keeps_wake=keep_wake,
                          short_fill=fill, overwrite=overwrite, release_on_read=release_on_read)
    src, frames, ends = _drive(emu, 10, timeout, stall_p=stall_p, int_line=int_line, seed=seed,
                               resets_at=tuple(resets_at))
    if not release_on_read:  # clearing before the read would race the protocol's chip: never without proof
        assert not src._clear_first
    if "SensorError" not in ends and rate == 0.0:  # faults over: frames again within a second
        emu.faults.armed.clear()
        src.stats["reset"] = 0
        got = []
        for _ in range(2):
            try:
                got.append(src.read(1.0))
            except SensorTimeout:
                continue
        assert got, src.stats
        for f in got:
            _assert_exact(emu, f)
