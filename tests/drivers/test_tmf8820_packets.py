"""Property tests of the TMF8820 packet codec and measurement assembly (hypothesis)."""

from __future__ import annotations

import numpy as np
from hypothesis import example, given, settings
from hypothesis import strategies as st

from place_safe.drivers.tmf8820 import packets as P
from place_safe.drivers.tmf8820 import registers as R
from place_safe.drivers.tmf8820.ticks import TickClock
from place_safe.sensor.histogram import COUNT_MAX

u8 = st.integers(0, 0xFF)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 0xFFFFFFFF)
results = st.builds(
    P.Result, u8, st.integers(-128, 127), u8, u32, u32, u32, u32,
    st.lists(u8, min_size=18, max_size=18), st.lists(u16, min_size=18, max_size=18),
    st.lists(u8, min_size=18, max_size=18), st.lists(u16, min_size=18, max_size=18))
channels = st.builds(lambda seed: np.random.default_rng(seed).integers(0, COUNT_MAX + 1, (10, 128)),
                     st.integers(0, 2**32 - 1))


@given(results, u8)
def test_result_frames_round_trip(res, tid):
    buf = P.encode_result(res, tid)
    assert len(buf) == R.RESULT_SIZE
    assert P.decode_header(buf).tid == tid
    assert P.decode_result(buf) == res


@given(channels)
def test_histograms_round_trip_through_30_packets(ch):
    blocks = P.split_channels(ch)
    assert len(blocks) == R.HIST_PACKETS and all(len(b) == 128 for b in blocks)
    pkts = [P.encode_histogram_packet(k, b, k) for k, b in enumerate(blocks)]
    assert all(len(p) == R.HIST_PACKET_SIZE for p in pkts)
    decoded = [P.decode_histogram_packet(p) for p in pkts]
    assert [n for n, _ in decoded] == list(range(30))
    np.testing.assert_array_equal(P.join_channels([d for _, d in decoded]), ch)


@given(st.binary(max_size=300))
def test_decoders_reject_garbage_with_packet_errors_only(buf):
    for decode in (P.decode_result, P.decode_histogram_packet):
        try:
            decode(buf)
        except P.PacketError:
            pass


@given(st.binary(min_size=1, max_size=R.HIST_PACKET_SIZE - 1))
def test_a_cut_packet_never_decodes(prefix):
    ch = np.arange(1280).reshape(10, 128)
    whole = P.encode_histogram_packet(3, P.split_channels(ch)[3])
    cut = whole[:len(prefix)]
    try:
        P.decode_histogram_packet(cut)
    except P.PacketError:
        return
    raise AssertionError("a cut packet decoded")


@settings(max_examples=200, deadline=None)  # timing varies on a busy machine
@given(st.lists(st.integers(0, 29), max_size=40), st.booleans())
@example(numbers=list(range(30)) + [1, 0] + list(range(2, 30)), short=False)  # a lost result, then a swap
@example(numbers=[0, 1, 1, 0, 1] + list(range(2, 30)), short=False)  # a stray packet 1, then a whole measurement
def test_the_assembler_never_returns_a_half_frame(numbers, short):
    """Whatever packets arrive, a Frame comes out only for exactly packets 0..29 in order, whole, since the
    last packet that started a new measurement (a number the measurement already held, or a packet 0 after
    a packet numbered 2 or more: the device moved on; a packet 1 after a stray 1 and a 0 continues from that
    0), so never more than 30 packets are held."""
    blocks = P.split_channels(np.ones((10, 128)))
    asm = P.MeasurementAssembler()
    current: list[int] = []
    for n in numbers:
        dropped = asm.add_histogram(n, blocks[n])
        moved_on = n in current or (n == 0 and any(k > 1 for k in current))
        assert dropped == ("overwritten" if moved_on else None)
        stray = moved_on and n == 1 and current == [1, 0]  # a stray 1, then the next measurement's 0 and this 1
        if dropped:
            assert asm.drops == ["overwritten"] + (["out_of_order"] if not stray and any(
                b <= a for a, b in zip(current, current[1:])) else [])
        current = [0, 1] if stray else [n] if dropped else current + [n]
        assert asm.packets == len(current) <= 30 and len(asm._blocks) <= 30  # one measurement held, at most
    if short:
        asm.mark("short_read")
    frame = asm.add_result(P.Result())
    whole = current == list(range(30)) and not short
    assert (frame is not None) == whole
    if frame is None:
        # every fault of the measurement is reported (a short read first), each exactly once
        assert ("short_read" in asm.drops) == short and (not short or asm.drops[0] == "short_read")
        assert ("missing_packet" in asm.drops) == (len(set(current)) < 30)
        increasing = all(b > a for a, b in zip(current, current[1:]))
        assert ("out_of_order" in asm.drops) == (not increasing)
        assert len(asm.drops) == len(set(asm.drops)) and asm.last_drop == asm.drops[0]
    else:
        assert frame.hists.shape == (9, 128) and frame.reference.shape == (128,)
    assert not asm.started  # the result frame always closes the measurement


def test_packets_whose_sub_headers_disagree_are_one_broken_measurement():
    blocks = P.split_channels(np.ones((10, 128)))
    asm = P.MeasurementAssembler()
    for n in range(30):
        asm.add_histogram(n, blocks[n], tag=(128, 0x16 if n != 7 else 0x17))
    assert asm.add_result(P.Result()) is None and asm.drops == ["bad_packet"]


@given(st.lists(st.floats(0, 0.2), min_size=1, max_size=50), u32)
def test_tick_clock_stamps_completion_within_the_smallest_delay(delays, start):
    clock = TickClock()
    period = 0.1
    stamps, truth = [], []
    for k, delay in enumerate(delays):
        ticks = (start + int(k * period / R.TICK_SECONDS)) % (1 << 32)
        done = 1000.0 + k * period
        stamps.append(clock.stamp(ticks, done + delay))
        truth.append(done)
    err = np.array(stamps) - np.array(truth)
    assert np.all(err >= -1e-6)
    assert err[-1] <= min(delays) + 1e-6
