"""Live recovery: estimate planes from a frame source as frames arrive (``place-safe stream``, ``place-safe sensor
stream`` and its live view).

:func:`run_live` is the consumer of a :class:`~place_safe.io.pipeline.SensorPipeline` (the one pipeline, with its
reader thread, bounded newest-first buffer and fault policy: see :mod:`place_safe.io.pipeline`) that estimates in
the calling thread, in arrival order, and reports every estimate to a callback. The streams' limits
(:data:`~place_safe.io.pipeline.STREAM_POLICY`): a read may block ``read_timeout`` seconds, ``max_timeouts`` in
a row end the run, and so does a source error (raised to the caller after the run has stopped).

Frames are gated by the pipeline's one :class:`~place_safe.io.pipeline.FrameGate`, as the placement loop's are,
with the streams' limits: a frame whose stamp is not later than the previous one's (a frozen sensor, a
duplicate) is not estimated and counts in ``repeated``; on a source stamped with this host's monotonic clock
(``clock_domain`` "monotonic") a frame stamped later than now (+ :data:`FUTURE_TOLERANCE`) is not estimated and
counts in ``future``. There is no age limit (a readout shows the age instead; the paper solver takes seconds a
frame), and a frame without a stamp is estimated and counted in ``unstamped`` (there is no clock to judge it by).

Latency is measured from arrival (when ``read`` returned) to the end of the estimate, so it includes the time
spent waiting in the buffer.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from place_safe.io.pipeline import STREAM_POLICY, FrameGate, SensorPipeline, clock_domain_of, stamp_of
from place_safe.io.replay import parse_error
from place_safe.io.source import FrameSource
from place_safe.recovery.estimator import Estimator, PlaneEstimate
from place_safe.sensor.frame import Frame


@dataclass
class StreamStats:
    """What happened during a live run. Times in seconds; ``latencies`` per estimated frame."""

    received: int = 0          # frames the source delivered
    estimated: int = 0         # frames the estimator processed (with or without a plane)
    dropped: int = 0           # frames discarded because the consumer was busy
    bad_frames: int = 0        # estimates without a plane because the frame was unusable
    no_plane: int = 0          # estimates without a plane (includes bad_frames)
    timeouts: int = 0          # SensorTimeout raised by the source
    repeated: int = 0          # frames not estimated: stamped no later than the previous one (a frozen sensor)
    future: int = 0            # frames not estimated: stamped later than now on this host's clock
    unstamped: int = 0         # frames estimated without a usable stamp (not gated)
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
                "repeated": self.repeated, "future": self.future, "unstamped": self.unstamped,
                "elapsed_s": round(self.elapsed, 4), "fps": round(self.fps, 3),
                "input_fps": round(self.input_fps, 3), "latency_ms": {
                    "median": ms(self.latency_median), "p95": ms(self.latency_p95), "max": ms(self.latency_max)},
                "ended_by": self.ended_by}

    def summary(self) -> str:
        """A few human-readable lines."""
        def ms(v: float | None) -> str:
            return "n/a" if v is None else f"{v * 1e3:.1f} ms"

        return (f"frames: {self.received} received, {self.estimated} estimated, {self.dropped} dropped waiting for the estimator, "
                f"{self.no_plane} without a plane ({self.bad_frames} bad), {self.timeouts} timeouts"
                + "".join(f", {n} {what}" for what, n in (("repeated", self.repeated), ("from the future", self.future),
                                                          ("unstamped", self.unstamped)) if n) + "\n"
                f"latency (arrival -> estimate): median {ms(self.latency_median)}, p95 {ms(self.latency_p95)}, "
                f"max {ms(self.latency_max)}\n"
                f"throughput: {self.fps:.1f} estimates/s (source {self.input_fps:.1f} frames/s) over "
                f"{self.elapsed:.2f} s; ended: {self.ended_by}")


#: s, how far a frame's stamp may lie after the host's monotonic clock before it counts as from the future
FUTURE_TOLERANCE = 0.01

#: Called for every estimate: (index of the frame in arrival order, frame, estimate, latency in s).
OnEstimate = Callable[[int, Frame, PlaneEstimate, float], None]


def run_live(source: FrameSource, estimator: Estimator, on_estimate: OnEstimate | None = None,
             max_frames: int | None = None, queue_size: int = 1, read_timeout: float = STREAM_POLICY.read_timeout,
             max_timeouts: int = STREAM_POLICY.max_timeouts or 5, stop: threading.Event | None = None) -> StreamStats:
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
    policy = replace(STREAM_POLICY, read_timeout=read_timeout, max_timeouts=max_timeouts)
    pipe = SensorPipeline(source, estimator, policy, threaded=True, estimate_on_reader=False, queue_size=queue_size,
                          max_frames=max_frames)
    gate = FrameGate(max_age=None, future_tolerance=FUTURE_TOLERANCE)
    host_clock = clock_domain_of(source) == "monotonic"
    stop = stop or threading.Event()
    t0 = time.monotonic()
    pipe.start()
    watcher = threading.Thread(target=lambda: (stop.wait(), pipe.request_stop()), daemon=True)
    watcher.start()
    try:
        while (m := pipe.next()) is not None:
            stamp = stamp_of(m.frame)
            if not math.isfinite(stamp):
                stats.unstamped += 1
            elif (why := gate.check(stamp, time.monotonic() if host_clock else None)) is not None:
                if why.startswith("future"):
                    stats.future += 1
                else:
                    stats.repeated += 1
                continue
            else:
                gate.accept(stamp)
            est = pipe.estimate(m.frame)
            latency = time.monotonic() - m.arrived
            stats.estimated += 1
            stats.latencies.append(latency)
            if not est.ok:
                stats.no_plane += 1
                if parse_error(m.frame) is not None or _fails_validation(m.frame):
                    stats.bad_frames += 1
            if on_estimate is not None:
                on_estimate(m.index, m.frame, est, latency)
    finally:
        stop.set()
        pipe.stop(join=read_timeout + 1.0)
        stats.elapsed = time.monotonic() - t0
    stats.received, stats.timeouts, stats.dropped = pipe.frames, pipe.timeouts, pipe.dropped
    stats.ended_by = pipe.ended_by or "stopped"
    if pipe.failure is not None:
        raise pipe.failure
    return stats


def _fails_validation(frame: Frame) -> bool:
    """Whether ``frame`` is not a frame :meth:`Frame.is_valid` passes (anything a source hands over)."""
    try:
        return not frame.is_valid()
    except Exception:
        return True


__all__ = ["StreamStats", "run_live", "OnEstimate", "FUTURE_TOLERANCE"]
