"""Holding Ctrl-C off (place_safe.io.interrupts) and what it gives write_frames (place_safe.io.frame_file)."""

from __future__ import annotations

import json
import signal

import pytest

from place_safe.io.frame_file import WriteInterrupted, load_frames, write_frames
from place_safe.io.interrupts import interrupts_held


def test_a_sigint_inside_the_block_is_raised_when_it_ends(sigint_raises):
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


def test_a_second_sigint_inside_the_block_is_raised_at_once(sigint_raises):
    """A write blocked on a stalled pipe retries after each signal: a second Ctrl-C is not held (a review, session
    86: the recording could not be stopped until the pipe's reader went away)."""
    done = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_held():
            signal.raise_signal(signal.SIGINT)
            done.append("after the first")
            signal.raise_signal(signal.SIGINT)
            done.append("after the second")
    assert done == ["after the first"] and signal.getsignal(signal.SIGINT) is signal.default_int_handler


def test_a_held_sigint_takes_the_default_action_where_that_was_the_handler():
    """With SIGINT's handler the default action (SIG_DFL), a Ctrl-C inside the block was dropped: the process went on.
    It now ends the process after the block, as the signal would have (a review, session 86)."""
    import subprocess
    import sys

    code = ("import signal\n"
            "from place_safe.io.interrupts import interrupts_held\n"
            "signal.signal(signal.SIGINT, signal.SIG_DFL)\n"
            "with interrupts_held():\n"
            "    signal.raise_signal(signal.SIGINT)\n"
            "    print('block ended', flush=True)\n"
            "print('still running', flush=True)\n")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert run.stdout == "block ended\n" and run.returncode == -signal.SIGINT


def test_a_ctrl_c_while_writing_to_dev_null_is_an_interrupt(synthetic_frames):
    """``/dev/null`` says it can seek, then refuses to be truncated: a Ctrl-C while frames were written there (``sensor
    record -o /dev/null``) ended "error: Invalid argument", exit 2, where a file gives "interrupted", exit 130 (a
    review, session 86). Only a regular file is cut back."""
    frames = list(synthetic_frames)[:2]

    def made():
        yield from frames
        raise KeyboardInterrupt

    for jsonl in (False, True):
        with pytest.raises(WriteInterrupted) as stop:
            write_frames("/dev/null", made(), jsonl=jsonl)
        assert stop.value.written == 2
