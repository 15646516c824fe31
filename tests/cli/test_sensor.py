"""``place-safe sensor``: info, record, stream (with a rerun recording) and bench, over the emulator."""

from __future__ import annotations

import json

import pytest

from place_safe.cli.app import main
from place_safe.drivers.tmf8820.bench import random_frames
from place_safe.exceptions import SensorTimeout
from place_safe.io.frame_file import load_frames, write_frames
from place_safe.io.source import FrameSource


def test_info_json(capsys):
    assert main(["sensor", "info", "emu:synthetic:1", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["mode"] == "3x3" and info["active_range"].startswith("short") and info["app_version"]


def test_record_writes_a_frame_file(tmp_path, capsys):
    src = tmp_path / "in.json"
    write_frames(src, random_frames(3, seed=4))
    out = tmp_path / "out.jsonl"
    assert main(["sensor", "record", f"emu:file:{src}", "-o", str(out), "--frames", "3", "--bus-hz", "1e6", "-q"]) == 0
    got = load_frames(out)
    assert len(got) == 3 and all(f.timestamp is not None for f in got)
    assert main(["sensor", "record", f"emu:file:{src}", "-o", str(out)]) == 2  # exists, no --force
    assert "use --force" in capsys.readouterr().err


def test_record_leaves_out_a_file_sources_unreadable_entries(tmp_path, capsys):
    """`sensor record file:X` copied an entry of X it could not parse as the replay's stand-in, a frame of NaN counts,
    and wrote the literal NaN into the recording: not JSON (a strict reader refuses the whole file) and the entry's
    reason lost. Such entries are now left out and counted on the summary line; a source with none readable is one
    error line, exit 2, and no file."""
    src = tmp_path / "in.json"
    write_frames(src, random_frames(3, seed=4))
    entries = json.loads(src.read_text())
    src.write_text(json.dumps(entries[:1] + [{"hists": "abc"}] + entries[1:]))
    out = tmp_path / "out.json"
    assert main(["sensor", "record", f"file:{src}", "-o", str(out), "-q", "--timeout", "1"]) == 0
    err = capsys.readouterr().err
    assert (f"wrote 3 frames to {out} (stopped: source ended); 1 unreadable frame of the source left out (the first: "
            f"{src.name}: frame 1: hists must hold numbers, not text)") in err
    json.loads(out.read_text(), parse_constant=lambda c: pytest.fail(f"{c} in the recording"))
    assert len(load_frames(out)) == 3
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{"hists": "abc"}, {"hists": [1]}]))
    assert main(["sensor", "record", f"file:{bad}", "-o", str(tmp_path / "none.json"), "-q", "--timeout", "1"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("place-safe: error: sensor record: no readable frame from ")
    assert "2 unreadable frames of the source left out" in err[0] and not (tmp_path / "none.json").exists()



@pytest.mark.parametrize("suffix", [".json", ".jsonl"])
def test_a_recording_stopped_with_ctrl_c_keeps_the_frames_read_as_a_readable_file(tmp_path, capsys, monkeypatch,
                                                                                  suffix):
    """`sensor record -o rec.json` stopped with Ctrl-C (the way to end a long recording) left the JSON list without
    its ']': every frame recorded was lost to the readers ("truncated JSON list"). Ctrl-C now ends the recording
    there: the file holds the frames read, the summary line says why it stopped, exit status 130. Interrupted
    before the first frame, nothing is written."""
    import place_safe.cli.sensor as sensor_cli

    frames = list(random_frames(3, seed=4))
    monkeypatch.setattr(sensor_cli, "open_source", lambda uri, **opts: _Frames(frames, KeyboardInterrupt))
    out = tmp_path / f"rec{suffix}"
    assert main(["sensor", "record", "emu:synthetic", "-o", str(out), "--frames", "100", "-q"]) == 130
    assert capsys.readouterr().err.splitlines() == [f"wrote 3 frames to {out} (stopped: interrupted)"]
    assert len(load_frames(out)) == 3
    monkeypatch.setattr(sensor_cli, "open_source", lambda uri, **opts: _Frames([], KeyboardInterrupt))
    none = tmp_path / f"none{suffix}"
    assert main(["sensor", "record", "emu:synthetic", "-o", str(none), "-q"]) == 130
    assert capsys.readouterr().err.splitlines() == ["place-safe: interrupted"] and not none.exists()


class _CutWrites:
    """A file whose ``cut``-th write of a frame's text (one holding "hists") is cut mid-way by a Ctrl-C: ``how`` is
    "raise" (the KeyboardInterrupt raised there, between the two halves) or "signal" (a real SIGINT sent to the
    process between them)."""

    def __init__(self, fh, cut: int, how: str):
        self.fh, self.cut, self.how, self.frames = fh, cut, how, 0

    def write(self, data):
        if "hists" not in (data if isinstance(data, str) else data.decode("utf-8", "replace")):
            return self.fh.write(data)
        self.frames += 1
        if self.frames != self.cut:
            return self.fh.write(data)
        half = len(data) // 2
        self.fh.write(data[:half])
        if self.how == "raise":
            raise KeyboardInterrupt
        import signal

        signal.raise_signal(signal.SIGINT)
        return self.fh.write(data[half:])

    def __getattr__(self, name):
        return getattr(self.fh, name)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.fh.close()


@pytest.mark.parametrize("suffix", [".json", ".jsonl"])
@pytest.mark.parametrize("how,kept", [("raise", 2), ("signal", 3)])
def test_a_ctrl_c_while_a_frame_is_written_leaves_a_readable_recording(tmp_path, capsys, monkeypatch, sigint_raises,
                                                                       suffix, how, kept):
    """A Ctrl-C that landed while `sensor record -o rec.json` wrote a frame (round 15's leftover: round 15 kept one
    between frames) cut the file mid-frame, a JSON list without its ']' that every reader refused; the summary was
    "place-safe: interrupted". Each frame's text is now written whole with Ctrl-C held off, the file cut back to the
    last whole frame and closed: a write cut by a KeyboardInterrupt keeps the frames before it, a SIGINT during the
    write lets that frame finish; the summary says so, exit 130."""
    import place_safe.cli.sensor as sensor_cli
    import place_safe.io.frame_file as frame_file

    frames = list(random_frames(5, seed=4))
    monkeypatch.setattr(sensor_cli, "open_source", lambda uri, **opts: _Frames(frames))
    real_open = open
    monkeypatch.setattr(frame_file, "open", lambda *a, **k: _CutWrites(real_open(*a, **k), 3, how), raising=False)
    out = tmp_path / f"rec{suffix}"
    assert main(["sensor", "record", "emu:synthetic", "-o", str(out), "--frames", "5", "-q"]) == 130
    assert capsys.readouterr().err.splitlines() == [f"wrote {kept} frames to {out} (stopped: interrupted)"]
    got = load_frames(out, strict=True)
    assert [f.to_dict() for f in got] == [f.to_dict() for f in frames[:kept]]
    if suffix == ".json":
        json.loads(out.read_text())


class _Frames(FrameSource):
    """A source of ``frames`` that raises ``end`` once they are read (StopIteration: it ends; KeyboardInterrupt: a
    Ctrl-C while it is read)."""

    def __init__(self, frames, end: type[BaseException] = StopIteration):
        self.left = list(frames)
        self.end = end

    def read(self, timeout=1.0):
        if not self.left:
            raise self.end
        return self.left.pop(0)


def test_stream_saves_a_rerun_recording(tmp_path, capsys):
    src = tmp_path / "in.json"
    write_frames(src, load_frames("tests/data/tmf8820_ur5_sweep.json")[20:23])
    rrd = tmp_path / "run.rrd"
    assert main(["sensor", "stream", f"file:{src}", "--max-frames", "3", "--save", str(rrd)]) == 0
    out = capsys.readouterr().out
    assert "tilt" in out and "distance" in out
    assert rrd.is_file() and rrd.stat().st_size > 1000


def test_stream_save_keeps_a_file_that_is_not_a_recording_unless_forced(tmp_path, capsys):
    """``--save sweep.json`` replaced the frame file with a recording, without a word (session 82). A file that is not
    a rerun recording is kept (one line, exit 2, before the sensor opens); --force replaces it; a recording is replaced
    as ever (rerunning a command with the same --save works as before)."""
    src = tmp_path / "in.json"
    write_frames(src, load_frames("tests/data/tmf8820_ur5_sweep.json")[20:23])
    kept = tmp_path / "sweep.json"
    kept.write_bytes(src.read_bytes())
    argv = ["sensor", "stream", f"file:{src}", "--max-frames", "2", "--jsonl"]
    assert main([*argv, "--save", str(kept)]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"place-safe: error: sensor stream: --save {kept} is a file that is not a rerun recording; it is kept (use "
        "--force to replace it)"]
    assert kept.read_bytes() == src.read_bytes()
    rrd = tmp_path / "run.rrd"
    for _ in range(2):  # a recording: replaced without --force
        assert main([*argv, "--save", str(rrd)]) == 0
    assert rrd.read_bytes()[:3] == b"RRF"
    assert main([*argv, "--save", str(kept), "--force"]) == 0 and kept.read_bytes()[:3] == b"RRF"
    capsys.readouterr()
    assert main([*argv, "--force"]) == 2
    assert capsys.readouterr().err.splitlines() == ["place-safe: error: sensor stream: --force goes with --save"]


def test_a_rerun_recording_that_cannot_be_written_is_one_line_naming_the_file(capsys):
    """--save /dev/full: rerun's RuntimeError was an "internal error"; now the one line of every write that found no
    room, naming the file and the OS error (exit 2, as for -o /dev/full), before the sensor is opened."""
    assert main(["sensor", "stream", "file:tests/data/tmf8820_ur5_sweep.json", "--max-frames", "1",
                 "--save", "/dev/full"]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == ["place-safe: error: No space left on device: /dev/full"]
    assert captured.out == ""


def test_bench_prints_and_writes_figures(tmp_path, capsys):
    js = tmp_path / "bench.json"
    assert main(["bench", "sensor", "--frames", "10", "--bus-hz", "400000", "--json", str(js), "-q"]) == 0
    rows = json.loads(js.read_text())
    assert rows[0]["frames"] == 10 and rows[0]["bytes_per_frame"] >= rows[0]["transfer_min"]
    # one row per way of waiting (INT line, polling) and publish latency (0, 50, 200 us by default), frames/s
    # against the bus limit and the ceiling (whole-ms periods: a driver at the ceiling equals it)
    assert [(r["wait"], r["publish_latency_s"]) for r in rows] == [
        (w, pytest.approx(lat)) for w in ("int", "poll") for lat in (0.0, 50e-6, 200e-6)]
    assert all(r["fps"] <= r["host_ceiling_fps"] * (1 + 1e-9) and r["host_ceiling_fps"] <= r["fps_limit"]
               for r in rows)
    assert all(r["host_ceiling_fps"] <= r["bytes_ceiling_fps"] for r in rows)
    out = capsys.readouterr().out
    assert "frames/s" in out and "latency us" in out and "of limit" in out and "of ceil" in out


def test_bench_help_explains_the_figures(capsys):
    with pytest.raises(SystemExit):
        main(["bench", "sensor", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "publish latency" in text and "bus limit" in text and "ceiling" in text
    assert "31 x L" in text and "START/STOP" in text  # the ceiling's arithmetic


class _Silent(FrameSource):
    """A sensor that never publishes: every read times out (at once, so the test does not wait); counts its reads."""

    def __init__(self) -> None:
        self.reads = 0

    def read(self, timeout: float = 1.0):
        self.reads += 1
        raise SensorTimeout(f"no frame within {timeout:g} s")


@pytest.mark.parametrize("command", ["stream", "record"])
def test_a_sensor_that_never_answers_is_one_line_exit_1_after_one_timeout(command, tmp_path, capsys, monkeypatch):
    """A bus device that never publishes: exit 0 with "0 received" (stream waited five --timeouts: 5 min with
    --timeout 60); now one line, exit 1, after one read (one timeout's silence), and record leaves its output alone."""
    silent = _Silent()
    monkeypatch.setattr("place_safe.cli.sensor.open_source", lambda uri, **options: silent)
    out = tmp_path / "frames.json"
    out.write_text("old")
    extra = ["-o", str(out), "--force", "-q"] if command == "record" else []
    assert main(["sensor", command, "i2c:/dev/i2c-1", "--timeout", "60", *extra]) == 1
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        f"place-safe: error: sensor {command}: no frame from the sensor in 60 s: source 'i2c:/dev/i2c-1' did not "
        "answer within --timeout 60 s" + (f"; {out} not written" if command == "record" else "")]
    assert silent.reads == 1 and captured.out == ""
    assert out.read_text() == "old"


@pytest.mark.parametrize("command", ["stream", "record"])
def test_a_source_that_ends_before_its_first_frame_is_one_line_exit_1(command, tmp_path, capsys):
    empty = tmp_path / "empty.json"
    empty.write_text("[]")
    out = tmp_path / "frames.json"
    extra = ["-o", str(out), "-q"] if command == "record" else []
    assert main(["sensor", command, f"file:{empty}", *extra]) == 1
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"place-safe: error: sensor {command}: no frame from the sensor in ")
    assert err[0].endswith(f"source 'file:{empty}' ended before its first frame"
                           + (f"; {out} not written" if command == "record" else "")), err
    assert captured.out == "" and not out.exists()


@pytest.mark.parametrize("command", ["stream", "record"])
def test_an_emulated_file_without_a_readable_frame_is_one_line_exit_2(command, tmp_path, capsys):
    """The emulator skipped the entries it could not parse and ended: "ended before its first frame", exit 1, as a
    sensor that stops; now the file's fault, as `sensor record file:X` says it."""
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps([{"hists": "abc"}, {"hists": [1]}]))
    out = tmp_path / "frames.json"
    extra = ["-o", str(out), "-q"] if command == "record" else []
    assert main(["sensor", command, f"emu:file:{bad}", "--bus-hz", "1e6", *extra]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == ["place-safe: error: no readable frame in bad.json: 2 unreadable entries (the "
                                         "first: bad.json: frame 0: hists must hold numbers, not text)"]
    assert captured.out == "" and not out.exists()


@pytest.mark.parametrize("argv, match", [
    (["bench", "sensor", "--frames", "0"], "expected a whole number from 1 to 100000"),
    (["sensor", "info", "file:x.json", "--patch", "p.hex"], "does not apply"),
    (["sensor", "info", "nope"], "not a source URI"),
    (["sensor", "info", "emu:synthetic:1", "--patch", "missing.hex"], "does not exist"),
])
def test_bad_usage_is_one_line_exit_2(argv, match, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1


def test_info_says_what_the_period_is_and_its_unit(capsys):
    """``period_ms: 117`` beside ``requested_period_ms: 33`` said neither what the period is nor why it differs."""
    assert main(["sensor", "info", "emu:synthetic:1"]) == 0
    lines = {line.split(":", 1)[0].strip(): line for line in capsys.readouterr().out.splitlines()}
    period = lines["period_ms"]
    assert "ms (measurement period in use: one frame every" in period and "frames/s" in period
    assert "lengthened from the 33 ms asked to what the bus can read out" in period
    assert "(the shortest measurement period asked for: --period-ms)" in lines["requested_period_ms"]
    with pytest.raises(SystemExit):
        main(["sensor", "info", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "period_ms is the measurement period in use, in milliseconds" in text
    assert "--period-ms MS shortest measurement period wanted, ms" in text


def test_an_int_line_without_gpiod_names_the_extra_to_install(capsys, monkeypatch):
    """--int-line needs gpiod, which the [hw] extra did not install; a missing one is one line naming the extra."""
    import sys
    import tomllib
    from pathlib import Path

    monkeypatch.setitem(sys.modules, "gpiod", None)  # not installed
    assert main(["sensor", "info", "i2c:1", "--int-line", "/dev/gpiochip0:17"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "needs the gpiod package" in err[0] and err[0].endswith('pip install "place-safe[hw]"')
    project = tomllib.loads((Path(__file__).parents[2] / "pyproject.toml").read_text())["project"]
    assert any(r.split(";")[0].strip().startswith("gpiod>=2") for r in project["optional-dependencies"]["hw"])


class _FillsUp:
    """A recording file on a disk with ``room`` bytes left: a write takes what fits, then fails with ENOSPC."""

    def __init__(self, path, room: int) -> None:
        self.fh, self.room = open(path, "wb", buffering=0), room

    def write(self, data) -> int:
        import errno
        import os

        if self.room <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        n = self.fh.write(bytes(data[:self.room]))
        self.room -= n
        return n

    def tell(self) -> int:
        return self.fh.tell()

    def close(self) -> None:
        self.fh.close()


def test_a_disk_that_fills_mid_stream_stops_it_with_one_line_and_keeps_the_recording(tmp_path, capsys, monkeypatch,
                                                                                     sweep_path):
    """--save on a disk that filled up mid-stream: rerun logged its own errors, the stream went on and said "wrote
    run.rrd", exit 0 (and disconnecting could hang). Now one line naming the file, exit 1, no traceback; the bytes
    written before stay a readable recording."""
    import shutil
    import subprocess

    import place_safe.cli.live_view as live_view

    room = 40_000  # the header and a few frames
    monkeypatch.setattr(live_view, "_open_output", lambda path: _FillsUp(path, room))
    rrd = tmp_path / "run.rrd"
    assert main(["sensor", "stream", f"file:{sweep_path}", "--max-frames", "30", "--save", str(rrd)]) == 1
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"place-safe: error: sensor stream: --save {rrd}: No space left on device after "
                             f"{room / 1e3:.1f} kB (at ")
    assert err[0].endswith(f"stopped; the frames written before stay readable (rerun {rrd})")
    assert rrd.stat().st_size == room and "tilt" in captured.out
    rerun = shutil.which("rerun")
    if rerun is not None:  # rerun's own reader takes the recording cut short (the footer could not be written)
        done = subprocess.run([rerun, "rrd", "verify", "--check-footers", "false", str(rrd)], capture_output=True,
                              text=True, timeout=120)
        assert done.returncode == 0 and "verified without error" in done.stdout + done.stderr


def test_a_viewer_that_cannot_be_started_is_one_usage_line(capsys, monkeypatch, sweep_path):
    """`sensor stream --view` where rerun finds no viewer to spawn ended "internal error: RuntimeError: Failed to find
    Rerun Viewer executable in PATH", exit 1. It is the machine's setup, not a fault of ours: one line saying what to
    do, exit 2, and no sensor opened."""
    import rerun

    def no_viewer(*args, **kwargs):
        raise RuntimeError("Failed to find Rerun Viewer executable in PATH.")

    monkeypatch.setattr(rerun, "init", no_viewer)
    assert main(["sensor", "stream", f"file:{sweep_path}", "--max-frames", "3", "--view"]) == 2
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert len(err) == 1 and captured.out == ""
    assert err[0].startswith("place-safe: error: --view cannot start the rerun viewer: Failed to find Rerun Viewer")
    assert "--save RUN.rrd" in err[0]


def test_a_source_that_cannot_be_opened_leaves_no_recording_behind(tmp_path, capsys):
    """`sensor stream --save` makes its recording before it opens the sensor (an output it cannot write opens no
    sensor); a source that then cannot be opened left a header-only .rrd behind. Now it is removed (a file that was
    there before is left)."""
    rrd = tmp_path / "run.rrd"
    assert main(["sensor", "stream", f"file:{tmp_path / 'missing.json'}", "--save", str(rrd)]) != 0
    assert len(capsys.readouterr().err.splitlines()) == 1 and not rrd.exists()
