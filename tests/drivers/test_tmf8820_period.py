"""The measurement period the TMF8820 driver keeps (place_safe.drivers.tmf8820.period): fitted to the
read-out, lengthened on an overwrite, shortened when safe, with no overwrite storm and a period that
converges. The plant below is a queue in simulated milliseconds (no wall-clock timing): each measurement's
read-out adds to a backlog that the period drains, and a backlog above one packet transfer overwrites."""

from __future__ import annotations

import math
import random

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.drivers.tmf8820 import bench
from place_safe.drivers.tmf8820.emulated import EmulatedTMF8820
from place_safe.drivers.tmf8820.period import INTERVALS, RELAX_FRAMES, PeriodFit, need_ms


def _simulate(fit: PeriodFit, frames: int, readout_ms: float, model_err: int, *, noise_ms: float = 0.0,
              stall_p: float = 0.0, backlog_ms: float = 3.0, guess_err: int = 0, seed: int = 0) -> dict:
    """Run ``fit`` against a chip whose read-out takes ``readout_ms`` (plus noise and host stalls) while the
    driver's model says ``ceil(readout_ms) + model_err``, from a first guess ``guess_err`` ms off, until
    ``frames`` whole measurements arrived. Overwrites are counted from the first fit on (before it the guess
    is all the driver has)."""
    rng = random.Random(seed)
    true_need = math.ceil(readout_ms)

    def need() -> int:
        return max(1, true_need + model_err)

    fit.guess(max(1, true_need + guess_err))

    backlog, delivered, overwrites, stalls = 0.0, 0, [], 0
    periods = []
    while delivered < frames:
        t = readout_ms + (rng.gauss(0.0, noise_ms) if noise_ms else 0.0)
        if stall_p and rng.random() < stall_p:
            stalls += 1
            t += rng.uniform(backlog_ms, 3 * backlog_ms)
        backlog = max(0.0, backlog + t - fit.period_ms)
        if backlog > backlog_ms:
            if fit.fitted:
                overwrites.append(delivered)
            backlog = 0.0
            fit.overwritten(need)
        else:
            delivered += 1
            fit.frame(need)
        periods.append(fit.period_ms)
    return {"overwrites": overwrites, "stalls": stalls, "periods": periods, "need": true_need}


def _storm_bound(model_err: int) -> int:
    """Overwrites one wrong model costs in a row: the doubling steps that climb out of its deficit, plus one."""
    return math.ceil(math.log2(abs(model_err) + 1)) + 2


@settings(max_examples=200, deadline=None)
@given(readout=st.floats(20.0, 300.0), err=st.integers(-4, 4), frames=st.integers(50, 3000),
       floor=st.integers(0, 120), guess=st.integers(-5, 5))
def test_a_steady_chip_gets_few_overwrites_and_a_period_that_settles(readout, err, frames, floor, guess):
    fit = PeriodFit(floor)
    run = _simulate(fit, frames, readout, err, guess_err=guess)
    need, ow = run["need"], run["overwrites"]
    probes = math.log2(frames / RELAX_FRAMES + 1) + 2
    assert len(ow) <= probes * _storm_bound(err)  # failed probes are exponentially rare, each climb is short
    for k in range(len(ow)):  # no storm: within any RELAX_FRAMES frames only one climb out of a deficit
        assert sum(1 for x in ow[k:] if x < ow[k] + RELAX_FRAMES) <= _storm_bound(err)
    final = fit.period_ms
    assert final >= floor
    assert final <= max(floor, need + max(err, 0) + max(-err, 1))
    if err >= 0 or floor >= need:  # a model that is right (or pessimistic) never loses a measurement
        assert not ow
        assert final == max(floor, need + err)
    assert fit.changes <= 2 * len(ow) + probes + 1  # changes become rare too


@settings(max_examples=100, deadline=None)
@given(readout=st.floats(30.0, 120.0), noise=st.floats(0.0, 0.3), stall_p=st.sampled_from([0.0, 0.005, 0.02]),
       frames=st.integers(200, 2000), seed=st.integers(0, 10_000))
def test_noise_and_host_stalls_lengthen_only_for_a_while(readout, noise, stall_p, frames, seed):
    """With a model that covers the noise: overwrites come only from host stalls (and rare noise), and the
    period comes back down to the model's need once it has been safe for the wait."""
    fit = PeriodFit(0)
    spread = math.ceil(readout + 4 * noise) - math.ceil(readout)  # the ms a 4-sigma read-out spills over
    run = _simulate(fit, frames, readout, spread, noise_ms=noise, stall_p=stall_p, seed=seed)
    need = run["need"] + spread
    ow = run["overwrites"]
    assert len(ow) <= run["stalls"] + math.log2(frames / RELAX_FRAMES + 1) + 2 + frames / 500
    assert fit.period_ms >= need  # never below the model
    if not ow or frames - ow[-1] > fit.wait:  # back at the model's need once it was safe for a while
        assert fit.period_ms == need


@settings(max_examples=200, deadline=None)
@given(base=st.floats(0.5e-3, 5e-3), spread=st.floats(0.0, 0.2e-3), n=st.integers(8, 300),
       stalls=st.lists(st.floats(1.5e-3, 0.2), max_size=20), shift=st.floats(1e-6, 1e-3), seed=st.integers(0, 99))
def test_the_modelled_need_covers_31_intervals_ignores_stalls_and_grows_with_them(base, spread, n, stalls,
                                                                                  shift, seed):
    rng = random.Random(seed)
    iv = [base + rng.uniform(0.0, spread) for _ in range(n)]
    xfer = [0.8 * base] * 10
    need = need_ms(iv, xfer)
    assert need is not None
    assert need >= math.ceil(INTERVALS * sum(iv) / n * 1000.0 - 1e-9)  # the whole read-out fits in the period
    assert need_ms([x + shift for x in iv], xfer) >= need  # longer packets never shorten it
    mixed = iv + [base + spread + x for x in stalls[:n // 4]]  # host stalls (1 ms above the rest): not read-out
    rng.shuffle(mixed)
    assert need_ms(mixed, xfer) == need
    assert need_ms(iv[:7], xfer) is None and need_ms(iv, []) is None


@pytest.mark.parametrize("hz, latency, int_line, period", [
    (400e3, 0.0, True, 99), (400e3, 50e-6, True, 101), (400e3, 200e-6, True, 105),
    (1e6, 0.0, True, 40), (1e6, 50e-6, True, 42), (1e6, 200e-6, True, 46),
    (400e3, 0.0, False, 102), (400e3, 200e-6, False, 107), (1e6, 50e-6, False, 42), (1e6, 200e-6, False, 47)])
def test_the_ceiling_arithmetic(hz, latency, int_line, period):
    top = bench.ceiling(hz, latency, int_line, measurement_s=0.041)
    assert top["period_ms"] == period
    assert top["fps"] == pytest.approx(1.0 / max(period / 1000.0, 0.041))
    assert top["fps"] <= top["bytes_fps"]


@pytest.mark.slow
@settings(max_examples=10, deadline=None)
@given(hz=st.sampled_from([400e3, 1e6]), lo=st.floats(0.0, 150e-6), width=st.floats(0.0, 100e-6),
       int_line=st.booleans(), floor=st.sampled_from([0, 33]), seed=st.integers(0, 99))
def test_over_the_emulator_the_period_converges_near_the_ceiling_without_overwrite_storms(
        hz, lo, width, int_line, floor, seed):
    """The driver streaming from the emulated chip with a publish latency anywhere in [lo, lo + width]: after
    its first fits, at most a few overwrites, and the period ends between the ceiling's at the shortest
    latency (no host sustains less) and one ms above the ceiling's at the longest."""
    hi = lo + width
    src = EmulatedTMF8820(bench.random_frames(32, seed) * 8, bus_hz=hz, int_line=int_line,
                          driver={"period_ms": floor}, emulator={"publish_latency_s": (lo, hi)})
    emu = src.emulator
    try:
        for _ in range(10):
            src.read(2.0)
        ow0, ch0 = emu.stats["overwritten"], src.driver.stats["period_changes"]
        for _ in range(150):
            src.read(2.0)
        assert emu.stats["overwritten"] - ow0 <= 2
        assert src.driver.stats["period_changes"] - ch0 <= 4
        period = src.driver.period_in_use_ms
        assert period >= max(floor, bench.ceiling(hz, lo, int_line)["period_ms"])
        assert period <= max(floor, bench.ceiling(hz, hi, int_line)["period_ms"] + 1)
    finally:
        src.close()
