"""The TMF8820 measurement period a host can keep: fitted to the measured read-out, lengthened when a
measurement is overwritten, shortened again once it has been safe for a while.

Concept
-------
The chip measures once per period and overwrites a measurement the host has not read out by the time the
next one completes (``docs/tmf8820-protocol.md``), so a period shorter than the host's read-out gives no
frame at all, and every millisecond above it is lost frame rate. The read-out of one measurement, from the
host's own timing (:func:`need_ms`): 31 packet-to-packet intervals, each "wait for the interrupt, read the
packet, clear it, the chip's publish latency" (measured between detections). A chip that is not kept
waiting publishes packet 0 as its measurement completes, so a read-out can take one publish latency less;
but once one measurement runs late, the next one's packet 0 waits for the release of the last result plus
a publish latency, so a period below 31 intervals never drains a backlog, and any hiccup (a host stall, a
re-read) then grows into an overwrite. The period is a whole number of milliseconds:
``ceil(31 * mean interval + margin)``. The margin is a queue's: the slack ``s`` (period minus mean
read-out) absorbs a late read-out, and a backlog ``B`` of about one packet transfer (measured from a packet's
detection to the end of its clear) means an overwrite. A backlog that moves by steps of mean ``-s`` and
variance ``v = 31 * var(interval)`` passes ``B`` about ``exp(-2 s B / v)`` of the time, so ``s = K v / B``
with :data:`QUEUE_K` = ln(1000) / 2 keeps that near one measurement in a thousand (the overwrite feedback
below deals with the rest).

:class:`PeriodFit` decides, from that model and from what actually happens (``period_ms``, milliseconds,
never below the floor the user asked for; ``need`` is a callable giving the model's need in ms, or None
before there are enough timings, asked only when it matters):

* ``fit``: at the first whole measurement the period becomes the model's need (before it, the caller uses
  a guess from the bus speed).
* ``overwritten``: a measurement was lost. The period grows by ``step`` ms (1, doubling while overwrites
  come within :data:`OVERWRITE_MEMORY` frames of each other, so a far too short period is left in a few
  steps), and to at least the model's need. If the period is one a probe shortened it to, that probe
  failed (however late): the wait before the next one doubles, up to :data:`MAX_RELAX_FRAMES`.
* ``frame``: after ``wait`` frames (first :data:`RELAX_FRAMES`) with neither an overwrite nor a change, and
  when the model says a shorter period holds, the period is shortened to the model's need (a probe).

So over ``F`` frames of a steady chip, failed probes number at most ``log2(F / RELAX_FRAMES)`` (each one
overwrite), and a period too short by ``d`` ms costs about ``log2(d) + 1`` overwrites: no overwrite storm,
and changes become exponentially rare (the period converges to the model's need or one step above it).
A host stall that overwrites a measurement lengthens the period by 1 ms, and a later probe takes it back.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

#: Packets of one measurement (30 histogram packets and the result frame): intervals in one read-out.
INTERVALS = 31
#: Queue margin factor: ``ln(1 / p) / 2`` for an overwrite in about ``p`` = 1/1000 of the measurements.
QUEUE_K = 0.5 * math.log(1000.0)
#: Slack (s) added to the modelled read-out before it is rounded up to whole milliseconds.
SLACK_S = 10e-6
#: Overwrites within this many frames of each other double the lengthening step.
OVERWRITE_MEMORY = 20
#: Frames without an overwrite or a change before the period may be shortened again (then doubling).
RELAX_FRAMES = 50
#: The longest wait (frames) between two probes.
MAX_RELAX_FRAMES = 3200
#: The longest step (ms) one overwrite adds.
MAX_STEP_MS = 32
PERIOD_MAX_MS = 0xFFFF


def need_ms(intervals: Sequence[float], transfers: Sequence[float]) -> int | None:
    """Shortest whole-ms period that holds the read-out modelled from packet-to-packet ``intervals`` (s),
    with the queue margin for a backlog of one of the packet ``transfers`` (s, detection to the end of the
    interrupt clear). Intervals above the median by more than 1 ms (host stalls) are left out. None with
    fewer than 8 intervals or no transfer."""
    if len(intervals) < 8 or not transfers:
        return None
    ordered = sorted(intervals)
    n = len(ordered)
    med = 0.5 * (ordered[(n - 1) // 2] + ordered[n // 2])
    usual = [x for x in ordered if x <= med + 0.001]  # plain float sums: this runs once a frame
    mean = sum(usual) / len(usual)
    var = sum((x - mean) ** 2 for x in usual) / len(usual)
    transfer = max(sum(transfers) / len(transfers), 1e-6)
    margin = QUEUE_K * INTERVALS * var / transfer
    readout = INTERVALS * mean + margin + SLACK_S
    return min(PERIOD_MAX_MS, max(1, math.ceil(readout * 1000.0)))


class PeriodFit:
    """The period in use (ms) and how it adapts (see module docstring). ``floor_ms``: the shortest period
    the user wants. Each event method returns the new period when it changes, else None."""

    def __init__(self, floor_ms: int, *, relax_frames: int = RELAX_FRAMES,
                 max_relax_frames: int = MAX_RELAX_FRAMES) -> None:
        self.floor_ms = int(floor_ms)
        self.period_ms = self.floor_ms
        self.fitted = False
        self.wait = int(relax_frames)
        self.max_wait = int(max_relax_frames)
        self.changes = 0
        self._clean = 0                   # frames since the last overwrite or change
        self._since_overwrite = math.inf  # frames since the last overwrite
        self._streak = 0                  # overwrites in a row within OVERWRITE_MEMORY frames
        self._probe = False               # the last change shortened the period

    def _set(self, ms: int) -> int | None:
        ms = min(PERIOD_MAX_MS, max(self.floor_ms, int(ms)))
        self._clean = 0
        if ms == self.period_ms:
            return None
        self.period_ms = ms
        self.changes += 1
        return ms

    def guess(self, ms: int) -> int | None:
        """Before any measurement: a period from the bus speed (replaced at the first fit)."""
        return None if self.fitted else self._set(ms)

    def fit(self, need: Callable[[], int | None]) -> int | None:
        """The first whole measurement: the period becomes the model's need."""
        ms = None if self.fitted else need()
        if ms is None:
            return None
        self.fitted = True
        self._probe = False
        return self._set(ms)

    def overwritten(self, need: Callable[[], int | None]) -> int | None:
        """A measurement was overwritten before it was read out: lengthen."""
        self._streak = self._streak + 1 if self._since_overwrite < OVERWRITE_MEMORY else 0
        self._since_overwrite = 0
        if self._probe:  # the shorter period did not hold: wait longer before the next probe
            self.wait = min(self.max_wait, 2 * self.wait)
            self._probe = False
        self.fitted = True
        step = min(MAX_STEP_MS, 2 ** self._streak)
        return self._set(max(self.period_ms + step, need() or 0))

    def frame(self, need: Callable[[], int | None]) -> int | None:
        """A whole measurement arrived: shorten when it has been safe for ``wait`` frames and the model says
        a shorter period holds."""
        self._clean += 1
        self._since_overwrite += 1
        if not self.fitted:
            return self.fit(need)
        if self._clean < self.wait:
            return None
        ms = need()
        if ms is None or max(ms, self.floor_ms) >= self.period_ms:
            return None
        self._probe = True
        return self._set(ms)


__all__ = ["PeriodFit", "need_ms", "RELAX_FRAMES", "OVERWRITE_MEMORY", "MAX_RELAX_FRAMES"]
