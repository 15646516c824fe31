"""Reading and writing frame files (docs/interfaces.md), streamed so large files never sit whole in memory.

Two layouts are read: a JSON list of frames (the shared format) and JSON Lines (one frame object
per line, the project's capture format). Both are parsed incrementally.
"""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

from place_safe.exceptions import FrameError, FrameFileError
from place_safe.sensor.frame import Frame

_CHUNK = 1 << 16


def iter_frame_dicts(path: str | Path) -> Iterator[dict]:
    """Yield the raw frame objects of a JSON-list or JSON-Lines file one at a time.

    Raises :class:`FrameFileError` if the file is missing, not JSON, or not a list of objects.
    """
    p = Path(path)
    try:
        fh = open(p, "r", encoding="utf-8")
    except OSError as exc:
        raise FrameFileError(f"cannot open frame file {p}: {exc.strerror}") from None
    with fh:
        yield from _iter_stream(fh, p)


def _iter_stream(fh: IO[str], p: Path) -> Iterator[dict]:
    dec = json.JSONDecoder()
    buf = fh.read(_CHUNK)
    pos = _skip_ws(buf, 0)
    while pos >= len(buf):
        more = fh.read(_CHUNK)
        if not more:
            raise FrameFileError(f"{p}: file is empty; expected a JSON list of frames")
        buf += more
        pos = _skip_ws(buf, pos)
    is_list = buf[pos] == "["
    if is_list:
        pos += 1
    elif buf[pos] != "{":
        raise FrameFileError(f"{p}: not a frame file; expected a JSON list of frame objects or JSON Lines")
    index = 0
    eof = False
    while True:
        pos = _skip_ws(buf, pos)
        if is_list and pos < len(buf) and buf[pos] == ",":
            pos = _skip_ws(buf, pos + 1)
        if pos < len(buf) and is_list and buf[pos] == "]":
            return
        if pos >= len(buf):
            if eof:
                if is_list:
                    raise FrameFileError(f"{p}: truncated JSON list (missing ']')")
                return
            more = fh.read(_CHUNK)
            buf = buf[pos:] + more
            pos = 0
            eof = not more
            continue
        try:
            obj, end = dec.raw_decode(buf, pos)
        except json.JSONDecodeError as exc:
            if not eof:
                more = fh.read(_CHUNK)
                buf = buf[pos:] + more
                pos = 0
                eof = not more
                continue
            raise FrameFileError(f"{p}: invalid JSON in frame {index}: {exc.msg}") from None
        if end == len(buf) and not eof:
            # A number or literal may continue in the next chunk; make sure the object is complete.
            more = fh.read(_CHUNK)
            if more:
                buf = buf[pos:] + more
                pos = 0
                continue
            eof = True
        if not isinstance(obj, dict):
            raise FrameFileError(f"{p}: frame {index} is a {type(obj).__name__}, expected an object")
        yield obj
        index += 1
        buf, pos = buf[end:], 0


def _skip_ws(buf: str, pos: int) -> int:
    n = len(buf)
    while pos < n and buf[pos] in " \t\r\n":
        pos += 1
    return pos


def iter_frames(path: str | Path) -> Iterator[Frame | FrameError]:
    """Yield a :class:`Frame` per entry, or the :class:`FrameError` that made an entry unusable.

    File-level problems raise :class:`FrameFileError`; per-frame problems are yielded so a
    caller can report them in place and go on.
    """
    for d in iter_frame_dicts(path):
        try:
            yield Frame.from_dict(d)
        except FrameError as exc:
            yield exc


def load_frames(path: str | Path, strict: bool = True) -> list[Frame]:
    """All frames of a file as a list. With ``strict`` a bad frame raises :class:`FrameFileError`."""
    out: list[Frame] = []
    for i, f in enumerate(iter_frames(path)):
        if isinstance(f, FrameError):
            if strict:
                raise FrameFileError(f"{path}: frame {i}: {f}")
            continue
        out.append(f)
    return out


def write_frames(path: str | Path, frames: Iterable[Frame], jsonl: bool = False) -> int:
    """Write frames as a JSON list (default) or JSON Lines; returns the number written."""
    n = 0
    with open(path, "w", encoding="utf-8") as fh:
        if not jsonl:
            fh.write("[\n")
        for f in frames:
            if n and not jsonl:
                fh.write(",\n")
            fh.write(json.dumps(f.to_dict()))
            if jsonl:
                fh.write("\n")
            n += 1
        if not jsonl:
            fh.write("\n]\n")
    return n
