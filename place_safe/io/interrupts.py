"""Holding Ctrl-C off while a file is in a state no reader takes (one frame half written).

:func:`interrupts_held` defers a SIGINT that arrives inside its block to the block's end, where the handler that was in
place runs (Python's default raises :class:`KeyboardInterrupt`). Signals reach Python's main thread only: off it, and
where SIGINT's handler was not set from Python, the block runs as it is.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def interrupts_held() -> Iterator[None]:
    """Run the block with SIGINT deferred: a Ctrl-C inside it is delivered (to the handler in place before, restored)
    once the block has ended, so the block is never cut short by one."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)
    if previous is None:  # (set outside Python: it cannot be put back)
        yield
        return
    caught: list = []
    signal.signal(signal.SIGINT, lambda signum, frame: caught.append(frame))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and callable(previous):
            previous(signal.SIGINT, caught[0])


__all__ = ["interrupts_held"]
