"""A computation run in a separate process alongside the caller, whose result may never be wanted.

``calibrate --method diff`` needs a second forward fit (each zone's own time scale, with the geometry nominal on a
level sweep and free with tilted frames: :func:`~place_safe.calibration.second_fit.reconsider_geometry`). On a
machine with a spare core it starts at once beside the first, in a child Python process, and is stopped if its result
is not asked for (the first fit failed). With no spare core it runs inline, when asked for.

    with Alongside(fn, *args) as job:   # starts fn(*args) in a child process when a core is free
        ...                             # the caller's own work
        value = job.result()            # fn's return value (raised again here if fn raised); inline without a child
    # leaving the block stops a child whose result was not asked for

The child is ``python -m place_safe.calibration.alongside IN OUT`` with the caller's ``sys.path`` (not
:mod:`multiprocessing`: its "spawn" start imports the caller's main script again, which breaks a task script without a
``__main__`` guard, and a forked child of a process that has run torch may deadlock). ``fn`` and its arguments go to
it as a pickle in a private temporary directory, and the value (or ``fn``'s exception, with the child's traceback as a
note) comes back the same way. The child runs the code as imported from that path: what the caller changed at run time
(a patched module constant) does not reach it. It ignores Ctrl-C (its own session: the caller stops it) and ends,
removing its directory, when the caller's end of its standard input closes, so a caller killed outright leaves neither
a process nor files behind.

Whatever keeps the child from giving ``fn``'s outcome (no usable interpreter, ``fn`` defined in ``__main__`` or not
picklable with its arguments, a child that died or whose value cannot be unpickled) makes :meth:`Alongside.result` run
``fn`` inline instead, so the outcome is what the call inline gives; ``why_inline`` says why.
"""
from __future__ import annotations

import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any


def spare_cores() -> int:
    """Cores this process may run on, less the one it runs on (0 when that cannot be told). Not the machine's load."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(n - 1, 0)


class Alongside:
    """``fn(*args)`` in a child process when :func:`spare_cores` allows (``parallel`` None) or ``parallel`` is True,
    else inline on the first :meth:`result` (also whenever the child cannot give ``fn``'s outcome: ``why_inline``).
    The context manager stops an unfinished child and removes its files on exit."""

    def __init__(self, fn: Callable, *args: Any, parallel: bool | None = None):
        self.fn, self.args = fn, args
        self.parallel = spare_cores() > 0 if parallel is None else bool(parallel)
        self.why_inline: str | None = None if self.parallel else "no spare core"
        self._proc: subprocess.Popen | None = None
        self._dir: Path | None = None
        self._done: tuple[str, Any] | None = None

    def __enter__(self) -> "Alongside":
        if self.parallel:
            self._start()
        return self

    def _start(self) -> None:
        if not sys.executable or getattr(sys, "frozen", False):
            self.why_inline = "no Python interpreter to start"
            return
        if getattr(self.fn, "__module__", None) == "__main__":
            self.why_inline = "the function is defined in __main__"
            return
        try:
            payload = pickle.dumps((self.fn, self.args), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as exc:  # (pickle raises several kinds)
            self.why_inline = f"not picklable: {type(exc).__name__}"
            return
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in sys.path if p), "PYTHONSAFEPATH": "1"}
        try:
            self._dir = Path(tempfile.mkdtemp(prefix="place_safe_alongside_"))
            (self._dir / "in.pkl").write_bytes(payload)
            with open(self._dir / "stderr.txt", "wb") as err:
                self._proc = subprocess.Popen(
                    [sys.executable, "-m", __name__, str(self._dir / "in.pkl"), str(self._dir / "out.pkl")],
                    stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=err, env=env,
                    start_new_session=os.name == "posix")
        except OSError as exc:  # no temporary directory, or no process
            self.why_inline = f"the child did not start: {type(exc).__name__}: {exc}"
            self._stop()

    def result(self) -> Any:
        """``fn``'s value: the child's (waiting for it), or computed now without one. ``fn``'s exception is raised
        again here."""
        if self._done is None and self._proc is not None:
            code = self._proc.wait()
            try:
                self._done = pickle.loads((self._dir / "out.pkl").read_bytes())
            except Exception as exc:  # died, or its value does not unpickle here: inline, below
                tail = self._stderr_tail()
                self.why_inline = (f"the child ended without a usable result (exit code {code}: "
                                   f"{type(exc).__name__}{'; ' + tail if tail else ''})")
            self._stop()
        if self._done is None:
            try:
                self._done = ("ok", self.fn(*self.args))
            except Exception as exc:
                self._done = ("error", exc)
        kind, value = self._done
        if kind == "error":
            raise value
        return value

    def _stderr_tail(self, lines: int = 3) -> str:
        try:
            text = (self._dir / "stderr.txt").read_text(encoding="utf-8", errors="replace").strip().splitlines()
        except OSError:
            return ""
        return " | ".join(text[-lines:])

    def _stop(self) -> None:
        if self._proc is not None:
            if self._proc.poll() is None:
                self._proc.kill()
            self._proc.wait()
            if self._proc.stdin is not None:
                self._proc.stdin.close()
            self._proc = None
        if self._dir is not None:
            shutil.rmtree(self._dir, ignore_errors=True)
            self._dir = None

    def __exit__(self, *exc) -> None:
        self._stop()


def _orphan_watch(job: Path) -> None:
    """In the child: when the caller's end of standard input closes (it ended, or was killed), remove the job's
    directory and end at once."""
    try:
        while sys.stdin.buffer.read(4096):
            pass
    except (OSError, ValueError):
        pass
    shutil.rmtree(job, ignore_errors=True)
    os._exit(1)


def _child(inp: str, out: str) -> int:
    """The child: unpickle ``(fn, args)`` from ``inp``, write ``("ok", fn(*args))`` or ``("error", exception)`` (its
    traceback added as a note) to ``out`` (written whole, then renamed into place)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the caller stops it
    threading.Thread(target=_orphan_watch, args=(Path(inp).parent,), daemon=True).start()
    try:
        fn, args = pickle.loads(Path(inp).read_bytes())
        result = ("ok", fn(*args))
    except Exception as exc:
        if hasattr(exc, "add_note"):
            exc.add_note("in the process alongside:\n" + traceback.format_exc())
        result = ("error", exc)
    try:
        data = pickle.dumps(result, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception:  # an unpicklable value or exception: no result file, the caller runs fn inline
        traceback.print_exc()
        return 1
    tmp = Path(out).with_suffix(".part")
    tmp.write_bytes(data)
    tmp.replace(out)
    return 0


__all__ = ["Alongside", "spare_cores"]


if __name__ == "__main__":
    sys.exit(_child(*sys.argv[1:3]))
