"""The sensor pipeline (place_safe.io.pipeline): its fault policy and frame gate, with scripted sources.

Behaviour only: no test asserts how long anything takes.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.exceptions import SensorError, SensorTimeout
from place_safe.geometry import Plane
from place_safe.io.live import run_live
from place_safe.io.pipeline import (PLACEMENT_POLICY, STREAM_POLICY, FaultPolicy, FrameGate, SensorPipeline,
                                    stamp_of)
from place_safe.recovery.estimator import PlaneEstimate
from place_safe.sensor.frame import Frame

#: A policy with no waiting to speak of, so that scripted faults run through at once.
QUICK = FaultPolicy(read_timeout=0.0, backoff_start=0.0, backoff_max=0.0)


def frame(stamp: float | None, **extra) -> Frame:
    return Frame(np.zeros((9, 128)), np.ones(128), timestamp=stamp, extra=dict(extra))


class Script:
    """A source that plays a script: a Frame is returned, an exception instance raised, the end is StopIteration."""

    clock_domain = "monotonic"

    def __init__(self, *steps) -> None:
        self.steps = list(steps)
        self.reads = 0

    def read(self, timeout: float = 1.0):
        self.reads += 1
        if not self.steps:
            raise StopIteration
        step = self.steps.pop(0)
        if isinstance(step, BaseException):
            raise step
        return step


class Polled(Script):
    clock_domain = "robot"


class Truth:
    """Returns a level plane at 0.2 m for every frame; counts its calls."""

    def __init__(self) -> None:
        self.calls = 0

    def estimate(self, frame):
        self.calls += 1
        return PlaneEstimate(Plane([0.0, 0.0, 1.0], 0.2))


def drain(pipe: SensorPipeline) -> list:
    out = []
    while (m := pipe.next()) is not None:
        out.append(m)
    return out


def test_policies_are_checked_and_the_two_consumers_limits_are_the_documented_ones():
    assert STREAM_POLICY.max_timeouts == 5 and STREAM_POLICY.max_errors == 1
    assert PLACEMENT_POLICY.max_timeouts is None and PLACEMENT_POLICY.max_errors is None
    for bad in ({"read_timeout": -1.0}, {"read_bound": math.nan}, {"max_timeouts": 0}, {"max_errors": True}):
        with pytest.raises(ValueError):
            FaultPolicy(**bad)
    with pytest.raises(ValueError):
        SensorPipeline(Script(), Truth(), queue_size=0)


def test_timeouts_in_a_row_end_the_pipeline_and_a_frame_resets_the_count():
    t = SensorTimeout("quiet")
    src = Script(t, t, frame(1.0), t, t, t, frame(2.0))
    pipe = SensorPipeline(src, Truth(), FaultPolicy(read_timeout=0.0, max_timeouts=3), estimate_on_reader=False,
                          queue_size=8)
    with pipe:
        got = drain(pipe)
    assert [m.frame.timestamp for m in got] == [1.0]  # the third timeout in a row ended it before frame 2
    assert pipe.timeouts == 5 and pipe.ended_by == "3 timeouts in a row" and pipe.failure is None


def test_source_errors_are_kept_retried_and_cleared_by_the_next_frame():
    boom = SensorError("bus fault")
    src = Script(boom, boom, boom, frame(1.0), boom)
    pipe = SensorPipeline(src, Truth(), QUICK, queue_size=8)  # the placement's limits: never ended by errors
    with pipe:
        got = drain(pipe)
    assert [m.frame.timestamp for m in got] == [1.0] and got[0].estimate.ok
    assert pipe.errors == 4 and pipe.ended_by == "source ended" and pipe.failure is None
    assert pipe.error == "SensorError: bus fault"  # the error after the last frame still stands


def test_max_errors_in_a_row_end_the_pipeline_with_the_failure():
    src = Script(frame(1.0), RuntimeError("first"), RuntimeError("second"), frame(2.0))
    pipe = SensorPipeline(src, Truth(), FaultPolicy(read_timeout=0.0, backoff_start=0.0, max_errors=2),
                          estimate_on_reader=False, queue_size=8)
    with pipe:
        got = drain(pipe)
    assert len(got) == 1 and str(pipe.failure) == "second" and pipe.ended_by == "source error: second"


def test_a_full_buffer_drops_the_oldest_frames():
    src = Script(*(frame(float(i)) for i in range(6)))
    pipe = SensorPipeline(src, Truth(), QUICK, estimate_on_reader=False, queue_size=2)
    pipe.start()
    pipe._thread.join(5.0)  # the reader has read everything before anyone takes a frame
    got = drain(pipe)
    pipe.stop()
    assert [m.frame.timestamp for m in got] == [4.0, 5.0] and [m.index for m in got] == [4, 5]
    assert pipe.frames == 6 and pipe.dropped == 4


def test_take_gives_the_newest_estimate_once():
    src = Script(frame(1.0), frame(2.0), frame(3.0))
    pipe = SensorPipeline(src, Truth(), QUICK, queue_size=4)
    pipe.start()
    pipe._thread.join(5.0)
    m = pipe.take()
    assert m.frame.timestamp == 3.0 and m.estimate.ok and pipe.take() is None
    assert pipe.overwritten == 2
    pipe.stop()


def test_unusable_frames_and_failing_estimators_become_no_plane_estimates():
    class Raises:
        def __init__(self, exc):
            self.exc = exc

        def estimate(self, frame):
            raise self.exc

    class Odd(BaseException):
        pass

    truth = Truth()
    pipe = SensorPipeline(Script(), truth)
    est = pipe.estimate(frame(1.0, parse_error="entry 3: 'hists' is not a 9x128 array"))
    assert est.plane is None and "hists" in est.reason and truth.calls == 0  # the estimator never saw it
    for exc in (RuntimeError("solver bug"), Odd("strange"), ValueError()):
        est = SensorPipeline(Script(), Raises(exc)).estimate(frame(1.0))
        assert est.plane is None and est.reason.startswith(f"estimator failed: {type(exc).__name__}")


def test_an_interrupt_on_the_main_thread_is_not_swallowed():
    class CtrlC:
        def estimate(self, frame):
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        SensorPipeline(Script(), CtrlC()).estimate(frame(1.0))


def test_polled_sources_are_read_on_take_with_the_same_rules():
    src = Polled(SensorTimeout("quiet"), SensorError("dead"), frame(1.0))
    pipe = SensorPipeline(src, Truth())
    assert not pipe.threaded
    assert pipe.take() is None and pipe.timeouts == 1 and pipe.error is None
    assert pipe.take() is None and pipe.errors == 1 and pipe.error == "SensorError: dead"
    m = pipe.take()
    assert m.estimate.ok and pipe.error is None
    assert pipe.take() is None and pipe.ended_by == "source ended" and pipe.take() is None
    pipe.stop()


def test_the_stream_does_not_estimate_repeated_frames():
    src = Script(frame(1.0), frame(1.0), frame(0.5), frame(2.0), frame(None))
    truth = Truth()
    seen = []
    stats = run_live(src, truth, lambda i, f, e, lat: seen.append(i), queue_size=8)
    assert stats.received == 5 and stats.repeated == 2 and stats.estimated == 3 == truth.calls
    assert seen == [0, 3, 4]  # an unstamped frame is shown: the stream has no clock to judge it by
    assert stats.to_dict()["repeated"] == 2 and stats.unstamped == 1


def test_the_stream_gates_frames_from_the_future_on_the_host_clock_only():
    import time

    ahead = time.monotonic() + 100.0  # stamped on this host's monotonic clock, 100 s from now
    stats = run_live(Script(frame(1.0), frame(ahead), frame(2.0)), Truth(), queue_size=8)
    assert stats.future == 1 and stats.estimated == 2 and stats.to_dict()["future"] == 1
    robot_clock = Script(frame(1.0), frame(ahead), frame(ahead + 1))
    robot_clock.clock_domain = "robot"  # another clock: nothing to compare the stamp with
    stats = run_live(robot_clock, Truth(), queue_size=8)
    assert stats.future == 0 and stats.estimated == 3


def test_a_repeated_stamp_after_an_unstamped_frame_is_still_repeated():
    stats = run_live(Script(frame(1.0), frame(None), frame(1.0)), Truth(), queue_size=8)
    assert stats.unstamped == 1 and stats.repeated == 1 and stats.estimated == 2


def test_a_source_error_ends_the_stream_and_is_raised_after_it_stopped():
    src = Script(frame(1.0), SensorError("bus fault"), frame(2.0))
    with pytest.raises(SensorError, match="bus fault"):
        run_live(src, Truth(), queue_size=8)
    assert len(src.steps) == 1  # nothing read after the error


def test_stop_from_another_thread_ends_a_stream_waiting_for_frames():
    class Silent(Script):
        def read(self, timeout=1.0):
            raise SensorTimeout("quiet")

    stop = threading.Event()
    stop.set()
    stats = run_live(Silent(), Truth(), stop=stop, read_timeout=0.0, max_timeouts=10**6)
    assert stats.ended_by == "stopped" and stats.estimated == 0


@settings(max_examples=200, deadline=None)
@given(st.lists(st.one_of(st.floats(-10.0, 10.0), st.just(math.nan), st.just(math.inf)), max_size=40),
       st.floats(0.01, 5.0), st.floats(0.0, 0.1))
def test_the_gate_lets_through_only_fresh_newer_frames(stamps, max_age, tolerance):
    """Whatever a source stamps, the frames the gate accepts are finite, strictly newer than every frame accepted
    before, not from the future and not older than max_age: a frozen, replaying or wrong-clocked sensor cannot
    pass as fresh evidence. A frame's age is ``now - stamp`` (the test once wrote it ``now - max_age <= stamp``, which
    rounds otherwise: stamp -2.2e-94 s at now 0.2 s is 0.2 s old to the last bit, within a max_age of 0.2 s)."""
    gate = FrameGate(max_age=max_age, future_tolerance=tolerance)
    now = 0.0
    accepted = []
    for s in stamps:
        now += 0.05
        if gate.check(s, now) is None:
            gate.accept(s)
            assert math.isfinite(s) and now - s <= max_age and s <= now + tolerance
            assert not accepted or s > accepted[-1]
            accepted.append(s)
        else:
            assert not accepted or s <= accepted[-1] or not math.isfinite(s) or not (
                now - s <= max_age and s <= now + tolerance)


def test_stamp_of_reads_any_frame_like_object():
    assert stamp_of(frame(1.5)) == 1.5 and math.isnan(stamp_of(frame(None))) and math.isnan(stamp_of(object()))
