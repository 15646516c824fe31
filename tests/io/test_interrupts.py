"""Holding Ctrl-C off (place_safe.io.interrupts) and what it gives write_frames (place_safe.io.frame_file)."""

from __future__ import annotations

import json
import signal

import pytest

from place_safe.io.frame_file import WriteInterrupted, load_frames, write_frames
from place_safe.io.interrupts import interrupts_held


def test_a_sigint_inside_the_block_is_raised_when_it_ends():
    """The block runs to its end; the Ctrl-C then raises, and the handler before is back."""
    before = signal.getsignal(signal.SIGINT)
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_held():
            signal.raise_signal(signal.SIGINT)
            done.append("the rest of the block")
    assert done == ["the rest of the block"] and signal.getsignal(signal.SIGINT) is before
    with interrupts_held():  # none: nothing raised
        done.append("again")


@pytest.mark.parametrize("jsonl", [False, True])
def test_a_ctrl_c_while_the_frames_are_made_leaves_the_file_whole(tmp_path, synthetic_frames, jsonl):
    """A KeyboardInterrupt from the frames being written (a sensor read, a generator drawing them) left a JSON list
    without its ']': the file now holds the frames before it, closed, and WriteInterrupted says how many."""
    frames = list(synthetic_frames)[:3]

    def made():
        yield from frames[:2]
        raise KeyboardInterrupt

    out = tmp_path / ("f.jsonl" if jsonl else "f.json")
    with pytest.raises(WriteInterrupted) as stop:
        write_frames(out, made(), jsonl=jsonl)
    assert stop.value.written == 2 and isinstance(stop.value, KeyboardInterrupt)
    assert [f.to_dict() for f in load_frames(out)] == [f.to_dict() for f in frames[:2]]

    def none():
        raise KeyboardInterrupt
        yield

    with pytest.raises(WriteInterrupted) as stop:
        write_frames(out, none(), jsonl=jsonl)
    assert stop.value.written == 0  # (an empty list; in JSON Lines no line, as writing no frame gives)
    assert out.read_bytes() == b"" if jsonl else json.loads(out.read_text()) == []
