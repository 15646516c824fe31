"""PlacementLoop failure policy as invariants (issue 30): hypothesis searches sources, estimators and robots that
raise any exception class (``BaseException`` subclasses included), return garbage or block for ever in ``read``,
on the robot's clock (polled with a bound) and on the host clock (reader thread), for a ``run`` that raises,
hangs or releases where the release rule does not hold.

Invariants checked on every example:

* ``run()`` returns a :class:`LoopResult` (no exception escapes), except a ``KeyboardInterrupt`` / ``SystemExit``
  raised on the control thread, which is re-raised *after* the safe stop (documented in PlacementLoop);
* the arm is not left moving, and a run that did not release still holds the cup;
* the gripper opens only with the cup within the release clearance of the surface (or in contact).
"""

from __future__ import annotations

import asyncio
import threading
import time

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from place_safe.exceptions import ArgumentTypeError
from place_safe.placement.loop import LoopResult, PlacementLoop
from place_safe.placement.machine import PlacementConfig

from placement_fakes import KinematicRobot, TruthEstimator, TruthSource

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning", "ignore::pytest.PytestUnhandledThreadExceptionWarning")

CFG = PlacementConfig(descent_timeout=6.0, retreat_timeout=3.0)
#: s of host time a blocked robot-clock read is waited for in these tests (the default is 2 s)
BOUND = 0.05


class CustomBase(BaseException):
    """A BaseException subclass a driver might define (not an Exception)."""


class BadStr(Exception):
    def __str__(self) -> str:
        raise RuntimeError("__str__ of the error raised too")


FAILURES = {
    "oserror": lambda: OSError(121, "Remote I/O error"),
    "runtime": lambda: RuntimeError("driver bug"),
    "type": lambda: TypeError("bad frame"),
    "custom-base": lambda: CustomBase("not an Exception"),
    "generator-exit": lambda: GeneratorExit(),
    "cancelled": lambda: asyncio.CancelledError(),
    "keyboard": lambda: KeyboardInterrupt(),
    "system-exit": lambda: SystemExit(3),
    "bad-str": lambda: BadStr(),
    "memory": lambda: MemoryError(),
    "recursion": lambda: RecursionError("deep"),
}
GARBAGE = [None, 5, "frame", object(), np.zeros(3), {"hists": 1}]


class FailingSource:
    """A TruthSource that, from its ``after``-th read on, fails in one of the ways ``mode`` names."""

    def __init__(self, robot: KinematicRobot, mode: str, after: int, host: bool, release: threading.Event,
                 garbage: object = None) -> None:
        self.inner = TruthSource(robot, clock=None if not host else (lambda: robot.t + 1000.0))
        self.clock_domain = self.inner.clock_domain
        self.mode, self.after, self.calls, self.release, self.garbage = mode, after, 0, release, garbage

    def read(self, timeout: float = 1.0):
        self.calls += 1
        if self.calls >= self.after:
            if self.mode == "block":
                self.release.wait()  # for ever, until the test ends
                raise OSError("released at the end of the test")
            if self.mode == "garbage":
                return self.garbage
            if self.mode in FAILURES:
                raise FAILURES[self.mode]()
        return self.inner.read(timeout)

    def close(self) -> None:
        pass


class FailingEstimator(TruthEstimator):
    def __init__(self, mode: str, after: int) -> None:
        super().__init__()
        self.mode, self.after, self.calls = mode, after, 0

    def estimate(self, frame):
        self.calls += 1
        if self.calls >= self.after:
            if self.mode == "garbage":
                return "not an estimate"
            raise FAILURES[self.mode]()
        return super().estimate(frame)


def _check_safe(robot: KinematicRobot, res: LoopResult | None) -> None:
    assert not robot.is_moving(), "the arm was left moving"
    if robot.opened:
        assert robot.opened_at is not None and robot.opened_at <= CFG.release_clearance + 1e-6, (
            f"released {robot.opened_at * 1e3:.1f} mm above the surface")
    if res is not None:
        assert isinstance(res, LoopResult) and res.reason
        if res.outcome != "released":
            assert not robot.opened


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mode=st.sampled_from([*FAILURES, "block", "garbage"]), after=st.integers(1, 300), host=st.booleans(),
       garbage=st.sampled_from(GARBAGE), height=st.floats(0.03, 0.08))
def test_a_failing_or_blocking_source_ends_in_a_safe_stop(mode, after, host, garbage, height):
    robot = KinematicRobot(height=height)
    release = threading.Event()
    source = FailingSource(robot, mode, after, host, release, garbage)
    loop = PlacementLoop(robot, source, TruthEstimator(), config=CFG, read_bound=BOUND)
    try:
        res = loop.run(timeout=15.0)
    finally:
        release.set()
    _check_safe(robot, res)
    if mode == "block" and not host and source.calls >= after and res.outcome != "released":
        assert loop.pipeline.blocked == 1  # waited once, then went on without the sensor
    if mode in FAILURES and source.calls >= after and res.outcome == "refused":
        assert res.reason


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mode=st.sampled_from([m for m in FAILURES if m not in ("keyboard", "system-exit")] + ["garbage"]),
       after=st.integers(1, 60), host=st.booleans())
def test_a_failing_estimator_never_escapes(mode, after, host):
    robot = KinematicRobot(height=0.08)
    source = TruthSource(robot, clock=None if not host else (lambda: robot.t + 1000.0))
    loop = PlacementLoop(robot, source, FailingEstimator(mode, after), config=CFG, read_bound=BOUND)
    res = loop.run(timeout=15.0)
    _check_safe(robot, res)


ROBOT_CALLS = ("step", "time", "tcp_pose", "contact_force", "fault", "speed_linear", "stop", "gripper")


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(method=st.sampled_from(ROBOT_CALLS), mode=st.sampled_from(list(FAILURES)), after=st.integers(1, 300))
def test_a_robot_raising_any_exception_class_is_stopped_and_only_interrupts_go_on(method, mode, after):
    robot = KinematicRobot(height=0.05)
    real = getattr(robot, method)
    calls = {"n": 0}

    def failing(*a, **kw):
        if threading.current_thread() is not threading.main_thread():
            return real(*a, **kw)  # a simulated sensor's own pose reads (the reader thread): the source's failures
        calls["n"] += 1            # are test_a_failing_or_blocking_source_ends_in_a_safe_stop's
        if calls["n"] == after:  # once, on the control thread: a stop after it must still work
            raise FAILURES[mode]()
        return real(*a, **kw)

    setattr(robot, method, failing)
    loop = PlacementLoop(robot, TruthSource(robot), TruthEstimator(), config=CFG, read_bound=BOUND)
    interrupt = mode in ("keyboard", "system-exit") and method not in ("stop",)
    try:
        res = loop.run(timeout=15.0)
    except (KeyboardInterrupt, SystemExit):
        assert calls["n"] >= after and mode in ("keyboard", "system-exit")
        assert loop.machine.finished and "interrupted" in (loop.machine.reason or "")
        _check_safe(robot, None)
        return
    _check_safe(robot, res)
    if interrupt and calls["n"] >= after and method != "stop":
        pytest.fail(f"{mode} from robot.{method} on the control thread was swallowed")


def test_a_keyboard_interrupt_from_the_robot_stops_it_then_goes_on():
    robot = KinematicRobot(height=0.08)
    real = robot.step
    n = {"k": 0}

    def step(dt):
        n["k"] += 1
        if n["k"] == 100:
            raise KeyboardInterrupt
        real(dt)

    robot.step = step
    loop = PlacementLoop(robot, TruthSource(robot), TruthEstimator(), config=CFG)
    with pytest.raises(KeyboardInterrupt):
        loop.run(timeout=15.0)
    assert robot.commands[-1] == "stop" and not robot.is_moving() and not robot.opened
    res = loop.result()
    assert res.final_phase == "aborted" and "interrupted: KeyboardInterrupt" in res.reason


def test_a_robot_clock_source_that_blocks_for_ever_is_a_dead_sensor_not_a_hang():
    robot = KinematicRobot(height=0.08)
    release = threading.Event()
    source = FailingSource(robot, "block", 1, host=False, release=release)
    try:
        res = PlacementLoop(robot, source, TruthEstimator(), config=CFG, read_bound=BOUND).run(timeout=15.0)
    finally:
        release.set()
    assert res.outcome == "refused" and not robot.opened
    assert "did not return from read()" in " ".join(t.reason for t in res.transitions)


@pytest.mark.parametrize("kwargs, match", [
    ({"config": "x"}, "config must be a PlacementConfig"),
    ({"config": {"accel": 1.0}}, "config must be a PlacementConfig"),
    ({"tool": "tool.json"}, "tool must be place_safe.robot.tool.ToolFrames"),
    ({"period": "0.008"}, "period must be a number"),
    ({"plane_filter": 3}, "plane_filter must be a PlaneFilter"),
    ({"host_clock": 5}, "host_clock must be a callable"),
])
def test_constructor_arguments_of_the_wrong_kind_say_what_was_expected(kwargs, match):
    robot = KinematicRobot()
    with pytest.raises(ArgumentTypeError, match=match):
        PlacementLoop(robot, TruthSource(robot), TruthEstimator(), **kwargs)


@pytest.mark.parametrize("robot, source, estimator, match", [
    ("robot", None, None, "robot must be a place_safe.robot.interface.Robot"),
    (None, "file:frames.json", None, "source must be a FrameSource"),
    (None, None, "peak", "estimator must have estimate"),
])
def test_robot_source_and_estimator_of_the_wrong_kind(robot, source, estimator, match):
    r = KinematicRobot()
    with pytest.raises(ArgumentTypeError, match=match):
        PlacementLoop(robot or r, source or TruthSource(r), estimator or TruthEstimator())


def test_out_of_range_numbers_are_value_errors():
    robot = KinematicRobot()
    for kw in ({"period": 0.0}, {"period": float("nan")}, {"max_frame_age": 1e9}, {"read_bound": -1.0}):
        with pytest.raises(ValueError):
            PlacementLoop(robot, TruthSource(robot), TruthEstimator(), **kw)
    loop = PlacementLoop(robot, TruthSource(robot), TruthEstimator())
    for t in (float("inf"), 0, -1, 1e9, "10", True):
        with pytest.raises(ValueError):
            loop.run(timeout=t)


class HugeStampSource(TruthSource):
    """A TruthSource whose frames, from the ``after``-th on, carry a time stamp no float can hold."""

    def __init__(self, robot: KinematicRobot, after: int) -> None:
        super().__init__(robot)
        self.after, self.calls = after, 0

    def read(self, timeout: float = 1.0):
        frame = super().read(timeout)
        self.calls += 1
        if frame is not None and self.calls >= self.after:
            frame.timestamp = 10 ** 400
        return frame


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(what=st.sampled_from(["time", "tcp_pose", "contact_force", "host_clock", "stamp"]), after=st.integers(1, 200))
def test_an_integer_beyond_any_float_is_a_bad_value_not_an_internal_error(what, after):
    """A robot, clock or frame that answers an int too large for a float (10**400) is refused, stopped and held with
    the value named, like NaN: it raised OverflowError inside the loop ("internal error: OverflowError")."""
    robot = KinematicRobot(height=0.05)
    calls = {"n": 0}

    def huge_after(real):
        def read(*a, **kw):
            calls["n"] += 1
            value = real(*a, **kw)
            if calls["n"] < after:
                return value
            if what == "tcp_pose":
                value = np.asarray(value, dtype=float).tolist()
                value[0][3] = 10 ** 400
                return value
            return 10 ** 400
        return read

    kw = {}
    source = HugeStampSource(robot, after) if what == "stamp" else TruthSource(robot)
    if what in ("time", "tcp_pose", "contact_force"):
        setattr(robot, what, huge_after(getattr(robot, what)))
    if what == "host_clock":
        kw["host_clock"] = huge_after(time.monotonic)
    loop = PlacementLoop(robot, source, TruthEstimator(), config=CFG, read_bound=BOUND, **kw)
    res = loop.run(timeout=15.0)
    _check_safe(robot, res)
    assert "internal error" not in res.reason, res.reason


HOST_CLOCK_FAILURES = {
    "nan": lambda n, t0: float("nan"), "none": lambda n, t0: None, "text": lambda n, t0: "12.5",
    "inf": lambda n, t0: float("inf"), "complex": lambda n, t0: 1j, "beyond a float": lambda n, t0: 10 ** 400,
    "back": lambda n, t0: t0 - n, "raises": None}


@settings(max_examples=16, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(kind=st.sampled_from(sorted(HOST_CLOCK_FAILURES)), after=st.integers(1, 300), host_stamps=st.booleans())
@example(kind="raises", after=8, host_stamps=False)  # the clock raising in the pipeline's polled read (found by it)
def test_a_failing_host_clock_ends_held_and_refused_naming_the_clock(kind, after, host_stamps):
    """The host clock times the sensor's frames (arrivals, the read bound, host-stamped frames). One that answers no
    finite number, steps back or raises ends the placement held and refused with the clock named: it was read as
    frames "unstamped", "stale" or "future" ("no surface plane within 1.5 s"), and as an internal error when it
    raised. Either kind of source: stamped on the robot's clock or on the host's."""
    robot = KinematicRobot(height=0.05)
    calls = {"n": 0}
    t0 = time.monotonic()

    def clock():
        calls["n"] += 1
        if calls["n"] < after:
            return robot.t + 1000.0
        if kind == "raises":
            raise RuntimeError("the clock is gone")
        return HOST_CLOCK_FAILURES[kind](calls["n"], t0)

    source = TruthSource(robot, clock=lambda: robot.t + 1000.0) if host_stamps else TruthSource(robot)
    loop = PlacementLoop(robot, source, TruthEstimator(), config=CFG, read_bound=BOUND, host_clock=clock)
    loop.start()
    t_end = time.monotonic() + 30.0
    while not loop.finished and time.monotonic() < t_end:
        loop.tick()
        time.sleep(0.0002 if host_stamps else 0.0)
    loop.pipeline.stop()
    res = loop.result()
    _check_safe(robot, res)
    if res.outcome != "released":  # (a clock that fails only after the release leaves the cup released)
        assert res.outcome == "refused" and not robot.opened
        assert "host clock failed" in res.reason and "internal error" not in res.reason, res.reason


def test_a_host_clock_that_keeps_time_changes_nothing():
    """The same check on a clock that only moves forward (or stands still for a tick) lets the placement release."""
    robot = KinematicRobot(height=0.05)
    ticks = {"n": 0}

    def clock():
        ticks["n"] += 1
        return robot.t + 1000.0 + (ticks["n"] // 2) * 1e-9  # equal readings in pairs: standing still is not back

    res = PlacementLoop(robot, TruthSource(robot), TruthEstimator(), config=CFG, read_bound=BOUND,
                        host_clock=clock).run(timeout=15.0)
    assert res.outcome == "released", res.reason


class Unreadable:
    """A fault report whose ``str`` fails."""

    def __str__(self) -> str:
        raise RuntimeError("str")


class GarbledEstimator(TruthEstimator):
    """A TruthEstimator whose estimates, from the first on, carry ``field = value`` (set on the estimate as returned)."""

    def __init__(self, field: str, value) -> None:
        super().__init__()
        self.field, self.value = field, value

    def estimate(self, frame):
        est = super().estimate(frame)
        if self.field == "covariance":
            cov = np.array(est.covariance, dtype=object)
            cov[2, 2] = self.value
            est.covariance = cov
        else:
            setattr(est, self.field, self.value)
        return est


@pytest.mark.parametrize("case", ["seconds-none", "seconds-huge", "seconds-text", "plane-text", "covariance-huge",
                                  "fault-array", "fault-unreadable"])
def test_values_an_estimator_or_robot_hands_back_are_never_an_internal_error(case):
    """Returned (not raised) garbage: an estimate whose ``seconds`` is None, 10**400 or text, whose plane is text, whose
    covariance holds 10**400; a robot whose ``fault()`` is an array or an object whose ``str`` fails. Each ended
    "internal error: ..." (the frame log's float(), plane.to_dict(), the offset's float(), ``bool(array)``): now the
    frame's plane is used or dropped, or the fault is said, and the run ends safe with a reason (an adversarial round)."""
    robot = KinematicRobot(height=0.05)
    estimator = TruthEstimator()
    field, _, what = case.partition("-")
    if field in ("seconds", "plane", "covariance"):
        value = {"none": None, "huge": 10 ** 400, "text": "1 ms"}[what]
        estimator = GarbledEstimator(field, "level" if field == "plane" else value)
    else:
        robot.fault = lambda: np.array([1, 2]) if what == "array" else Unreadable()
    loop = PlacementLoop(robot, TruthSource(robot), estimator, config=CFG, read_bound=BOUND, log_frames=True)
    res = loop.run(timeout=15.0)
    _check_safe(robot, res)
    assert "internal error" not in res.reason, res.reason
    if field == "fault":
        assert res.outcome != "released" and "robot fault: an unreadable fault report" in res.reason
    if field == "seconds":  # the plane itself is good: the placement goes on
        assert res.outcome == "released"


def test_a_pose_beyond_any_arms_reach_is_bad_robot_state_not_a_release():
    """A robot that reports its TCP 1e15 m away (a finite, rigid pose) while the cup hangs half over a table's edge: the
    surface map's floats lost the footprint there and the cup was released over the edge (an adversarial round). A pose
    farther than MAX_REACH from the base is now robot state that cannot be trusted: held, refused, said."""
    from place_safe.geometry import MAX_REACH

    robot = KinematicRobot(height=0.08)
    x_cup = float((robot.T @ robot.tool.tcp_T_cup)[0, 3])

    class TruePoseSource(TruthSource):  # the sensor measures from where the arm really is
        def _measure(self, t):
            reported, robot.tcp_pose = robot.tcp_pose, lambda: robot.T.copy()
            try:
                return super()._measure(t)
            finally:
                robot.tcp_pose = reported

    source = TruePoseSource(robot, hole=lambda x, y: x > x_cup - 0.02)

    def far():
        T = robot.T.copy()
        T[0, 3] += 1e15
        return T

    robot.tcp_pose = far
    res = PlacementLoop(robot, source, TruthEstimator(), config=CFG, read_bound=BOUND).run(timeout=15.0)
    _check_safe(robot, res)
    assert res.outcome != "released" and f"beyond any arm's reach (> {MAX_REACH:g} m)" in res.reason


def test_readings_beyond_any_touch_or_clock_are_said_in_a_short_line():
    """A force of 1e308 N was taken as a touch and printed with 300 digits; a frame 1e308 s old was "stale: frame
    measured 1000...0 s ago". Now the force is robot state that cannot be trusted, and both reasons are short."""
    from place_safe.io.pipeline import FrameGate
    from place_safe.placement.machine import MAX_FORCE_READING, RobotState

    T = np.eye(4)
    assert RobotState(0.0, T, T, contact_force=0.5 * MAX_FORCE_READING).problem() is None
    why = RobotState(0.0, T, T, contact_force=1e308).problem()
    assert why == f"robot contact force 1e+308 N is no reading of a touch (> {MAX_FORCE_READING:g} N)"
    stale = FrameGate(max_age=0.5).check(-1e308, 0.0)
    assert stale == "stale: frame measured 1e+308 s ago (> 0.50 s)"
    assert FrameGate(max_age=0.5).check(-0.75, 0.0) == "stale: frame measured 0.750 s ago (> 0.50 s)"



class PulledAway(TruthEstimator):
    """From 2 cm of cup clearance on, the table is gone (the robot's surface 0.3 m lower) and every frame says
    ``reason``: what a sensor sees with nothing beyond its cover glass."""

    def __init__(self, robot: KinematicRobot, reason: str) -> None:
        super().__init__()
        self.robot, self.reason, self.gone = robot, reason, False

    def estimate(self, frame):
        from place_safe.recovery.estimator import PlaneEstimate

        if self.gone or self.robot.cup_z() < 0.02:
            self.gone = True
            self.robot.surface_z = -0.30
            return PlaneEstimate(None, reason=self.reason)
        return super().estimate(frame)


@pytest.mark.parametrize("reason", ["too close: the return overlaps the internal return (the plane read lies 6.0 mm "
                                    "from the sensor, within the pulse's 14.8 mm of it)",
                                    "only 2 zone(s) show a return above the noise floor; a plane needs 3 or more"])
def test_frames_too_close_with_the_sensor_far_from_the_plane_do_not_hold_it(reason):
    """The fakes' sensor sits 7 cm above the cup's bottom: frames "too close" with the cup 2 cm up cannot be the
    table. The old plane was held on them and the cup released 0.3 m above the surface (a review, session 74); now
    the plane goes stale and the placement is refused, as for any frame without a plane."""
    robot = KinematicRobot(height=0.06)
    res = PlacementLoop(robot, TruthSource(robot), PulledAway(robot, reason), config=CFG, read_bound=BOUND).run(20.0)
    _check_safe(robot, res)
    assert res.outcome == "refused" and not robot.opened, res.reason


def test_a_sensor_stuck_on_one_measurement_is_refused_saying_the_frames_do_not_follow_the_arm():
    """A driver that re-reads a stale buffer and stamps it anew: the frames' plane moves with the arm, the fusion
    restarts on the run of outliers and the approach is refused for want of a plane, saying why (it said only "no
    surface plane": the twelfth bad-input round, session 82)."""
    import copy

    class Stuck(TruthSource):
        def __init__(self, robot, **kw):
            super().__init__(robot, **kw)
            self.held = None

        def read(self, timeout=1.0):
            f = super().read(timeout)
            if self.robot.t >= 0.3:
                self.held = self.held or f
                g = copy.copy(self.held)
                g.timestamp = f.timestamp
                return g
            return f

    robot = KinematicRobot(height=0.1)
    res = PlacementLoop(robot, Stuck(robot), TruthEstimator()).run(timeout=20.0)
    assert res.outcome == "refused" and robot.opened_at is None
    assert "restarted after" in res.reason and "stuck on one measurement" in res.reason
