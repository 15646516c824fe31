"""The sensor pipeline: frames from a :class:`~place_safe.io.source.FrameSource` to plane estimates, off the
caller's thread, with one fault policy. ``place-safe stream``, ``place-safe sensor stream`` (and its live view)
run it through :func:`place_safe.io.live.run_live`; :class:`~place_safe.placement.loop.PlacementLoop` takes its
newest estimate every control tick.

Threads
-------
A **reader thread** calls ``source.read(read_timeout)`` in a loop, stamps each frame's arrival on the host
clock (``clock``, default ``time.monotonic``, seconds) and puts it in a bounded buffer. When the buffer is full
the OLDEST waiting item is discarded and counted in ``dropped``: a live pipeline wants the newest frame, not a
backlog. Where the estimator runs is the consumer's choice:

* ``estimate_on_reader=False`` (the streams): the consumer takes frames with :meth:`SensorPipeline.next` and
  estimates them in its own thread with :meth:`SensorPipeline.estimate`; a slow estimator makes the buffer drop
  frames, never delays reading;
* ``estimate_on_reader=True`` (the placement loop): the reader estimates each frame before buffering it, and
  :meth:`SensorPipeline.take` hands the control thread the newest result without blocking: a 125 Hz tick never
  waits for I/O or for the solver.

A source on the robot's clock (the simulated sensor, ``clock_domain == "robot"``) advances only when the
simulation steps, so it is **polled** instead (``threaded=False``): each :meth:`~SensorPipeline.take` reads once
(``read(0)``) on a helper thread, waited for at most ``read_bound`` seconds, and estimates inline.

Fault policy
------------
The same rules for every consumer; only the limits are the consumer's (:class:`FaultPolicy`):

* **timeout** (:class:`~place_safe.exceptions.SensorTimeout`): counted in ``timeouts``; reading goes on at once.
  ``max_timeouts`` in a row end the pipeline (the streams: 5, a silent sensor ends the command; the placement
  loop: no limit, its frame-age rule refuses on a silent sensor by itself).
* **source error** (any other exception from ``read``, ``BaseException`` subclasses included): counted in
  ``errors``, its one-line description kept in ``error`` until a frame is estimated again; the reader waits a
  back-off (``backoff_start`` doubling to ``backoff_max``) while the error stands, then retries.
  ``max_errors`` in a row end the pipeline and the last of them is kept in ``failure`` (the streams: 1, the
  command reports it; the placement loop: no limit, it refuses while ``error`` is set: a dead sensor).
* **end** (``StopIteration``): the pipeline ends.
* **blocked read** of a polled source (longer than ``read_bound``): a dead sensor (``error``), never a hung
  caller; later takes return None at once until that read comes back.
* **unusable frame** (an entry the file reader could not parse: ``extra["parse_error"]``): a no-plane estimate
  with the reason, the estimator is not called; an **estimator that raises** (any exception class) gives a
  no-plane estimate "estimator failed: ...". An interrupt (Ctrl-C) on the main thread is always re-raised.
* **stale, repeated, future or unstamped frames**: judged by :class:`FrameGate` against the consumer's clock:
  the placement loop gates on the robot's clock (all four rules); the streams (:func:`place_safe.io.live.run_live`)
  drop repeated frames (a stamp not later than the previous frame's: a frozen sensor or a duplicate) and, on a
  source stamped with the host's monotonic clock, frames from the future, and count them; they set no age limit
  and count unstamped frames without dropping them.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from place_safe.exceptions import ArgumentTypeError, SensorTimeout
from place_safe.io.replay import parse_error
from place_safe.io.source import FrameSource
from place_safe.recovery.estimator import Estimator, PlaneEstimate

#: s (host clock): the longest a read of a polled (robot-clock) source may take before the pipeline goes on
#: without it (a simulated sensor answers in milliseconds; one that blocks is a dead sensor, not a reason to hang).
READ_BOUND = 2.0
#: Exceptions that are a request to stop the program (Ctrl-C, ``sys.exit``): raised on the main thread they are
#: re-raised after the caller's safe stop; raised by a source or an estimator on a reader thread they are that
#: part's failure like any other.
INTERRUPTS = (KeyboardInterrupt, SystemExit)


def describe_exception(exc: BaseException) -> str:
    """``Type: first line of the message`` of any exception, even one whose ``str`` raises."""
    try:
        text = str(exc).strip()
    except BaseException:  # noqa: BLE001 - a broken __str__ must not break the report of it
        text = ""
    name = type(exc).__name__
    return f"{name}: {text.splitlines()[0]}" if text else name


def is_interrupt_here(exc: BaseException) -> bool:
    """An interrupt raised on the main thread (a real Ctrl-C or exit request), to be re-raised after a safe stop."""
    return isinstance(exc, INTERRUPTS) and threading.current_thread() is threading.main_thread()


@dataclass(frozen=True)
class FaultPolicy:
    """The consumer's limits of the pipeline's fault rules (see the module docstring). Seconds; counts in a row."""

    read_timeout: float = 0.1  # s one source.read may block on the reader thread
    max_timeouts: int | None = None  # timeouts in a row that end the pipeline (None: never)
    max_errors: int | None = None  # source errors in a row that end the pipeline (None: retry for ever)
    backoff_start: float = 0.01  # s, the first wait after a source error
    backoff_max: float = 0.5  # s, the longest wait between retries
    read_bound: float = READ_BOUND  # s (host clock) a polled source's read may take

    def __post_init__(self) -> None:
        for key in ("read_timeout", "backoff_start", "backoff_max", "read_bound"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and v >= 0):
                raise ValueError(f"FaultPolicy: {key} must be a number of seconds >= 0, got {v!r}")
        for key in ("max_timeouts", "max_errors"):
            v = getattr(self, key)
            if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 1):
                raise ValueError(f"FaultPolicy: {key} must be None or a count >= 1, got {v!r}")


#: The streams' limits: a second per read, five silent reads in a row or one source error end the run.
STREAM_POLICY = FaultPolicy(read_timeout=1.0, max_timeouts=5, max_errors=1)
#: The placement loop's: short reads, never ended by the pipeline (the loop judges a silent or failing sensor).
PLACEMENT_POLICY = FaultPolicy()


@dataclass
class Measurement:
    """One frame and its plane estimate (None until estimated), with when it arrived (host clock, s) and its
    index in arrival order."""

    frame: Any
    estimate: Any
    arrived: float
    index: int = 0


class FrameGate:
    """Which frames count as new evidence: one rule for every consumer, on the consumer's clock (seconds).

    :meth:`check` gives the reason to drop a frame stamped ``stamp`` at time ``now`` (None: use it):
    ``unstamped`` (no finite stamp), ``future`` (later than ``now + future_tolerance``), ``stale`` (older than
    ``max_age``) and ``repeated`` (not later than the last stamp :meth:`accept` ed: a duplicate, a frozen sensor
    or frames out of order). ``now=None`` (no common clock) or a limit of None skips the rules that need it.
    """

    def __init__(self, max_age: float | None = None, future_tolerance: float | None = None) -> None:
        self.max_age = max_age
        self.future_tolerance = future_tolerance
        self.last_stamp = -math.inf

    def check(self, stamp: float, now: float | None = None) -> str | None:
        if not math.isfinite(stamp):
            return "unstamped: frame has no usable timestamp"
        if now is not None and self.future_tolerance is not None and stamp > now + self.future_tolerance:
            return f"future: frame stamped {_seconds(stamp - now)} s after the robot's clock"
        if now is not None and self.max_age is not None and now - stamp > self.max_age:
            return f"stale: frame measured {_seconds(now - stamp)} s ago (> {self.max_age:.2f} s)"
        if stamp <= self.last_stamp:
            return "repeated: frame not newer than the last one used (duplicate or out of order)"
        return None

    def accept(self, stamp: float) -> None:
        self.last_stamp = stamp


def _seconds(x: float) -> str:
    """Seconds for a reason: to the millisecond, or in three figures where that would fill the line (a clock off by
    1e308 s)."""
    return f"{x:.3f}" if abs(x) < 1e6 else f"{x:.3g}"


def stamp_of(frame: Any) -> float:
    """A frame's ``timestamp`` as a float (NaN when it has none, it is not a number -- text, a bool, an int beyond any
    float -- or reading it fails)."""
    try:
        t = getattr(frame, "timestamp", None)
        if isinstance(t, (bool, str, bytes)):
            return math.nan
        return float(t)
    except Exception:
        return math.nan


class _Buffer:
    """Bounded FIFO that discards the oldest item when full (thread-safe)."""

    def __init__(self, size: int) -> None:
        self.items: deque = deque()
        self.size = size
        self.cond = threading.Condition()
        self.closed = False
        self.dropped = 0

    def put(self, item: Any) -> None:
        with self.cond:
            if len(self.items) >= self.size:
                self.items.popleft()
                self.dropped += 1
            self.items.append(item)
            self.cond.notify()

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()

    def get(self, block: bool = True) -> Any:
        """Next item; None when there is none (not blocking) or once the buffer is closed and empty."""
        with self.cond:
            while block and not self.items and not self.closed:
                self.cond.wait()
            return self.items.popleft() if self.items else None

    def newest(self) -> Any:
        """The newest item, discarding older ones (counted as dropped); None when empty. Never blocks."""
        with self.cond:
            if not self.items:
                return None
            self.dropped += len(self.items) - 1
            item = self.items[-1]
            self.items.clear()
            return item


def clock_domain_of(source: Any) -> str:
    """A source's ``clock_domain`` ("robot" or "monotonic", the default when it has none); any other value
    (or an attribute that raises) is an :class:`~place_safe.exceptions.ArgumentTypeError`."""
    try:
        domain = getattr(source, "clock_domain", "monotonic")
    except BaseException as exc:  # noqa: BLE001 - a property that raises is a broken source
        if isinstance(exc, INTERRUPTS):
            raise
        raise ArgumentTypeError(f"source.clock_domain raised {describe_exception(exc)}") from None
    if domain not in ("robot", "monotonic"):
        raise ArgumentTypeError(f"source.clock_domain must be 'robot' or 'monotonic', got {domain!r}")
    return domain


class SensorPipeline:
    """A frame source feeding an estimator (see the module docstring for the threads and the fault policy).

    source: the frame source (not closed here). estimator: ``estimate(frame) -> PlaneEstimate``.
    policy: the consumer's limits. threaded: None chooses by the source's clock domain (polled when "robot").
    estimate_on_reader: the reader thread estimates (:meth:`take`) instead of the consumer (:meth:`next`).
    queue_size: items that may wait in the buffer. max_frames: the reader stops after this many frames.
    clock: the host clock stamping arrivals (s).

    Counters (read them after :meth:`stop`): ``frames`` (delivered by the source), ``estimated``, ``dropped``
    (discarded from the full buffer or never taken), ``timeouts``, ``errors``, ``blocked`` (polled reads that
    did not return within ``read_bound``); ``error`` (the standing source error, one line), ``failure`` (the
    exception that ended the pipeline, if any) and ``ended_by`` (why the reader stopped).
    """

    def __init__(self, source: FrameSource, estimator: Estimator, policy: FaultPolicy = PLACEMENT_POLICY, *,
                 threaded: bool | None = None, estimate_on_reader: bool = True, queue_size: int = 1,
                 max_frames: int | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        if isinstance(queue_size, bool) or not isinstance(queue_size, int) or queue_size < 1:
            raise ValueError(f"queue_size must be >= 1, got {queue_size}")
        self.source, self.estimator, self.policy = source, estimator, policy
        self.threaded = (clock_domain_of(source) != "robot") if threaded is None else bool(threaded)
        self.estimate_on_reader = bool(estimate_on_reader)
        self.max_frames = max_frames
        self.clock = clock
        self.frames = self.estimated = self.timeouts = self.errors = self.blocked = 0
        self.error: str | None = None
        self.failure: BaseException | None = None
        self.ended_by = ""
        self._runs = {"timeouts": 0, "errors": 0}  # in a row
        self._buffer = _Buffer(queue_size)
        self._stop = threading.Event()
        self._ended = False
        self._thread: threading.Thread | None = None
        # polled sources: one read at a time on a helper thread
        self._worker: threading.Thread | None = None
        self._request = threading.Event()
        self._done = threading.Event()
        self._pending = False
        self._waiting_out = False
        self._polled: tuple[bool, Any] | None = None

    # -- compatibility names of the placement loop's counters ------------------------------------
    @property
    def read_timeout(self) -> float:
        return self.policy.read_timeout

    @property
    def read_bound(self) -> float:
        return self.policy.read_bound

    @property
    def dropped(self) -> int:
        return self._buffer.dropped

    overwritten = dropped  # results the loop never took

    @property
    def ended(self) -> bool:
        """The reader has stopped and nothing is left to take."""
        return (self._ended or self._stop.is_set()) and not self._buffer.items

    # -- lifecycle -----------------------------------------------------------------------------
    def start(self) -> "SensorPipeline":
        if self.threaded and self._thread is None:
            self._thread = threading.Thread(target=self._run, name="place-safe-sensor", daemon=True)
            self._thread.start()
        return self

    def request_stop(self) -> None:
        """Ask the reader to end (from any thread, without waiting); a blocked :meth:`next` returns what is left."""
        self._stop.set()
        self._request.set()  # wakes the polled helper so it can end
        self._buffer.close()

    def stop(self, join: float = 2.0) -> None:
        """End reading and wait up to ``join`` seconds for the reader (it finishes its current read: at most
        ``read_timeout`` later)."""
        self.request_stop()
        if self._thread is not None:
            self._thread.join(timeout=join)
            self._thread = None
        if self._worker is not None:
            self._worker.join(timeout=0.05 if self._pending else 1.0)  # a blocked read is left behind (daemon)
            self._worker = None

    def __enter__(self) -> "SensorPipeline":
        return self.start()

    def __exit__(self, *exc: Any) -> None:
        self.stop()

    # -- the fault policy ------------------------------------------------------------------------
    def _read(self, timeout: float) -> tuple[bool, Any]:
        """``(True, frame)`` or ``(False, None)`` after a timeout, the end or an error of ``source.read``.

        Never raises: every exception class is the source's failure -- except an interrupt on the main thread
        (Ctrl-C), which is re-raised."""
        try:
            return True, self.source.read(timeout)
        except SensorTimeout:
            self.timeouts += 1
            self._in_a_row("timeouts")
        except StopIteration:
            self._end("source ended")
        except BaseException as exc:  # a dead bus, a driver bug, a BaseException subclass: a failing sensor
            if is_interrupt_here(exc):
                raise
            self.errors += 1
            self.error = describe_exception(exc)
            if self._in_a_row("errors"):
                self.failure = exc
                self._end(f"source error: {exc}")
        return False, None

    def _in_a_row(self, kind: str) -> bool:
        """Count one more timeout or error in a row; True (and the pipeline ended) when the policy's limit is hit."""
        run = self._runs
        run[kind] += 1
        limit = self.policy.max_timeouts if kind == "timeouts" else self.policy.max_errors
        if limit is not None and run[kind] >= limit:
            if kind == "timeouts":
                self._end(f"{run[kind]} timeouts in a row")
            return True
        return False

    def _end(self, why: str) -> None:
        if not self._ended:
            self._ended = True
            self.ended_by = why

    def estimate(self, frame: Any) -> PlaneEstimate:
        """The frame's plane estimate; never raises (see the fault policy), except an interrupt on the main thread."""
        reason = parse_error(frame)
        if reason:
            est = PlaneEstimate(None, reason=str(reason))
        else:
            try:
                est = self.estimator.estimate(frame)
            except BaseException as exc:  # estimators never raise for bad data; a bug must not stop the caller
                if is_interrupt_here(exc):
                    raise
                est = PlaneEstimate(None, reason=f"estimator failed: {describe_exception(exc)}")
        self.estimated += 1
        self.error = None
        return est

    def _arrived(self, frame: Any) -> Measurement:
        self._runs = {"timeouts": 0, "errors": 0}
        m = Measurement(frame, None, self.clock(), self.frames)
        self.frames += 1
        return m

    # -- the reader thread -------------------------------------------------------------------------
    def _run(self) -> None:
        backoff = self.policy.backoff_start
        try:
            while not self._stop.is_set() and not self._ended:
                if self.max_frames is not None and self.frames >= self.max_frames:
                    self._end("max_frames")
                    break
                ok, frame = self._read(self.policy.read_timeout)
                if not ok:
                    if self.error is not None and not self._ended:
                        self._stop.wait(backoff)
                        backoff = min(backoff * 2, self.policy.backoff_max)
                    continue
                backoff = self.policy.backoff_start
                m = self._arrived(frame)
                if self.estimate_on_reader:
                    m.estimate = self.estimate(frame)
                    m.arrived = self.clock()  # the loop ages a result from when it was ready
                self._buffer.put(m)
            self._end("stopped")
        except BaseException as exc:  # noqa: BLE001 - a bug here ends the pipeline with the reason, never silently
            self.failure = exc
            self._end(f"source error: {exc}")
        finally:
            self._buffer.close()

    # -- consumers -------------------------------------------------------------------------------
    def next(self) -> Measurement | None:
        """The oldest waiting measurement (blocks until one arrives); None once the pipeline has ended."""
        return self._buffer.get(block=True)

    def take(self) -> Measurement | None:
        """The newest measurement not taken before, or None (never blocks). Polled sources: read and estimate
        one frame now (a read waited for at most ``read_bound``)."""
        if not self.threaded:
            return None if (self._ended or self._stop.is_set()) else self._bounded_read()
        return self._buffer.newest()

    # -- polled (robot-clock) sources ----------------------------------------------------------------
    def _serve(self) -> None:
        while True:
            self._request.wait()
            self._request.clear()
            if self._stop.is_set():
                return
            self._polled = self._read(0.0)
            self._done.set()

    def _bounded_read(self) -> Measurement | None:
        if self._worker is None:
            self._worker = threading.Thread(target=self._serve, name="place-safe-sensor-poll", daemon=True)
            self._worker.start()
        if not self._pending:
            self._done.clear()
            self._pending = True
            self._request.set()
        if not self._done.wait(0.0 if self._waiting_out else self.policy.read_bound):
            if not self._waiting_out:
                self._waiting_out = True
                self.blocked += 1
                self.errors += 1
                self.error = (f"source did not return from read() within {self.policy.read_bound:g} s "
                              "(blocked: treated as a dead sensor)")
            return None
        self._pending = self._waiting_out = False
        (ok, frame), self._polled = self._polled or (False, None), None
        if not ok:
            return None
        m = self._arrived(frame)
        m.estimate = self.estimate(frame)
        m.arrived = self.clock()
        return m


__all__ = ["SensorPipeline", "FaultPolicy", "FrameGate", "Measurement", "STREAM_POLICY", "PLACEMENT_POLICY",
           "READ_BOUND", "INTERRUPTS", "describe_exception", "is_interrupt_here", "clock_domain_of", "stamp_of"]
