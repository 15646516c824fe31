"""Live recovery: estimate planes from a frame source as frames arrive.

Concept
-------
Two threads and a bounded buffer. The producer (a background thread) reads the
:class:`~place_safe.io.source.FrameSource` and stamps each frame's arrival time (``time.monotonic``,
seconds); the consumer (the calling thread) takes frames from the buffer and runs the estimator.
When the buffer is full the OLDEST waiting frame is discarded and counted as dropped: a live
pipeline wants the newest frame, not a growing backlog. With ``queue_size=1`` the consumer always
works on the latest frame.

Latency is measured from arrival (when ``read`` returned) to the end of the estimate, so it includes
the time spent waiting in the buffer. Faults never stall the loop:

* a frame that cannot be used (unparseable entry, NaN/negative counts, missing reference) gives a
  no-plane :class:`~place_safe.recovery.estimator.PlaneEstimate` with a ``reason``;
* :class:`~place_safe.exceptions.SensorTimeout` from the source is counted and reading goes on, until
  ``max_timeouts`` timeouts in a row end the run;
* an unexpected exception inside the estimator becomes a no-plane estimate with the error as reason.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from place_safe.recovery.estimator import Estimator, PlaneEstimate
from place_safe.exceptions import SensorTimeout
from place_safe.sensor.frame import Frame
from place_safe.io.source import FrameSource


@dataclass
class StreamStats:
    """What happened during a live run. Times in seconds; ``latencies`` per estimated frame."""

    received: int = 0          # frames the source delivered
    estimated: int = 0         # frames the estimator processed (with or without a plane)
    dropped: int = 0           # frames discarded because the consumer was busy
    bad_frames: int = 0        # estimates without a plane because the frame was unusable
    no_plane: int = 0          # estimates without a plane (includes bad_frames)
    timeouts: int = 0          # SensorTimeout raised by the source
    elapsed: float = 0.0       # wall time of the run
    ended_by: str = ""         # "source ended", "max_frames", "timeouts", "stopped", "source error: ..."
    latencies: list[float] = field(default_factory=list)

    def _pct(self, q: float) -> float | None:
        return float(np.percentile(self.latencies, q)) if self.latencies else None

    @property
    def latency_median(self) -> float | None:
        return self._pct(50)

    @property
    def latency_p95(self) -> float | None:
        return self._pct(95)

    @property
    def latency_max(self) -> float | None:
        return float(max(self.latencies)) if self.latencies else None

    @property
    def fps(self) -> float:
        """Estimates per second of wall time."""
        return self.estimated / self.elapsed if self.elapsed > 0 else 0.0

    @property
    def input_fps(self) -> float:
        """Frames delivered by the source per second of wall time."""
        return self.received / self.elapsed if self.elapsed > 0 else 0.0

    def to_dict(self) -> dict:
        """JSON form; latencies in milliseconds."""
        def ms(v: float | None) -> float | None:
            return None if v is None else round(v * 1e3, 3)

        return {"received": self.received, "estimated": self.estimated, "dropped": self.dropped,
                "bad_frames": self.bad_frames, "no_plane": self.no_plane, "timeouts": self.timeouts,
                "elapsed_s": round(self.elapsed, 4), "fps": round(self.fps, 3),
                "input_fps": round(self.input_fps, 3), "latency_ms": {
                    "median": ms(self.latency_median), "p95": ms(self.latency_p95), "max": ms(self.latency_max)},
                "ended_by": self.ended_by}

    def summary(self) -> str:
        """A few human-readable lines."""
        def ms(v: float | None) -> str:
            return "n/a" if v is None else f"{v * 1e3:.1f} ms"

        return (f"frames: {self.received} received, {self.estimated} estimated, {self.dropped} dropped, "
                f"{self.no_plane} without a plane ({self.bad_frames} bad), {self.timeouts} timeouts\n"
                f"latency (arrival -> estimate): median {ms(self.latency_median)}, p95 {ms(self.latency_p95)}, "
                f"max {ms(self.latency_max)}\n"
                f"throughput: {self.fps:.1f} estimates/s (source {self.input_fps:.1f} frames/s) over "
                f"{self.elapsed:.2f} s; ended: {self.ended_by}")


#: Called for every estimate: (index of the frame in arrival order, frame, estimate, latency in s).
OnEstimate = Callable[[int, Frame, PlaneEstimate, float], None]


class _Buffer:
    """Bounded FIFO that discards the oldest item when full (thread-safe)."""

    def __init__(self, size: int) -> None:
        self.items: deque = deque()
        self.size = size
        self.cond = threading.Condition()
        self.closed = False
        self.dropped = 0

    def put(self, item) -> None:
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

    def get(self):
        """Next item, or None once the buffer is closed and empty."""
        with self.cond:
            while not self.items and not self.closed:
                self.cond.wait()
            return self.items.popleft() if self.items else None


def _unusable_reason(frame: Frame) -> str | None:
    reason = frame.extra.get("parse_error") if isinstance(frame.extra, dict) else None
    return str(reason) if reason else None


def run_live(source: FrameSource, estimator: Estimator, on_estimate: OnEstimate | None = None,
             max_frames: int | None = None, queue_size: int = 1, read_timeout: float = 1.0,
             max_timeouts: int = 5, stop: threading.Event | None = None) -> StreamStats:
    """Recover planes from ``source`` as frames arrive until it ends; returns the run's statistics.

    source: any frame source; it is not closed here.
    estimator: the recovery method (its ``estimate`` never raises for bad frames).
    on_estimate: callback per estimate (called in the calling thread, in arrival order).
    max_frames: stop after the source delivered this many frames.
    queue_size: frames that may wait for the estimator; older ones are dropped beyond that.
    read_timeout: seconds one ``source.read`` may block.
    max_timeouts: consecutive timeouts that end the run.
    stop: set it from another thread to end the run early.
    """
    if queue_size < 1:
        raise ValueError(f"queue_size must be >= 1, got {queue_size}")
    stats = StreamStats()
    buf = _Buffer(queue_size)
    stop = stop or threading.Event()
    producer_error: list[BaseException] = []

    def produce() -> None:
        in_a_row = 0
        try:
            while not stop.is_set():
                if max_frames is not None and stats.received >= max_frames:
                    stats.ended_by = "max_frames"
                    return
                try:
                    frame = source.read(read_timeout)
                except StopIteration:
                    stats.ended_by = "source ended"
                    return
                except SensorTimeout:
                    stats.timeouts += 1
                    in_a_row += 1
                    if in_a_row >= max_timeouts:
                        stats.ended_by = f"{in_a_row} timeouts in a row"
                        return
                    continue
                in_a_row = 0
                arrived = time.monotonic()
                buf.put((stats.received, frame, arrived))
                stats.received += 1
            stats.ended_by = "stopped"
        except BaseException as exc:  # a source failure ends the run; reported by the consumer
            producer_error.append(exc)
            stats.ended_by = f"source error: {exc}"
        finally:
            buf.close()

    t0 = time.monotonic()
    thread = threading.Thread(target=produce, name="place-safe-frame-source", daemon=True)
    thread.start()
    try:
        while True:
            item = buf.get()
            if item is None:
                break
            index, frame, arrived = item
            reason = _unusable_reason(frame)
            if reason is not None:
                est = PlaneEstimate(None, reason=reason)
            else:
                try:
                    est = estimator.estimate(frame)
                except Exception as exc:  # the loop must go on whatever one frame does
                    est = PlaneEstimate(None, reason=f"estimator failed: {type(exc).__name__}: {exc}")
            latency = time.monotonic() - arrived
            stats.estimated += 1
            stats.latencies.append(latency)
            if not est.ok:
                stats.no_plane += 1
                if reason is not None or _fails_validation(frame):
                    stats.bad_frames += 1
            if on_estimate is not None:
                on_estimate(index, frame, est, latency)
    finally:
        stop.set()
        thread.join(timeout=read_timeout + 1.0)
        stats.elapsed = time.monotonic() - t0
        stats.dropped = buf.dropped
    if producer_error:
        raise producer_error[0]
    return stats


def _fails_validation(frame: Frame) -> bool:
    try:
        frame.validate()
    except Exception:
        return True
    return False


__all__ = ["StreamStats", "run_live", "OnEstimate"]
