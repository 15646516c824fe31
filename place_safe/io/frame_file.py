"""Reading and writing frame files (docs/interfaces.md), streamed so large files never sit whole in memory.

Two layouts are read: a JSON list of frames (the shared format) and JSON Lines (one frame object
per line, the project's capture format). Files are UTF-8; a byte-order mark is accepted at the file's start (one
before a later frame makes that frame an error saying so).

The reader is linear in the file size: a small scanner (:class:`_Splitter`) finds where each frame
ends by following brackets and string quotes over the raw bytes (regular-expression jumps, so the
numbers in between cost nothing in Python), and each frame is decoded once, when it is complete.
One frame may be at most :data:`MAX_FRAME_BYTES` long and :data:`MAX_DEPTH` levels deep. Problems
inside one frame (bytes that are not UTF-8, invalid JSON, nesting too deep, a frame too large, an
integer too long, a value that is not an object) are yielded as a :class:`FrameError` for that
frame, naming the file and the frame index; only problems with the file's structure (not a list,
truncated, unreadable) raise :class:`FrameFileError`, after every complete frame before them. In JSON Lines each
non-blank line is one item at its line's index: a frame, or an error for the line (a line that ends inside its frame,
text after the frame on its line); a line ends at LF or CR LF, and between frames at a lone CR as well (a frame
broken by a lone CR inside it reads as the rest of its line).

Leniencies, on purpose: a comma after the last frame (``[{...}, ]``, as hand-edited lists often end) is read as the
end of the list, not as a frame. An empty list (``[]``, or a JSON Lines file without a frame) is a frame file with no
frames: the reader yields none, so ``recover --jsonl`` writes its one line per input frame, none, and exits 0 (as
docs/interfaces.md has it), ``stream`` replays nothing and exits 0, and ``evaluate`` and ``calibrate``, which need
frames with ground truth, refuse it (exit 2). ``sensor stream file:`` differs on purpose: it reads the file as a live
sensor, where no frame within its wait is the sensor failing (exit 1, as for a silent device).
"""

from __future__ import annotations

import json
import os
import re
import stat
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO

from place_safe.exceptions import FrameError, FrameFileError
from place_safe.sensor.frame import Frame, has_bool
from place_safe.io.input_file import MAX_FRAME_FILE_BYTES, check_input_file
from place_safe.io.interrupts import interrupts_held
from place_safe.io.json_values import DuplicateKey, unique_keys

try:  # a C parser, 5-8x faster on a frame; the standard library's when it is missing or declines
    import orjson as _orjson
except ImportError:  # pragma: no cover - a declared dependency
    _orjson = None

_CHUNK = 1 << 16
#: Largest frame accepted (bytes of JSON): a TMF8820 frame is about 10 kB; larger ones are skipped
#: with a per-frame error, without being held in memory.
MAX_FRAME_BYTES = 32 << 20
#: Deepest nesting accepted inside one frame (a frame needs 4 levels).
MAX_DEPTH = 64

_BOM = b"\xef\xbb\xbf"
_WS = b" \t\r\n"
_OUTSIDE = re.compile(rb'[\[\]{}"]')  # what matters outside strings
_INSIDE = re.compile(rb'["\\]')       # what matters inside a string
#: In JSON Lines every frame is one line: a line end inside a frame ends that frame as broken.
_OUTSIDE_LINES = re.compile(rb'[\[\]{}"\n]')
_INSIDE_LINES = re.compile(rb'["\\\n]')
_LINE_BROKEN = "the line ends inside the frame (JSON Lines: one frame per line)"
_LINE_EXTRA = "text after the frame on its line (JSON Lines: one frame per line)"
#: A byte-order mark is read at the file's start only; one before a later frame (files with one joined) makes that frame
#: an error of its own (it read as a frame of three bytes, then as "text after the frame" or a broken list)
_BOM_INSIDE = "a UTF-8 byte-order mark before the frame (only the file's start may have one: were files joined?)"
#: JSON Lines: what ends a line (CR alone as well: such files read one frame per line)
_LINE_END = re.compile(rb"[\r\n]")
_SCALAR_END = re.compile(rb'[\s,\]\[{}"]')
#: Fast paths of the walk (one regular-expression match instead of a step per bracket or quote): a list
#: of numbers or of lists of numbers (a histogram, a pose), a string without escapes, and a run of object
#: members with such values. Line ends are left to the step-by-step walk in JSON Lines, where they end a
#: frame.
_STRING_SOURCE = rb'"[^"\\\n]*+"'


def _block_source(other: bytes) -> bytes:
    """A list of numbers or of lists of numbers, none of whose bytes is ``other``."""
    return rb'\[(?:[^\[\]{}"' + other + rb']++|\[[^\[\]{}"' + other + rb']*+\])*+\]'


def _pairs(space: bytes, other: bytes) -> re.Pattern:
    """A run of object members ``"key": value,`` whose values are plain strings, lists of numbers (or of
    lists of numbers) or scalars: nothing in them opens or closes anything the walk tracks."""
    scalar = rb'[^\[\]{}",\s]++'
    value = rb'(?:' + _STRING_SOURCE + rb'|' + _block_source(other) + rb'|' + scalar + rb')'
    return re.compile(rb'(?:' + _STRING_SOURCE + space + rb':' + space + value + space + rb',?' + space + rb')++')


_BLOCK = re.compile(_block_source(b""))
_BLOCK_LINES = re.compile(_block_source(rb"\n"))
_PLAIN_STRING = re.compile(_STRING_SOURCE)
_PAIRS = _pairs(rb'\s*+', b"")
_PAIRS_LINES = _pairs(rb'[ \t\r]*+', rb'\n')
#: An integer literal of 19 digits or more may lie beyond 64 bits, which orjson reads as a float and only
#: the standard parser keeps exact. Found at C speed (a regular expression over a frame's digits costs 3x
#: the parse): every digit maps to "0", the characters of a decimal fraction or exponent to "f", anything
#: else to " ", so such an integer shows as " " and 19 "0" (the digits of a float like 0.000123... do not,
#: and they are common in frames).
_DIGITS_19 = b"0" * 19
_LONG_INTEGER = b" " + _DIGITS_19
_SPACE = ord(" ")
_NUMBER_SHAPE = bytes(ord("0") if chr(c).isdigit() and c < 128 else ord("f") if chr(c) in ".eE" else ord(" ")
                      for c in range(256))


#: whitespace (:data:`_WS`) between frames, skipped as one run (byte by byte it read 12 MB/s)
_BLANKS = re.compile(b"[" + re.escape(_WS) + b"]+")


class _Splitter:
    """Incremental splitter of a byte stream into top-level JSON values (objects, lists, strings, scalars).

    :meth:`feed` takes the next chunk and returns the values completed in it as
    ``(bytes or None, error or None)``: ``None`` bytes with an error for a value that was too large
    or too deep (its bytes were dropped as they came). Between values, ``sep`` bytes (``,`` for a
    JSON list) and whitespace are skipped; ``]`` ends a list. Each input byte is looked at a
    constant number of times.
    """

    def __init__(self, is_list: bool, max_bytes: int | None = None, max_depth: int | None = None) -> None:
        self.is_list = is_list
        self.max_bytes = MAX_FRAME_BYTES if max_bytes is None else max_bytes
        self.max_depth = MAX_DEPTH if max_depth is None else max_depth
        self.closed = False        # saw the list's closing ']'
        self.need_sep = False      # a value was completed; a ',' (list) must come before the next
        self.trailing: bytes = b""  # non-whitespace after the end of the list
        self.broken: str | None = None  # what broke the file's structure (no more values after it)
        # JSON Lines: a completed value waits for its line's end, so text after it on the line makes the line one
        # error instead of more values (a stray '}' after a frame read as a frame of its own and moved every index)
        self.pending: tuple[bytes | None, str | None] | None = None
        self.skipping = False      # JSON Lines: the rest of a line with text after its frame is being passed over
        self._line_ended = False   # JSON Lines: the value just ended by its line's end (the newline already read)
        self._reset()

    def _reset(self) -> None:
        self.parts: list[bytes] = []
        self.size = 0
        self.depth = 0
        self.in_string = False
        self.escape = False
        self.kind: str | None = None   # None between values; "container", "string" or "scalar"
        self.error: str | None = None

    def _keep(self, data: bytes) -> None:
        if self.error is None:
            self.size += len(data)
            if self.size > self.max_bytes:
                self.error = f"frame is larger than {self.max_bytes} bytes"
                self.parts = []
            else:
                self.parts.append(data)

    def _broken_line(self) -> None:
        """JSON Lines: the current frame's line ended before the frame did; it becomes a per-frame error."""
        self.in_string = False
        self.escape = False
        if self.error is None:
            self.error = _LINE_BROKEN
            self.parts = []
        self._line_ended = True

    def _finish(self, out: list) -> None:
        item = (None if self.error else b"".join(self.parts), self.error)
        self._reset()
        self.need_sep = self.is_list
        if self.is_list or self._line_ended:
            out.append(item)
        else:
            self.pending = item
        self._line_ended = False

    def _flush(self, out: list) -> None:
        if self.pending is not None:
            out.append(self.pending)
            self.pending = None

    def feed(self, chunk: bytes) -> list[tuple[bytes | None, str | None]]:
        out: list[tuple[bytes | None, str | None]] = []
        pos, n = 0, len(chunk)
        while pos < n:
            if self.closed:
                rest = chunk[pos:].strip(_WS)
                if rest and not self.trailing:
                    self.trailing = rest[:20]
                return out
            if self.skipping:  # JSON Lines: up to the end of a line that has text after its frame
                m = _LINE_END.search(chunk, pos)
                if m is None:
                    return out
                pos, self.skipping = m.start(), False
            if self.kind is None:  # between values
                if (blank := _BLANKS.match(chunk, pos)) is not None:  # a run of whitespace at once
                    if self.pending is not None and _LINE_END.search(chunk, pos, blank.end()):
                        self._flush(out)
                    pos = blank.end()
                    continue
                if self.pending is not None:  # JSON Lines: more than the frame on its line: the line is one error
                    self.pending = (None, _LINE_EXTRA)
                    self.skipping = True
                    continue
                c = chunk[pos:pos + 1]
                if self.is_list and c == b"]":
                    self.closed = True
                    pos += 1
                    continue
                if self.is_list and c == b",":
                    if not self.need_sep:
                        self.broken = "a ',' with no frame before it"
                        return out
                    self.need_sep = False
                    pos += 1
                    continue
                if self.need_sep:
                    self.broken = f"expected ',' or ']' between frames, found {c.decode('latin-1')!r}"
                    return out
                if c in (b"{", b"["):
                    self.kind, self.depth = "container", 0
                elif c == b'"':
                    self.kind, self.in_string = "string", True
                    self._keep(c)
                    pos += 1
                    continue
                else:  # a number, a literal or a stray byte: its first byte is always taken, so a stray
                    self.kind = "scalar"  # '}' or ']' cannot stop the scan where it stands
                    self._keep(c)
                    pos += 1
                    continue
            if self.kind == "scalar":
                m = _SCALAR_END.search(chunk, pos)
                end = m.start() if m else n
                self._keep(chunk[pos:end])
                pos = end
                if m:
                    if self.size == len(_BOM) and chunk[end:end + 1] in (b"{", b"[") and b"".join(self.parts) == _BOM:
                        self._reset()  # the frame after the mark is the error, at its own index
                        self.error = _BOM_INSIDE
                        continue
                    self._finish(out)
                continue
            # container or string: walk the interesting bytes
            start = pos
            done = False
            while pos < n:
                if self.in_string:
                    if self.escape:
                        self.escape = False
                        pos += 1
                        continue
                    m = (_INSIDE if self.is_list else _INSIDE_LINES).search(chunk, pos)
                    pos = n if m is None else m.end()  # the string goes on past this chunk, or up to m
                    if m is None:
                        break
                    if m.group() == b"\n":  # JSON Lines: the frame's line ended inside a string
                        self._broken_line()
                        done = True
                        break
                    if m.group() == b"\\":
                        self.escape = True
                    else:
                        self.in_string = False
                        if self.kind == "string":
                            done = True
                            break
                    continue
                m = (_OUTSIDE if self.is_list else _OUTSIDE_LINES).search(chunk, pos)
                if m is None:
                    pos = n
                    break
                ch = m.group()
                if ch == b'"' and self.depth > 0 and self.depth + 2 <= self.max_depth \
                        and (fast := (_PAIRS if self.is_list else _PAIRS_LINES).match(chunk, m.start())):
                    pos = fast.end()  # object members with simple values (a frame's fields) at once
                    continue
                if ch == b'"' and (fast := _PLAIN_STRING.match(chunk, m.start())):
                    pos = fast.end()  # a whole string (a key, a short value) at once
                    continue
                if ch == b"[" and self.depth > 0 and self.depth + 2 <= self.max_depth \
                        and (fast := (_BLOCK if self.is_list else _BLOCK_LINES).match(chunk, m.start())):
                    pos = fast.end()  # a whole list of numbers (or of lists of numbers) at once
                    continue
                pos = m.end()
                if ch == b"\n":  # JSON Lines: the frame's line ended with brackets still open
                    self._broken_line()
                    done = True
                    break
                if ch == b'"':
                    self.in_string = True
                elif ch in (b"{", b"["):
                    self.depth += 1
                    if self.depth > self.max_depth and self.error is None:
                        self.error = f"frame is nested deeper than {self.max_depth} levels"
                        self.parts = []
                else:
                    self.depth -= 1
                    if self.depth == 0:
                        done = True
                        break
            self._keep(chunk[start:pos])
            if done:
                self._finish(out)
        return out

    def end(self) -> list[tuple[bytes | None, str | None]]:
        """Values completed by the end of the stream (a trailing number in JSON Lines)."""
        out: list[tuple[bytes | None, str | None]] = []
        if self.kind == "scalar":
            self._finish(out)
        self._flush(out)
        return out

    @property
    def inside_value(self) -> bool:
        return self.kind is not None


def _long_integer(raw: bytes) -> bool:
    """Whether ``raw`` holds an integer literal of 19 digits or more: :data:`_LONG_INTEGER` in its number shape.
    Found as the runs of 19 digits (a needle of one repeated byte is found fast; the real sweep's frames have
    about 3, the fractions of small floats) that a space comes before: searching for the space and digits at
    once is slow through a frame's many digits (17 us a frame)."""
    shape = raw.translate(_NUMBER_SHAPE)
    i = shape.find(_DIGITS_19)
    while i >= 0:
        if i > 0 and shape[i - 1] == _SPACE:  # i starts the run: the leftmost match of 19 digits
            return True
        i = shape.find(_DIGITS_19, i + len(_DIGITS_19))
    return False


#: A frame's keys whose name appearing twice in its text sends it through the duplicate-key check (:func:`_decode`).
_KEYS_ONCE = tuple(f'"{k}"'.encode() for k in ("hists", "reference_hist", "distances", "plane", "pose",
                                                "dist_to_plane", "timestamp"))


def _decode(raw: bytes) -> object:
    """One frame's bytes as a JSON value; raises ValueError with a short reason, among them a key given twice in
    one object where a frame's own key's name appears twice in its text (the readers keep the last value silently:
    a frame with a second ``"hists"`` pasted from another frame was read as that frame, without a word)."""
    if any(raw.count(k) > 1 for k in _KEYS_ONCE):
        try:
            json.loads(raw.decode("utf-8", errors="replace"), object_pairs_hook=unique_keys)
        except DuplicateKey as exc:
            raise ValueError(f"key {str(exc.args[0])[:40]!r} appears twice in one object (which value was "
                             "meant?)") from None
        except (ValueError, RecursionError):
            pass  # not JSON: said below
    if _orjson is not None and not _long_integer(raw):  # orjson: big integers -> floats
        try:
            return _orjson.loads(raw)
        except _orjson.JSONDecodeError:
            pass  # the standard library's parser gives the message (and accepts NaN, Infinity)
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ValueError(f"not UTF-8 text (byte {exc.start} of the frame)") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"invalid JSON ({exc.msg} at character {exc.pos} of the frame)") from None
    except RecursionError:
        raise ValueError("invalid JSON (nested too deeply)") from None
    except ValueError as exc:  # e.g. an integer longer than Python's 4300-digit limit
        raise ValueError(f"invalid JSON ({str(exc).splitlines()[0]})") from None


def _iter_entries(path: str | Path) -> Iterator[dict | FrameError]:
    """Each entry of a frame file as a dict, or a :class:`FrameError` naming the file and frame index."""
    p = check_input_file(path, "frame file", FrameFileError, MAX_FRAME_FILE_BYTES, "open")  # no FIFO, device, directory
    try:
        fh = open(p, "rb")
    except OSError as exc:
        raise FrameFileError(f"cannot open frame file {p}: {exc.strerror or exc}") from None
    with fh:
        yield from _iter_stream(fh, p)


def _read(fh: IO[bytes], p: Path) -> bytes:
    try:
        return fh.read(_CHUNK)
    except OSError as exc:
        raise FrameFileError(f"cannot read frame file {p}: {exc.strerror or exc}") from None


def _second_line_is_a_frame(p: Path) -> bool:
    """Whether the second non-blank line of file ``p`` starts a JSON object: a JSON Lines file whose first line is
    broken goes on with frames, where a pretty-printed frame goes on with its members."""
    try:
        with open(p, "rb") as fh:
            seen = 0
            while line := fh.readline(MAX_FRAME_BYTES + 2):
                if line.strip():
                    seen += 1
                    if seen == 2:
                        return line.lstrip().startswith(b"{")
    except OSError:
        pass
    return False


def _iter_stream(fh: IO[bytes], p: Path) -> Iterator[dict | FrameError]:
    from place_safe.config import printable  # (config reads JSON with io.json_values: imported here, not at the top)

    buf = b""
    while True:  # the first non-blank byte decides the layout
        more = _read(fh, p)
        buf += more
        if buf.startswith(_BOM):
            buf = buf[len(_BOM):]
        elif len(buf) < len(_BOM) and _BOM.startswith(buf) and more:
            continue
        stripped = buf.lstrip(_WS)
        if stripped:
            buf = stripped
            break
        buf = b""
        if not more:
            raise FrameFileError(f"{p}: file is empty; expected a JSON list of frames")
    first = buf[:1]
    # UTF-16: its byte-order mark, or one NUL byte of the first two (b"[\x00" little-endian, b"\x00[" big-endian: a
    # little-endian file without the mark read as a broken list, and NUL bytes alone as UTF-16; round 14)
    wide = buf[:2] in (b"\xff\xfe", b"\xfe\xff") or (len(buf) >= 2 and (buf[0] == 0) != (buf[1] == 0))
    # UTF-32: its mark, or three NUL bytes of the first four (it was said to look like UTF-16; session 89)
    widest = buf[:4] in (b"\xff\xfe\x00\x00", b"\x00\x00\xfe\xff") or (len(buf) >= 4 and buf[:4].count(0) == 3)
    wide = wide or widest
    if first == b"[" and not wide:
        splitter, buf = _Splitter(is_list=True), buf[1:]
    elif first == b"{" and not wide:
        splitter = _Splitter(is_list=False)
    else:
        raise FrameFileError(f"{p}: not a frame file; expected a JSON list of frame objects or JSON Lines"
                             + (f" (it looks like UTF-{32 if widest else 16} text: save it as UTF-8)" if wide else ""))
    index = 0
    shown = printable(p.name)  # (a reason's file name: its control characters escaped)

    def entries(values) -> Iterator[dict | FrameError]:
        nonlocal index
        for raw, error in values:
            if error == _LINE_BROKEN and index == 0 and not _second_line_is_a_frame(p):
                # the first frame spans lines and the next line does not start one: not JSON Lines at all
                raise FrameFileError(f"{p}: not JSON Lines: its first frame spans more than one line (a pretty-printed "
                                     "frame? write one frame per line, or a JSON list of frames)")
            where = f"{shown}: frame {index}"
            index += 1
            if error is None:
                try:
                    obj = _decode(raw)
                except ValueError as exc:
                    error = str(exc)
                else:
                    if not isinstance(obj, dict):
                        error = f"is a {_json_type(obj)}, expected an object"
                    elif (b"true" in raw or b"false" in raw) and (flag := _boolean_counts(obj)):
                        error = f"{flag} must hold numbers, not booleans"
                    else:
                        yield obj
                        continue
            yield FrameError(f"{where}: {error}")

    while True:
        if buf:
            yield from entries(splitter.feed(buf))  # values completed before a break still come out
            if splitter.broken:
                raise FrameFileError(f"{p}: {splitter.broken} (after {index} frame{'s' if index != 1 else ''})")
        buf = _read(fh, p)
        if not buf:
            break
    yield from entries(splitter.end())
    if splitter.inside_value:
        raise FrameFileError(f"{p}: truncated in frame {index} (the file ends inside it)")
    if splitter.is_list and not splitter.closed:
        raise FrameFileError(f"{p}: truncated JSON list (missing ']')")
    if splitter.trailing:
        raise FrameFileError(f"{p}: unexpected data after the closing ']': {splitter.trailing.decode('latin-1')!r}")


def _boolean_counts(d: dict) -> str | None:
    """The first count field of a frame object holding a JSON ``true`` or ``false`` (None if none does).

    ``Frame.from_dict`` reads a lone boolean among a histogram's 1152 counts as a count of 1 or 0 (walking every
    count there would cost a twentieth of the peak method's time a frame); the reader walks an entry only when
    its text holds ``true`` or ``false``, which a frame of numbers never does.
    """
    for key in ("hists", "reference_hist"):
        if has_bool(d.get(key)):
            return key
    return None


def _json_type(obj: object) -> str:
    return {list: "list", str: "string", bool: "boolean", type(None): "null"}.get(type(obj), "number")


def iter_frame_dicts(path: str | Path) -> Iterator[dict]:
    """Yield the raw frame objects of a JSON-list or JSON-Lines file one at a time.

    Raises :class:`FrameFileError` if the file is missing, not JSON, or not a list of objects
    (strict: use :func:`iter_frames` to get per-frame errors in place).
    """
    for entry in _iter_entries(path):
        if isinstance(entry, FrameError):
            raise FrameFileError(str(entry))
        yield entry


def iter_frames(path: str | Path, *, truth: bool = True) -> Iterator[Frame | FrameError]:
    """Yield a :class:`Frame` per entry, or the :class:`FrameError` that made an entry unusable.

    File-level problems raise :class:`FrameFileError`; per-frame problems are yielded, with a
    message naming the file, the frame index and the field, so a caller can report them in place
    and go on. Ground truth that is not a plane only clears that frame's ``truth`` (its reason is in
    ``truth_error``): recovery does not need it. ``truth=False`` does not read the ground truth at all
    (:meth:`Frame.from_dict`: every frame's ``truth`` None), for a caller that never uses it.
    """
    # (the name in a frame's reason, which the human tables print: its control characters escaped, as an error line's
    # are -- a name with an escape sequence recoloured the terminal from recover's table; session 82)
    from place_safe.config import printable

    name = printable(Path(path).name) if isinstance(path, (str, os.PathLike)) else ""  # _iter_entries says what else
    for i, d in enumerate(_iter_entries(path)):
        if isinstance(d, FrameError):
            yield d
            continue
        try:
            yield Frame.from_dict(d, truth=truth)
        except FrameError as exc:
            yield FrameError(f"{name}: frame {i}: {exc}")


def load_frames(path: str | Path, strict: bool = True) -> list[Frame]:
    """All frames of a file as a list. With ``strict`` a bad frame raises :class:`FrameFileError`."""
    out: list[Frame] = []
    for f in iter_frames(path):
        if isinstance(f, FrameError):
            if strict:
                raise FrameFileError(str(f))
            continue
        out.append(f)
    return out


class WriteInterrupted(KeyboardInterrupt):
    """Ctrl-C while :func:`write_frames` wrote: the file is whole with the ``written`` frames before it."""

    def __init__(self, written: int) -> None:
        super().__init__(written)
        self.written = written


def write_frames(path: str | Path, frames: Iterable[Frame], jsonl: bool = False) -> int:
    """Write frames as a JSON list (default) or JSON Lines; returns the number written.

    A Ctrl-C (:class:`KeyboardInterrupt`) while it writes, or while ``frames`` makes the next one, leaves a file that
    reads: each frame's text is built first and written with Ctrl-C held off (:func:`interrupts_held`), the file cut
    back to its last whole frame and a list closed; it is then raised as :class:`WriteInterrupted`, with the frames
    written. (A Ctrl-C landing in a frame's write cut the file mid-frame, a JSON list without its ']' that every
    reader refused: round 15's leftover of ``sensor record``.)"""
    n = 0
    whole = 0  # bytes written up to the last whole frame (0: not even the list's '[')
    fh = open(path, "wb")
    try:
        if not jsonl:
            with interrupts_held():
                fh.write(b"[")
                whole = 1
        for f in frames:
            data = _frame_text(f, n, jsonl)
            with interrupts_held():
                fh.write(data)
                n += 1
                whole += len(data)
        if not jsonl:
            fh.write(b"\n]\n")
    except KeyboardInterrupt as exc:
        with interrupts_held():
            if _regular(fh):  # (a pipe, /dev/null: nothing to cut back, the frames being written whole)
                fh.seek(whole)
                fh.truncate()
            if not jsonl:
                fh.write((b"\n]\n" if n else b"]\n") if whole else b"[]\n")
        raise WriteInterrupted(n) from exc
    finally:
        with interrupts_held():  # (the buffer's last bytes reach the file whole too)
            fh.close()
    return n


def _regular(fh) -> bool:
    """Whether the open file ``fh`` is a regular file (one that can be cut back: ``/dev/null`` says it can seek, then
    refuses to be truncated)."""
    try:
        return stat.S_ISREG(os.fstat(fh.fileno()).st_mode)
    except (OSError, ValueError):
        return False


def _frame_text(frame: Frame, index: int, jsonl: bool) -> bytes:
    """Frame ``index``'s whole text in the file: its JSON with the line end after it (JSON Lines) or the separator
    before it (a JSON list: a comma after every frame but the last)."""
    text = json.dumps(frame.to_dict())
    return (text + "\n" if jsonl else ("\n" if index == 0 else ",\n") + text).encode("utf-8")
