"""A computation run in a separate process alongside the caller, whose result may never be wanted.

``calibrate --method diff`` on a level sweep may need a second forward fit (the nominal geometry with each zone's own
time scale, :func:`~place_safe.calibration.forward_fit.reconsider_geometry`), but only the first fit can say so. On a
machine with a spare core the second fit starts at once beside the first, in a child Python process, and is stopped
when the first fit does not want it. With no spare core it runs inline, when asked for.

    with Alongside(fn, *args) as job:   # starts fn(*args) in a child process when a core is free
        ...                             # the caller's own work
        value = job.result()            # fn's return value (raised again here if fn raised); inline without a child
    # leaving the block stops a child whose result was not asked for

The child is ``python -m place_safe.calibration.alongside IN OUT`` (not :mod:`multiprocessing`: its "spawn" start
imports the caller's main script again, which breaks a task script without a ``__main__`` guard, and a forked child of
a process that has run torch may deadlock). ``fn`` and its arguments go to it as a pickle in a temporary file, and the
value (or the exception) comes back the same way, so ``fn`` should be a module-level function and its arguments
picklable (frames and forward parameters are); what cannot be pickled runs inline.
"""
from __future__ import annotations

import os
import pickle
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any


def spare_cores() -> int:
    """Cores this process may run on, less the one it runs on (0 when that cannot be told)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(n - 1, 0)


class Alongside:
    """``fn(*args)`` in a child process when :func:`spare_cores` allows (``parallel`` None) or ``parallel`` is True,
    else inline on the first :meth:`result`. The context manager stops an unfinished child and removes its files on
    exit."""

    def __init__(self, fn: Callable, *args: Any, parallel: bool | None = None):
        self.fn, self.args = fn, args
        self.parallel = spare_cores() > 0 if parallel is None else bool(parallel)
        self._proc: subprocess.Popen | None = None
        self._dir: tempfile.TemporaryDirectory | None = None
        self._done: tuple[str, Any] | None = None

    def __enter__(self) -> "Alongside":
        if self.parallel:
            try:
                payload = pickle.dumps((self.fn, self.args), protocol=pickle.HIGHEST_PROTOCOL)
            except Exception:  # (pickle raises several kinds) not for a child: inline, when asked for
                self.parallel = False
                return self
            self._dir = tempfile.TemporaryDirectory(prefix="place_safe_alongside_")
            job = Path(self._dir.name)
            (job / "in.pkl").write_bytes(payload)
            self._proc = subprocess.Popen([sys.executable, "-m", __name__, str(job / "in.pkl"), str(job / "out.pkl")],
                                          stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                          stderr=subprocess.DEVNULL)
        return self

    def result(self) -> Any:
        """``fn``'s value: the child's (waiting for it), or computed now without one. ``fn``'s exception is raised
        again here; a child that ended without a result raises :class:`RuntimeError`."""
        if self._done is None:
            if self._proc is None:
                try:
                    self._done = ("ok", self.fn(*self.args))
                except Exception as exc:
                    self._done = ("error", exc)
            else:
                code = self._proc.wait()
                out = Path(self._dir.name) / "out.pkl"
                try:
                    self._done = pickle.loads(out.read_bytes())
                except (OSError, pickle.UnpicklingError, EOFError, AttributeError, ImportError) as exc:
                    self._done = ("error", RuntimeError(f"the process alongside ended without a result (exit code "
                                                        f"{code}: {type(exc).__name__})"))
                self._stop()
        kind, value = self._done
        if kind == "error":
            raise value
        return value

    def _stop(self) -> None:
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            self._proc = None
        if self._dir is not None:
            self._dir.cleanup()
            self._dir = None

    def __exit__(self, *exc) -> None:
        self._stop()


def _child(inp: str, out: str) -> int:
    """The child: unpickle ``(fn, args)`` from ``inp``, write ``("ok", fn(*args))`` or ``("error", exception)`` to
    ``out`` (written whole, then renamed into place)."""
    try:
        fn, args = pickle.loads(Path(inp).read_bytes())
        result = ("ok", fn(*args))
    except BaseException as exc:  # noqa: BLE001 -- the parent raises it again
        result = ("error", exc)
    try:
        data = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as exc:  # an unpicklable value or exception: say what it was
        data = pickle.dumps(("error", RuntimeError(f"the result could not be sent back: {type(exc).__name__}: "
                                                   f"{exc}")))
    tmp = Path(out).with_suffix(".part")
    tmp.write_bytes(data)
    tmp.replace(out)
    return 0


__all__ = ["Alongside", "spare_cores"]


if __name__ == "__main__":
    sys.exit(_child(*sys.argv[1:3]))
