"""Input files: the one gate every file place_safe reads goes through before anything parses it.

Concept: a path given by a user (calibration, placement config, robot file, scenario, scene, mount
truth, frame file, ...) is opened only when it names a *regular file* of a bounded size. Anything else
is refused with one line naming the file and what it is instead:

* a missing path, a directory;
* a FIFO (opening one blocks until a writer appears: a command would wait for ever), a character device
  (``/dev/zero`` reads without end), a socket, a block device;
* a file larger than the kind's limit (a config is kilobytes; a huge one would be read whole into memory).

:func:`check_input_file` does the checks (``os.stat``, which never blocks on a FIFO);
:func:`read_input_bytes` checks and reads at most the limit (a file that grows while it is read is cut
off there and refused, not read until memory runs out). Frame files are streamed by
:mod:`place_safe.io.frame_file` after the same check, with their own, larger limit.

Outputs get the mirror check, :func:`output_file_problem` (``place-safe`` runs it on every output option
before a command starts): never a directory, never a FIFO without a reader; then
:func:`output_open_problem` opens it to append, once its folder exists; an output folder,
:func:`output_dir_problem`: a directory, or a path under one.

Limits (bytes): :data:`MAX_CONFIG_BYTES` for configuration-like files (calibration, placement, robot,
scenario, scene, truth, sensor parameters), :data:`MAX_FRAME_FILE_BYTES` for frame files.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

#: bytes: the largest configuration-like file read (calibrations with fit reports are ~20 kB).
MAX_CONFIG_BYTES = 16 * 1024 * 1024
#: bytes: the largest frame file read (streamed; a 100,000-frame capture is ~1 GB).
MAX_FRAME_FILE_BYTES = 8 * 1024 ** 3


def _kind(mode: int) -> str:
    if stat.S_ISDIR(mode):
        return "is a directory, not a file"
    if stat.S_ISFIFO(mode):
        return "is a FIFO (named pipe), not a regular file"
    if stat.S_ISCHR(mode):
        return "is a character device, not a regular file"
    if stat.S_ISBLK(mode):
        return "is a block device, not a regular file"
    if stat.S_ISSOCK(mode):
        return "is a socket, not a regular file"
    return "is not a regular file"


def _size(n: int) -> str:
    for unit, scale in (("GiB", 1024 ** 3), ("MiB", 1024 ** 2), ("kiB", 1024)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n} bytes"


def input_file_problem(path: str | os.PathLike, max_bytes: int | None = MAX_CONFIG_BYTES) -> str | None:
    """Why ``path`` cannot be read as an input file ("does not exist", "is a FIFO ...", "is 2 GiB, more than
    ..."), or None when it is a regular file within ``max_bytes`` (None: no size limit)."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return "does not exist"
    except NotADirectoryError:
        return "does not exist (a part of the path is not a directory)"
    except PermissionError:
        return "cannot be read (permission denied)"
    except (OSError, ValueError) as exc:  # a name too long, a NUL byte in it, a loop of links
        return f"cannot be read ({getattr(exc, 'strerror', None) or str(exc).splitlines()[0]})"
    if not stat.S_ISREG(st.st_mode):
        return _kind(st.st_mode)
    if max_bytes is not None and st.st_size > max_bytes:
        return f"is {_size(st.st_size)}, more than the {_size(max_bytes)} such a file may have"
    return None


def check_input_file(path: str | os.PathLike, what: str, error: type[Exception],
                     max_bytes: int | None = MAX_CONFIG_BYTES, verb: str = "read") -> Path:
    """``path`` as a Path when it names a regular file within ``max_bytes``; else raises ``error`` with one
    line: ``cannot {verb} {what} {path}: it {why}``."""
    if not isinstance(path, (str, os.PathLike)):
        raise error(f"{what}: expected a file path (str or os.PathLike), got {type(path).__name__}")
    why = input_file_problem(path, max_bytes)
    if why is not None:
        raise error(f"cannot {verb} {what} {os.fspath(path)}: it {why}")
    return Path(path)


def read_input_bytes(path: str | os.PathLike, what: str, error: type[Exception],
                     max_bytes: int = MAX_CONFIG_BYTES) -> bytes:
    """The bytes of the regular file ``path`` (at most ``max_bytes``); ``error`` with one line otherwise."""
    p = check_input_file(path, what, error, max_bytes)
    try:
        with open(p, "rb") as fh:
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise error(f"cannot read {what} from {p}: {exc.strerror or exc}") from None
    if len(raw) > max_bytes:  # it grew while being read
        raise error(f"{what} {p} is more than the {_size(max_bytes)} such a file may have")
    return raw


def output_file_problem(path: str | os.PathLike) -> str | None:
    """Why a command must not write ``path`` (a directory; a FIFO nobody reads, where opening it would block for
    ever; a socket or block device), or None. A missing path, a regular file, a character device such as
    ``/dev/null`` and a FIFO with a reader (``>(gzip > out.gz)``) are fine."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        return f"cannot be written ({getattr(exc, 'strerror', None) or str(exc).splitlines()[0]})"
    if stat.S_ISDIR(st.st_mode) or stat.S_ISSOCK(st.st_mode) or stat.S_ISBLK(st.st_mode):
        return _kind(st.st_mode)
    if stat.S_ISFIFO(st.st_mode):
        try:  # a non-blocking open for writing fails at once (ENXIO) when no process reads the pipe
            os.close(os.open(path, os.O_WRONLY | os.O_NONBLOCK))
        except OSError:
            return "is a FIFO (named pipe) that nothing reads: writing it would wait for ever"
    return None


def output_open_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be opened for writing (the system's words), or None: opened to append, which changes nothing
    in a file that is there, and removed again where it was not. Run on an output before the work that writes it, in
    its folder once that exists: ``evaluate --json /proc/x.json`` said so only after the whole evaluation, minutes with
    diff (an adversarial round, session 74)."""
    existed = os.path.lexists(path)
    try:
        with open(path, "a", encoding="utf-8"):
            pass
    except OSError as exc:
        return exc.strerror or str(exc)
    if not existed:
        try:
            os.remove(path)
        except OSError:
            pass
    return None


def output_dir_problem(path: str | os.PathLike) -> str | None:
    """Why ``path`` cannot be a folder for a command's files (it, or a part of the path, is not a directory), or None
    (a directory, or a missing path). Permissions are not checked: a folder that cannot be written fails when written,
    with its name. An empty name is no folder (``evaluate --out ''`` wrote its plots into the working folder; an empty
    output file name is refused, session 82)."""
    if os.fspath(path) == "":
        return "needs a folder name (it was given an empty one)"
    try:
        st = os.stat(path)
    except FileNotFoundError:
        return None
    except NotADirectoryError:
        return "cannot be a directory (a part of the path is a file)"
    except (OSError, ValueError) as exc:
        return f"cannot be written ({getattr(exc, 'strerror', None) or str(exc).splitlines()[0]})"
    return None if stat.S_ISDIR(st.st_mode) else "is not a directory"


__all__ = ["output_file_problem", "output_open_problem", "output_dir_problem", "check_input_file", "read_input_bytes", "input_file_problem", "MAX_CONFIG_BYTES", "MAX_FRAME_FILE_BYTES"]
