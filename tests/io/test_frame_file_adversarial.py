"""Adversarial and property-based tests of the frame-file reader (place_safe.io.frame_file).

Properties: whatever the bytes, reading yields a Frame or a FrameError per entry, or raises a
FrameFileError for the file's structure, never anything else; a bad entry affects only itself; the
result does not depend on where the chunks end; and every byte is decoded at most once (the reader
is linear in the file size, which bounds its time by the input's size without a timing assert).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import place_safe.io.frame_file as ff
from place_safe.exceptions import FrameError, FrameFileError
from place_safe.io.frame_file import iter_frames, load_frames
from place_safe.sensor.frame import Frame

#: The originals, captured once: hypothesis runs many examples inside one monkeypatch scope.
_DECODE = ff._decode
_KEEP = ff._Splitter._keep

SETTINGS = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _good() -> dict:
    rng = np.random.default_rng(0)
    ref = np.full(128, 30.0)
    ref[12:17] = [500, 3000, 9000, 3000, 500]
    return {"hists": rng.integers(20, 60, (9, 128)).tolist(), "reference_hist": ref.tolist(),
            "plane": {"normal": [0.0, 0.0, 1.0], "offset": 0.1}}


def _read(path) -> tuple[list, BaseException | None]:
    out: list = []
    try:
        for item in iter_frames(path):
            out.append(item)
    except FrameFileError as exc:
        return out, exc
    return out, None


def _kinds(items: list) -> list[str]:
    return ["frame" if isinstance(x, Frame) else "error" for x in items]


# -- any bytes -----------------------------------------------------------------------------------------
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=True) | st.text(max_size=8),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=20)


@SETTINGS
@given(data=st.binary(max_size=400))
def test_arbitrary_bytes_never_escape_as_other_errors(tmp_path, data):
    path = tmp_path / "any.json"
    path.write_bytes(data)
    items, _ = _read(path)
    assert all(isinstance(x, (Frame, FrameError)) for x in items)


@SETTINGS
@given(entries=st.lists(json_values, max_size=6), jsonl=st.booleans(), chunk=st.integers(1, 64))
def test_any_json_entries_give_one_item_each_at_any_chunk_size(tmp_path, monkeypatch, entries, jsonl, chunk):
    path = tmp_path / "e.json"
    if jsonl:
        entries = [e for e in entries if isinstance(e, dict)]  # JSON Lines holds objects
        path.write_text("\n".join(json.dumps(e) for e in entries) + "\n")
    else:
        path.write_text(json.dumps(entries))
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    items, err = _read(path)
    if jsonl and not entries:
        assert isinstance(err, FrameFileError)  # an empty file
        return
    assert err is None
    assert len(items) == len(entries)
    for item, entry in zip(items, entries):
        if not isinstance(entry, dict):
            assert isinstance(item, FrameError) and "expected an object" in str(item)


@SETTINGS
@given(lines=st.lists(st.sampled_from(["frame", "frame}", "frame frame", "frame]", "frame x", "frame  ", "}", "x",
                                       "frame{", "{}{}", "frame 1"]), min_size=1, max_size=6),
       ending=st.sampled_from(["\n", "\r\n", "\r"]), last=st.booleans(), chunk=st.integers(1, 64))
def test_json_lines_give_one_item_per_line_and_keep_their_index(tmp_path, monkeypatch, lines, ending, last, chunk):
    """One item per line, at its line's index: text after a frame on its line makes that line one error. A stray '}'
    after a frame came out as an item of its own, and every later frame's index moved by one (an adversarial round,
    session 74); two frames on a line were read as two."""
    good = json.dumps(_good())
    text = ending.join(line.replace("frame", good) for line in ["frame"] + lines) + (ending if last else "")
    path = tmp_path / "e.jsonl"
    path.write_bytes(text.encode())
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    items, err = _read(path)
    if err is not None:  # only a last line that ends inside its frame is a truncated file
        assert lines[-1] == "frame{" and not last and "truncated" in str(err), err
        items.append(None)
    assert len(items) == len(lines) + 1
    for item, line in zip(items, ["frame"] + lines):
        if item is not None:
            assert _kinds([item]) == (["frame"] if line in ("frame", "frame  ") else ["error"]), (line, item)


#: Values whose strings hold brackets, quotes, escapes and line ends, and lists of lists of numbers:
#: what the walk's fast paths (a whole string, a whole list of numbers) must skip exactly or decline.
tricky_values = st.recursive(
    st.integers() | st.floats(allow_nan=False) | st.text(alphabet='[]{}"\\\n ab,', max_size=6)
    | st.lists(st.lists(st.floats(allow_nan=False, allow_infinity=False), max_size=4), max_size=3),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(alphabet='[]{}"\\ k', max_size=4), inner,
                                                                max_size=4),
    max_leaves=16)


@SETTINGS
@given(entries=st.lists(st.dictionaries(st.text(max_size=4), tricky_values, max_size=4), max_size=5),
       indent=st.sampled_from([None, 1]), chunk=st.sampled_from([1, 7, 64, 1 << 16]))
def test_entries_read_equal_the_standard_parser(tmp_path, monkeypatch, entries, indent, chunk):
    """The reader's split (with its fast paths) gives exactly the entries json.loads reads from the file."""
    path = tmp_path / "e.json"
    path.write_text(json.dumps(entries, indent=indent))
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    assert list(ff.iter_frame_dicts(path)) == json.loads(path.read_text())


@pytest.mark.parametrize("chunk", [1, 7, 1 << 16])
def test_integers_beyond_64_bits_stay_exact(tmp_path, monkeypatch, chunk):
    text = '[{"seq": 18446744073709551616, "a": -9223372036854775809, "b": 999999999999999999999999999999}]'
    path = tmp_path / "e.json"
    path.write_text(text)
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    got = list(ff.iter_frame_dicts(path))
    assert got == json.loads(text) and all(isinstance(v, int) for v in got[0].values())


def test_json_lines_a_line_end_inside_a_list_of_numbers_breaks_that_frame(tmp_path):
    good = json.dumps(_good())
    path = tmp_path / "e.jsonl"
    path.write_text(good + "\n" + good.replace("[[", "[\n[", 1) + "\n" + good + "\n")
    items, err = _read(path)
    assert err is None and isinstance(items[0], Frame) and isinstance(items[-1], Frame)
    assert isinstance(items[1], FrameError) and "line ends inside the frame" in str(items[1])


@SETTINGS
@given(pieces=st.lists(st.sampled_from(["good", "bad-json", "not-object", "deep", "huge-int", "latin1",
                                         "ts-string", "ts-list", "bad-truth", "ragged"]), min_size=1, max_size=8),
       chunk=st.sampled_from([1, 7, 64, 1 << 16]))
def test_a_bad_entry_affects_only_itself(tmp_path, monkeypatch, pieces, chunk):
    good = json.dumps(_good()).encode()
    raw = {
        "good": good,
        "bad-json": b'{"hists": [1, 2,, 3]}',
        "not-object": b"[1, 2, 3]",
        "deep": b'{"a": ' + b"[" * 5000 + b"]" * 5000 + b"}",
        "huge-int": b'{"hists": ' + b"9" * 5000 + b"}",
        "latin1": b'{"hists": "\xe9t\xe9"}',
        "ts-string": good[:-1] + b', "timestamp": "noon"}',
        "ts-list": good[:-1] + b', "timestamp": [1, 2]}',
        "bad-truth": good.replace(b'"offset": 0.1', b'"offset": -0.1'),
        "ragged": b'{"hists": [[1, 2], [3]], "reference_hist": [0]}',
    }
    path = tmp_path / "mixed.json"
    path.write_bytes(b"\xef\xbb\xbf[" + b",\n".join(raw[p] for p in pieces) + b"]")
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    items, err = _read(path)
    assert err is None and len(items) == len(pieces)
    for i, (kind, item) in enumerate(zip(pieces, items)):
        if kind in ("good", "bad-truth", "ts-string", "ts-list"):  # recovery needs neither the truth nor the stamp
            assert isinstance(item, Frame)
            assert (item.truth is None) == (kind == "bad-truth")
            assert (item.timestamp_error is not None) == kind.startswith("ts-")
        else:
            assert isinstance(item, FrameError)
            assert f"frame {i}" in str(item) and "mixed.json" in str(item)  # names the file and the index


@SETTINGS
@given(entries=st.lists(json_values, max_size=5), chunk=st.integers(1, 50))
def test_every_byte_is_decoded_at_most_once(tmp_path, monkeypatch, entries, chunk):
    """Linear time: the reader never decodes (or re-decodes) more bytes than the file has."""
    path = tmp_path / "lin.json"
    path.write_text(json.dumps(entries))
    decoded = []
    monkeypatch.setattr(ff, "_decode", lambda raw: (decoded.append(len(raw)), _DECODE(raw))[1])
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    _read(path)
    assert sum(decoded) <= path.stat().st_size


# -- the cases of the issue ------------------------------------------------------------------------------
def test_huge_frame_is_skipped_without_being_held(tmp_path, monkeypatch):
    monkeypatch.setattr(ff, "MAX_FRAME_BYTES", 10_000)
    big = dict(_good(), junk="x" * 50_000)
    path = tmp_path / "big.json"
    path.write_text(json.dumps([_good(), big, _good()]))
    decoded = []
    real = ff._decode
    monkeypatch.setattr(ff, "_decode", lambda raw: (decoded.append(len(raw)), real(raw))[1])
    items = list(iter_frames(path))
    assert _kinds(items) == ["frame", "error", "frame"]
    assert "larger than 10000 bytes" in str(items[1])
    assert max(decoded) < 10_000  # the huge frame was never assembled


def test_deeply_nested_frame_is_a_frame_error(tmp_path):
    path = tmp_path / "deep.json"
    path.write_text("[" + "[" * 100_000 + "]" * 100_000 + "]")
    (item,) = list(iter_frames(path))
    assert isinstance(item, FrameError) and "nested deeper" in str(item)


def test_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "bom.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps([_good()]).encode())
    assert len(load_frames(path)) == 1


@pytest.mark.parametrize("chunk", [1, 2, 7, 1 << 16])
@pytest.mark.parametrize("jsonl", [False, True])
def test_a_byte_order_mark_before_a_later_frame_says_so_in_its_place(tmp_path, monkeypatch, chunk, jsonl):
    """Files joined, the second with a BOM: in JSON Lines that frame read as "text after the frame on its line", in a
    list as a three-byte frame that then broke the file ("expected ',' or ']'"). It is now that frame's error, saying
    what it is; the frames either side are read, and a BOM at the file's start is still accepted."""
    good = json.dumps(_good())
    sep = "\n" if jsonl else ", "
    text = "\ufeff" + ("" if jsonl else "[") + good + sep + "\ufeff" + good + sep + good + ("\n" if jsonl else "]")
    path = tmp_path / ("joined.jsonl" if jsonl else "joined.json")
    path.write_bytes(text.encode())
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    items, err = _read(path)
    assert err is None and _kinds(items) == ["frame", "error", "frame"]
    assert str(items[1]).startswith(f"{path.name}: frame 1: a UTF-8 byte-order mark before the frame")


def test_non_utf8_bytes_name_the_frame(tmp_path):
    path = tmp_path / "latin.json"
    path.write_bytes(b'[' + json.dumps(_good()).encode() + b', {"meta": "caf\xe9"}]')
    items = list(iter_frames(path))
    assert isinstance(items[0], Frame)
    assert isinstance(items[1], FrameError) and "not UTF-8" in str(items[1]) and "frame 1" in str(items[1])


@pytest.mark.parametrize("text", ["[", "[{", '[{"a": "unterminated', "[{}", "[{},", '{"a": 1}\n{"b"'])
def test_truncated_files_raise_after_the_complete_frames(tmp_path, text):
    path = tmp_path / "cut.json"
    path.write_text(text)
    with pytest.raises(FrameFileError, match="truncated"):
        list(iter_frames(path))


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=st.text(alphabet='{}[]",:\\ \n1ae-', max_size=60), first=st.sampled_from(["[", "{", " [", "\ufeff{"]),
       chunk=st.integers(1, 8))
def test_structural_noise_never_hangs(tmp_path, monkeypatch, text, first, chunk):
    """Stray brackets, quotes and escapes: the scanner makes progress on every step (a step budget
    proportional to the input turns a hang into a failure instead of a timing assert)."""
    data = (first + text).encode()
    path = tmp_path / "noise.json"
    path.write_bytes(data)
    budget = {"steps": 4 * len(data) + 16}

    def counted(self, part):
        budget["steps"] -= 1
        assert budget["steps"] >= 0, "the scanner stopped making progress"
        _KEEP(self, part)

    monkeypatch.setattr(ff._Splitter, "_keep", counted)
    monkeypatch.setattr(ff, "_CHUNK", chunk)
    items, _ = _read(path)
    assert all(isinstance(x, (Frame, FrameError)) for x in items)


def test_json_lines_a_broken_line_is_one_bad_frame_and_the_lines_after_it_are_read(tmp_path, synthetic_frames):
    # a recorder that crashed mid-line: the frames on the following lines must still be read
    line = json.dumps(synthetic_frames[0].to_dict())
    path = tmp_path / "crashed.jsonl"
    path.write_text(f'{line}\n{{"hists": [1, 2\n{line}\n{{"meta": "unterminated\n{line}\n')
    items = list(iter_frames(path))
    assert [type(x).__name__ for x in items] == ["Frame", "FrameError", "Frame", "FrameError", "Frame"]
    assert "frame 1" in str(items[1]) and "line ends inside the frame" in str(items[1])


def test_a_pretty_printed_frame_is_not_read_as_json_lines(tmp_path):
    """One frame written with indentation (valid JSON, starting with '{'): read as JSON Lines it became thousands of
    broken frames and exit 0; now one line saying what the file is not. A later frame broken over lines stays a
    per-frame error among good ones."""
    import json

    import numpy as np

    from place_safe.exceptions import FrameFileError
    from place_safe.io.frame_file import iter_frames
    from place_safe.sensor.frame import Frame

    d = Frame(np.full((9, 128), 100.0), np.full(128, 100.0)).to_dict()
    f = tmp_path / "pretty.jsonl"
    f.write_text(json.dumps(d, indent=1))
    with pytest.raises(FrameFileError, match="not JSON Lines: its first frame spans more than one line"):
        list(iter_frames(f))
    g = tmp_path / "later.jsonl"
    g.write_text(json.dumps(d) + "\n" + json.dumps(d, indent=1) + "\n" + json.dumps(d) + "\n")
    out = list(iter_frames(g))
    assert isinstance(out[0], Frame) and isinstance(out[-1], Frame) and len(out) > 3
    h = tmp_path / "first_broken.jsonl"  # a first line cut short, frames after it: one broken frame, the rest read
    h.write_text(json.dumps(d)[:500] + "\n" + json.dumps(d) + "\n" + json.dumps(d) + "\n")
    out = list(iter_frames(h))
    assert len(out) == 3 and not isinstance(out[0], Frame) and all(isinstance(f, Frame) for f in out[1:])
