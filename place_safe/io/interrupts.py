"""Holding Ctrl-C off while a file is in a state no reader takes (one frame half written).

:func:`interrupts_held` defers a SIGINT that arrives inside its block to the block's end, where it goes to the handler
that was in place: Python's own raises :class:`KeyboardInterrupt`, the default action (``SIG_DFL``) ends the process
as the signal would have, ``SIG_IGN`` drops it. A second SIGINT inside the same block is not held: it goes to that
handler at once (a write blocked on a stalled pipe retries after each signal, and a user pressing Ctrl-C again wants
out). Signals reach Python's main thread only: off it, and where SIGINT's handler was not set from Python, the block
runs as it is.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def interrupts_held() -> Iterator[None]:
    """Run the block with SIGINT deferred: a Ctrl-C inside it is delivered (to the handler in place before, restored)
    once the block has ended, so the block is not cut short by one; a second one is delivered at once."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is None:  # (set outside Python: it cannot be put back)
        yield
        return
    caught: list = []

    def hold(signum, frame):
        caught.append(frame)
        if len(caught) == 2:  # the second: the user insists (or a blocked write would hold it for ever)
            signal.signal(signal.SIGINT, previous)
            _deliver(previous, frame)

    signal.signal(signal.SIGINT, hold)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if len(caught) == 1:
            _deliver(previous, caught[0])


def _deliver(handler, frame) -> None:
    """Hand a held SIGINT to ``handler``, the one in place before: call it, or let the default action act."""
    if callable(handler):
        handler(signal.SIGINT, frame)
    elif handler == signal.SIG_DFL:
        signal.raise_signal(signal.SIGINT)


__all__ = ["interrupts_held"]
