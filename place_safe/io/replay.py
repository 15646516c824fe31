"""File replay: a :class:`~place_safe.io.source.FrameSource` that plays a frame file back like a live sensor.

Concept
-------
The file (JSON list or JSON Lines, docs/interfaces.md) is streamed with
:func:`place_safe.io.frame_file.iter_frames`, never loaded whole. Frame ``k`` of a pass becomes available
``k / rate_hz`` seconds after the replay started (wall clock, ``time.monotonic``); ``read`` blocks until
the next frame is due and stamps :attr:`Frame.timestamp` with its arrival time (seconds on the
``time.monotonic`` clock). With ``realtime=False`` frames are delivered as fast as they are asked for.

Faults, for testing the live pipeline:

* ``drop``: frame indices that never arrive (their slot stays empty, the next frame keeps its schedule);
* ``gaps``: ``{index: seconds}`` of silence inserted before a frame (the schedule shifts by that much), so
  a reader with a shorter ``timeout`` sees :class:`~place_safe.exceptions.SensorTimeout`;
* ``corrupt``: frame indices delivered with NaN histograms (they fail :meth:`Frame.validate`).

A file entry that cannot be parsed is delivered too, as a frame with NaN histograms whose
``extra["parse_error"]`` says what was wrong, so the consumer can report it in place. File-level
problems (missing file, not a frame file) raise :class:`~place_safe.exceptions.FrameFileError` from the
constructor or, when they appear mid-file (truncation), from ``read``. The end of the file raises
``StopIteration`` from ``read`` (the :class:`FrameSource` convention), unless ``loop`` restarts it. A looping
replay whose pass over the whole file held not one usable entry (each unparseable or failing
:meth:`Frame.validate`) raises :class:`~place_safe.exceptions.FrameFileError` from ``read`` where it would start
again: every later pass would be the same, so a loop without a frame limit would report them for ever.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

import numpy as np

from place_safe.exceptions import ArgumentTypeError, FrameError, FrameFileError, SensorTimeout
from place_safe.io.frame_file import iter_frames
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame
from place_safe.io.source import FrameSource


def _bad_frame(reason: str) -> Frame:
    """A frame that fails validation, carrying why in ``extra["parse_error"]``."""
    return Frame(np.full((N_ZONES, N_BINS), np.nan), None, extra={"parse_error": reason})


def parse_error(frame: object) -> str | None:
    """Why ``frame`` is a stand-in for a file entry that could not be parsed (:func:`_bad_frame`), or None for a frame
    that came from the file (or a sensor)."""
    extra = getattr(frame, "extra", None)
    reason = extra.get("parse_error") if isinstance(extra, dict) else None
    return str(reason) if reason else None


#: Hz: the slowest and fastest replay (a frame a minute and a half .. a million a second).
MIN_RATE_HZ, MAX_RATE_HZ = 0.01, 1e6


class FileReplaySource(FrameSource):
    """Replay a frame file at ``rate_hz`` (Hz) as if it came from the sensor.

    Parameters
    ----------
    path: frame file (JSON list or JSON Lines).
    rate_hz: delivery rate in frames per second (must be > 0).
    loop: start again at the first frame when the file ends (indices keep counting).
    realtime: pace delivery on the wall clock; False delivers each frame as soon as it is read.
    drop, gaps, corrupt: injected faults, see the module docstring (indices count delivered slots
        from 0 over the whole replay, across loops).
    clock: the time source (seconds); injectable for tests.
    """

    def __init__(self, path: str | Path, rate_hz: float = 30.0, loop: bool = False, realtime: bool = True,
                 drop: Iterable[int] = (), gaps: Mapping[int, float] | None = None,
                 corrupt: Iterable[int] = (), clock=time.monotonic) -> None:
        if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float, np.number)):
            raise ArgumentTypeError(f"rate_hz must be a number of frames per second, got {type(rate_hz).__name__}")
        if not (np.isfinite(rate_hz) and MIN_RATE_HZ <= rate_hz <= MAX_RATE_HZ):
            raise ValueError(f"rate_hz must be {MIN_RATE_HZ:g}..{MAX_RATE_HZ:g} frames per second, got {rate_hz}")
        self.path = Path(path)
        self.rate_hz = float(rate_hz)
        self.loop = loop
        self.realtime = realtime
        self.drop = frozenset(int(i) for i in drop)
        self.gaps = {int(k): float(v) for k, v in (gaps or {}).items()}
        self.corrupt = frozenset(int(i) for i in corrupt)
        self._clock = clock
        self._it: Iterator[Frame | FrameError] | None = self._open()
        self._pass_entries = 0    # entries of the file read in this pass
        self._pass_usable = False  # whether one of them parsed and passed Frame.validate
        self._pass_first_bad: str | None = None  # why the first of them did not
        self._pending = self._judged(next(self._it, None))  # raises FrameFileError now for an unreadable file
        if self._pending is None:
            self._it = None
        self._slot = 0            # index of the next slot (frame position in the replay)
        self._shift = 0.0         # accumulated injected silence (s)
        self._start: float | None = None  # clock time of the first read (slot 0 is due then)
        self.delivered = 0        # frames handed out by read()

    def _open(self) -> Iterator[Frame | FrameError]:
        return iter_frames(self.path)

    def _judged(self, item: Frame | FrameError | None) -> Frame | FrameError | None:
        """``item``, an entry of the file, counted in this pass: whether it is usable, and why not."""
        if item is None:
            return None
        self._pass_entries += 1
        if self._pass_usable:
            return item
        if isinstance(item, FrameError):
            why = str(item)  # names the file and the entry
        else:
            try:
                item.validate()
            except FrameError as exc:
                why = f"{self.path.name}: frame {self._pass_entries - 1}: {exc}"
            else:
                self._pass_usable = True
                return item
        if self._pass_first_bad is None:
            self._pass_first_bad = why
        return item

    def _end_pass(self) -> None:
        """Start a new pass of a looping replay; FrameFileError if the one that ended had no usable entry."""
        n, first = self._pass_entries, self._pass_first_bad
        if n and not self._pass_usable:
            self.close()
            raise FrameFileError(f"no usable frame in a whole pass over {self.path.name} ({n} "
                                 f"entr{'y' if n == 1 else 'ies'}, each unreadable or invalid; the first: {first}): "
                                 "looping would repeat them for ever")
        self._pass_entries, self._pass_usable, self._pass_first_bad = 0, False, None

    def _next_item(self) -> Frame | FrameError | None:
        """Next entry of the file (None at the end of a non-looping replay)."""
        if self._pending is not None:
            item, self._pending = self._pending, None
            return item
        if self._it is None:
            return None
        item = self._judged(next(self._it, None))
        if item is None and self.loop:
            self._end_pass()
            self._it = self._open()
            item = self._judged(next(self._it, None))
        if item is None:
            self._it = None
        return item

    @property
    def started_at(self) -> float | None:
        """Clock time (s) of the first ``read``: frame ``k`` is due ``k / rate_hz`` s later (plus gaps)."""
        return self._start

    def _due(self, slot: int) -> float:
        assert self._start is not None
        return self._start + slot / self.rate_hz + self._shift

    def read(self, timeout: float = 1.0) -> Frame:
        """The next frame, waiting until it is due; SensorTimeout if it is not due within ``timeout`` s."""
        if self._start is None:
            self._start = self._clock()
        while True:
            slot = self._slot
            if slot in self.gaps:
                self._shift += self.gaps.pop(slot)
            if self.realtime:
                wait = self._due(slot) - self._clock()
                if wait > timeout:
                    time.sleep(max(timeout, 0.0))
                    raise SensorTimeout(f"no frame from {self.path.name} within {timeout:.3f} s "
                                        f"(next due in {wait:.3f} s)")
                if wait > 0:
                    time.sleep(wait)
            item = self._next_item()
            if item is None:
                raise StopIteration
            self._slot += 1
            if slot in self.drop:
                continue
            if isinstance(item, FrameError):
                frame = _bad_frame(str(item))  # names the file and the frame's index in it
            elif slot in self.corrupt:
                frame = Frame(np.full((N_ZONES, N_BINS), np.nan), item.reference, item.distances,
                              item.confidences, truth=item.truth, extra=dict(item.extra, injected="corrupt"))
            else:
                frame = item
            frame.timestamp = self._clock()
            frame.extra = dict(frame.extra, replay_index=slot)
            self.delivered += 1
            return frame

    def close(self) -> None:
        if self._it is not None:
            close = getattr(self._it, "close", None)
            if close is not None:
                close()
        self._it = None
        self._pending = None


__all__ = ["parse_error", "FileReplaySource"]
