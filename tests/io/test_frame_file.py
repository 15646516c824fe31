"""Tests of place_safe.io.frame_file: the streamed reader (JSON list and JSON Lines) and writer."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

import place_safe.io.frame_file as frames_mod
from place_safe.exceptions import FrameError, FrameFileError
from place_safe.io.frame_file import iter_frame_dicts, iter_frames, load_frames, write_frames


def _entries(n: int) -> list[dict]:
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        out.append({"hists": rng.integers(0, 10**6, (9, 128)).tolist(),
                    "reference_hist": rng.integers(0, 1000, 128).tolist(),
                    "plane": {"normal": (np.array([0.0, 0.1, 1.0]) / np.sqrt(1.01)).tolist(), "offset": 0.05 + 0.01 * i},
                    "meta": {"i": i, "text": "a, b ] } [ { \" tricky"}})
    return out


@pytest.fixture()
def entries():
    return _entries(5)


def _write(path, entries, layout):
    if layout == "list":
        path.write_text(json.dumps(entries, indent=1))
    elif layout == "list-compact":
        path.write_text(json.dumps(entries, separators=(",", ":")))
    else:
        path.write_text("\n".join(json.dumps(e) for e in entries) + "\n")


LAYOUTS = ["list", "list-compact", "jsonl"]


@pytest.mark.parametrize("chunk", [1, 2, 5, 13])
@pytest.mark.parametrize("layout", LAYOUTS)
def test_reader_handles_every_chunk_boundary(tmp_path, monkeypatch, chunk, layout):
    """Tiny chunks put a boundary at every position of small objects (strings, nesting, numbers)."""
    monkeypatch.setattr(frames_mod, "_CHUNK", chunk)
    small = [{"id": i, "v": [1.5e-3, -2, [3, {"k": "a, b ] } [ { \" x"}]], "t": True, "n": None} for i in range(4)]
    path = tmp_path / "s.json"
    _write(path, small, layout)
    assert list(iter_frame_dicts(path)) == small


@pytest.mark.parametrize("chunk", [100, 4096, 1 << 16])
@pytest.mark.parametrize("layout", LAYOUTS)
def test_reader_reads_frames_across_chunks(tmp_path, monkeypatch, entries, chunk, layout):
    monkeypatch.setattr(frames_mod, "_CHUNK", chunk)
    path = tmp_path / "f.json"
    _write(path, entries, layout)
    assert list(iter_frame_dicts(path)) == entries
    fr = load_frames(path)
    assert [f.extra["meta"]["i"] for f in fr] == list(range(5))
    assert fr[2].truth.offset == pytest.approx(0.07)
    np.testing.assert_allclose(fr[2].truth.normal, np.array([0, 0.1, 1.0]) / np.linalg.norm([0, 0.1, 1.0]))


def test_numbers_split_across_chunks_are_not_cut(tmp_path, monkeypatch):
    monkeypatch.setattr(frames_mod, "_CHUNK", 3)
    path = tmp_path / "n.jsonl"
    path.write_text('{"a": 123456789}\n{"a": 0.000123}')
    assert [d["a"] for d in iter_frame_dicts(path)] == [123456789, 0.000123]


def test_empty_list_gives_no_frames(tmp_path):
    path = tmp_path / "e.json"
    path.write_text("  [ ]\n")
    assert list(iter_frames(path)) == []


@pytest.mark.parametrize("text,message", [
    ("", "empty"),
    ("   \n", "empty"),
    ("42", "not a frame file"),
    ('"frames"', "not a frame file"),
    ('[{"hists": [1, 2,', "truncated"),
    ('[{"hists": 1}', "truncated"),
    ('{"hists": 1}\n{"hists": 2', "truncated"),
    ('[{"hists": 1} {"hists": 1}]', "expected ','"),
    ('[{"hists": 1}] x', "after the closing"),
])
def test_malformed_files_raise_frame_file_error(tmp_path, text, message):
    path = tmp_path / "bad.json"
    path.write_text(text)
    with pytest.raises(FrameFileError, match=message):
        list(iter_frames(path))


def test_missing_file(tmp_path):
    with pytest.raises(FrameFileError, match="cannot open"):
        list(iter_frames(tmp_path / "nope.json"))


def test_frames_before_a_truncation_are_yielded_first(tmp_path, monkeypatch, entries):
    """Streaming: good frames come out before the reader reaches the broken end of the file."""
    monkeypatch.setattr(frames_mod, "_CHUNK", 256)
    text = json.dumps(entries)
    path = tmp_path / "t.json"
    path.write_text(text[: len(text) - 200])
    it = iter_frames(path)
    first = next(it)
    assert not isinstance(first, FrameError)
    with pytest.raises(FrameFileError):
        list(it)


def test_bad_entries_are_yielded_in_place(tmp_path, entries):
    bad = dict(entries[1])
    bad["hists"] = [[1, 2, 3]]
    path = tmp_path / "m.json"
    path.write_text(json.dumps([entries[0], bad, entries[2]]))
    got = list(iter_frames(path))
    assert isinstance(got[1], FrameError) and "shape" in str(got[1])
    assert not isinstance(got[0], FrameError) and not isinstance(got[2], FrameError)
    assert len(load_frames(path, strict=False)) == 2
    with pytest.raises(FrameFileError, match="frame 1"):
        load_frames(path)


@pytest.mark.parametrize("jsonl", [False, True])
@pytest.mark.parametrize("key", ["hists", "reference_hist"])
def test_a_key_given_twice_in_a_frame_is_an_error_in_place(tmp_path, entries, jsonl, key):
    """A frame with a second ``"hists"`` pasted from the next frame was read as that frame, without a word (both JSON
    readers keep the last value; a review's bad-input search): that frame is an error naming the key, the frames
    beside it load, and a note that merely mentions "hists" twice is no duplicate."""
    first = json.dumps(entries[0])
    dup = first[:-1] + f', "{key}": ' + json.dumps(entries[1][key]) + "}"
    note = dict(entries[2], meta={"note": '"hists" and "hists" again'})
    path = tmp_path / ("d.jsonl" if jsonl else "d.json")
    lines = [dup, json.dumps(entries[1]), json.dumps(note)]
    path.write_text("\n".join(lines) + "\n" if jsonl else "[" + ",".join(lines) + "]")
    got = list(iter_frames(path))
    assert isinstance(got[0], FrameError) and f"key '{key}' appears twice" in str(got[0])
    assert not isinstance(got[1], FrameError) and not isinstance(got[2], FrameError)


@pytest.mark.parametrize("layout", LAYOUTS)
@pytest.mark.parametrize("field,where", [("hists", (4, 77)), ("reference_hist", (50,))])
@pytest.mark.parametrize("value", [True, False])
def test_a_lone_boolean_among_the_counts_is_an_error_in_place(tmp_path, entries, layout, field, where, value):
    """One ``true`` or ``false`` among 1152 counts is not read as a count of 1 or 0: that frame is an error naming
    the field, and the frames beside it load (the text "true" in a note of another frame is not one)."""
    bad = json.loads(json.dumps(entries[1]))
    target = bad[field]
    for i in where[:-1]:
        target = target[i]
    target[where[-1]] = value
    good = dict(entries[2], note="true or false")
    path = tmp_path / "b.json"
    _write(path, [entries[0], bad, good], layout)
    got = list(iter_frames(path))
    assert isinstance(got[1], FrameError)
    assert str(got[1]) == f"b.json: frame 1: {field} must hold numbers, not booleans"
    assert not isinstance(got[0], FrameError) and not isinstance(got[2], FrameError)
    with pytest.raises(FrameFileError, match="frame 1: " + field):
        load_frames(path)


@pytest.mark.parametrize("jsonl", [False, True])
def test_write_then_read_round_trip(tmp_path, synthetic_frames, jsonl):
    path = tmp_path / ("w.jsonl" if jsonl else "w.json")
    assert write_frames(path, synthetic_frames, jsonl=jsonl) == len(synthetic_frames)
    back = load_frames(path)
    assert len(back) == len(synthetic_frames)
    for a, b in zip(synthetic_frames, back):
        np.testing.assert_allclose(a.hists, b.hists)
        np.testing.assert_allclose(a.reference, b.reference)
        np.testing.assert_allclose(a.truth.normal, b.truth.normal)
        assert a.truth.offset == pytest.approx(b.truth.offset)


def test_real_sweep_loads(sweep_path):
    fr = load_frames(sweep_path)
    assert len(fr) == 53
    assert all(f.truth is not None for f in fr)
    for f in fr:
        f.validate()


@settings(max_examples=400, deadline=None)
@given(st.lists(st.one_of(st.integers(-10**30, 10**30), st.floats(allow_nan=False, allow_infinity=False),
                          st.sampled_from([" ", ",", "[", "]", "-", "0.000000000000000000012345678901234567", "e-7"])),
                max_size=30))
def test_long_integer_test_finds_exactly_the_integer_literals_of_19_digits_or_more(parts):
    """The fast search for an integer literal of 19 digits or more (orjson would read it as a float) agrees with
    its definition, a space before 19 digits in the number shape, on random runs of numbers and separators."""
    raw = " ".join(repr(p) if not isinstance(p, str) else p for p in parts).encode()
    assert frames_mod._long_integer(raw) == (frames_mod._LONG_INTEGER in raw.translate(frames_mod._NUMBER_SHAPE))


def test_a_long_integer_is_read_exactly():
    raw = b'{"hists": 1, "n": 123456789012345678901234567890, "x": -0.00047130262929605347}'
    assert frames_mod._long_integer(raw)
    assert frames_mod._decode(raw)["n"] == 123456789012345678901234567890
    assert not frames_mod._long_integer(b'{"x": -0.00047130262929605347, "y": 1.2345678901234567890e3}')


@pytest.mark.parametrize("encoding", ["utf-16", "utf-16-be", "utf-16-le"])
@pytest.mark.parametrize("layout", ["list", "lines"])
def test_a_utf16_frame_file_is_said_to_be_utf16(tmp_path, encoding, layout):
    """A frame file saved as UTF-16 (some Windows editors' default) got only "not a frame file"; the error now says
    what it looks like and what to do. Little-endian without the byte-order mark read as a broken list ("expected ','
    or ']' between frames", round 14)."""
    p = tmp_path / "f.json"
    frames = [{"hists": [[0] * 128] * 9}] * 2
    text = json.dumps(frames) if layout == "list" else "\n".join(json.dumps(f) for f in frames)
    p.write_bytes(text.encode(encoding))
    with pytest.raises(FrameFileError, match="UTF-16 text: save it as UTF-8"):
        load_frames(p)


@pytest.mark.parametrize("encoding", ["utf-32", "utf-32-be", "utf-32-le"])
@pytest.mark.parametrize("layout", ["list", "lines"])
def test_a_utf32_frame_file_is_said_to_be_utf32(tmp_path, encoding, layout):
    """A UTF-32 frame file was said to look like UTF-16 text (or, big-endian without its mark, got no hint at all;
    an adversarial review, session 89)."""
    p = tmp_path / "f.json"
    frames = [{"hists": [[0] * 128] * 9}] * 2
    text = json.dumps(frames) if layout == "list" else "\n".join(json.dumps(f) for f in frames)
    p.write_bytes(text.encode(encoding))
    with pytest.raises(FrameFileError, match="UTF-32 text: save it as UTF-8"):
        load_frames(p)


def test_nul_bytes_are_not_said_to_be_utf16(tmp_path):
    """A file of NUL bytes (a preallocated or zeroed file) was said to look like UTF-16 text (round 14)."""
    p = tmp_path / "f.json"
    p.write_bytes(b"\x00" * 1000)
    with pytest.raises(FrameFileError, match="not a frame file") as e:
        load_frames(p)
    assert "UTF-16" not in str(e.value)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_frames_read_without_truth_are_the_same_frames_without_it(tmp_path, entries, layout):
    """``iter_frames(..., truth=False)`` (what ``recover`` reads) gives every frame and every error that the full read
    gives, field for field, except the ground truth, which stays unread (None, no ``truth_error``): a bad plane or
    pose costs neither reader the frame."""
    bad_plane = dict(entries[1], plane={"normal": [0, 0, -1], "offset": 0.1})  # behind the sensor
    bad_pose = dict(entries[2], pose=[[1, 0, 0, 0]], dist_to_plane=0.1)
    bad_pose.pop("plane")
    pose = dict(entries[3], pose=np.eye(4).tolist(), dist_to_plane=0.2)
    pose.pop("plane")
    broken = dict(entries[4], hists=[[1, 2]])
    path = tmp_path / "t.json"
    _write(path, [entries[0], bad_plane, bad_pose, pose, broken], layout)
    full, bare = list(iter_frames(path)), list(iter_frames(path, truth=False))
    assert len(full) == len(bare) == 5
    assert isinstance(full[4], FrameError) and str(full[4]) == str(bare[4])
    assert full[0].truth is not None and full[3].truth is not None and full[1].truth_error and full[2].truth_error
    for a, b in zip(full[:4], bare[:4]):
        assert b.truth is None and b.truth_error is None
        np.testing.assert_array_equal(a.hists, b.hists)
        np.testing.assert_array_equal(a.reference, b.reference)
        assert (a.extra, a.timestamp, a.timestamp_error) == (b.extra, b.timestamp, b.timestamp_error)


@pytest.mark.parametrize("name, shown", [("esc\x1b[31mred.json", "esc\\x1b[31mred.json"),
                                         ("line\nbreak.json", "line\\nbreak.json"), ("rtl\u202eknab.json",
                                                                                      "rtl\\u202eknab.json")])
def test_a_frames_reason_shows_the_files_name_with_its_control_characters_escaped(tmp_path, name, shown):
    """A frame's reason names its file, and recover's and evaluate's tables print it: a name with an escape sequence
    recoloured the terminal from recover's table, a newline broke its row (session 82; error lines were escaped in the
    sixth round). Both kinds of reason: an entry that is not an object, and one Frame.from_dict refuses."""
    import json as _json

    from place_safe.io.frame_file import iter_frames

    path = tmp_path / name
    path.write_text(_json.dumps([[1, 2], {"hists": "abc"}]))
    reasons = [str(f) for f in iter_frames(path)]
    assert reasons[0] == f"{shown}: frame 0: is a list, expected an object"
    assert reasons[1].startswith(f"{shown}: frame 1: hists")
    assert not any(c in r for r in reasons for c in "\x1b\n\u202e")
