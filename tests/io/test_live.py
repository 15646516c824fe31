"""Tests of live recovery: FileReplaySource (place_safe.io.replay) and run_live (place_safe.io.live)."""

from __future__ import annotations

import json
import threading
import time

import numpy as np
import pytest

from place_safe.recovery.estimator import Estimator, PlaneEstimate
from place_safe.exceptions import FrameFileError, NoPlaneError, SensorTimeout
from place_safe.geometry import Plane
from place_safe.io.replay import FileReplaySource
from place_safe.sensor.frame import Frame
from place_safe.io.live import StreamStats, run_live


class SlowEstimator(Estimator):
    """Takes ``delay`` seconds per frame and returns the frame's ground truth (or fails as told)."""

    name = "slow"

    def __init__(self, delay: float = 0.0, crash_on: int | None = None) -> None:
        self.delay = delay
        self.crash_on = crash_on
        self.seen: list[int] = []

    def _estimate(self, frame: Frame) -> PlaneEstimate:
        idx = frame.extra.get("replay_index")
        self.seen.append(idx)
        time.sleep(self.delay)
        if idx == self.crash_on:
            raise RuntimeError("boom")
        if frame.truth is None:
            raise NoPlaneError("no truth")
        return PlaneEstimate(frame.truth)


# -- FileReplaySource ------------------------------------------------------------------------------
def test_replay_paces_frames_and_stamps_arrival(synthetic_file):
    rate = 50.0
    with FileReplaySource(synthetic_file, rate_hz=rate) as src:
        t0 = time.monotonic()
        frames = list(src.frames(timeout=1.0))
        elapsed = time.monotonic() - t0
    assert len(frames) == 8
    stamps = np.array([f.timestamp for f in frames])
    assert np.all(np.diff(stamps) > 0)
    # paced: no frame arrives before it is due (sleeping never ends early)
    assert np.all(stamps - src.started_at >= np.arange(8) / rate - 1e-6)
    assert elapsed >= 7 / rate                            # 8 frames span 7 periods
    assert [f.extra["replay_index"] for f in frames] == list(range(8))
    assert all(f.truth is not None for f in frames)


def test_replay_without_realtime_is_immediate_and_ends_with_stopiteration(synthetic_file):
    src = FileReplaySource(synthetic_file, rate_hz=1.0, realtime=False)
    for _ in range(8):  # at 1 frame/s a paced replay would need 7 s; unpaced, no read waits (timeout 0.01 s)
        src.read(timeout=0.01)
    with pytest.raises(StopIteration):
        src.read()


def test_replay_faults_drop_gap_corrupt(synthetic_file):
    src = FileReplaySource(synthetic_file, rate_hz=100.0, drop=[1, 2], gaps={4: 0.3}, corrupt=[5])
    got, timeouts = [], 0
    while True:
        try:
            got.append(src.read(timeout=0.05))
        except SensorTimeout:
            timeouts += 1
        except StopIteration:
            break
    assert [f.extra["replay_index"] for f in got] == [0, 3, 4, 5, 6, 7]
    assert timeouts >= 1                                  # the 0.3 s silence is seen through 0.05 s reads
    bad = got[3]
    assert bad.extra.get("injected") == "corrupt"
    with pytest.raises(Exception, match="NaN"):
        bad.validate()


def test_replay_loops(synthetic_file):
    src = FileReplaySource(synthetic_file, rate_hz=1000.0, loop=True, realtime=False)
    got = [src.read() for _ in range(20)]
    assert [f.extra["replay_index"] for f in got] == list(range(20))
    np.testing.assert_allclose(got[8].hists, got[0].hists)


def test_replay_reports_unparseable_entries_in_place(tmp_path, synthetic_frames):
    entries = [synthetic_frames[0].to_dict(), {"hists": [[1, 2]]}, synthetic_frames[1].to_dict()]
    path = tmp_path / "mixed.json"
    path.write_text(json.dumps(entries))
    src = FileReplaySource(path, realtime=False)
    frames = [src.read(), src.read(), src.read()]
    assert "shape" in frames[1].extra["parse_error"]
    assert frames[0].extra.get("parse_error") is None


def test_replay_loop_over_a_file_without_a_usable_frame_ends_with_one_error(tmp_path, synthetic_frames):
    # every entry unparseable or failing validation: a pass gives nothing, and so would every pass after it
    negative = synthetic_frames[0].to_dict()
    negative["hists"] = [[-1.0] * len(row) for row in negative["hists"]]
    path = tmp_path / "bad.jsonl"
    path.write_text("\n".join(json.dumps(e) for e in ({"hists": "garbage"}, negative)) + "\n")
    src = FileReplaySource(path, realtime=False, loop=True)
    got = [src.read(), src.read()]                       # the pass itself is delivered, errors in place
    assert "hists" in got[0].extra["parse_error"] and not got[1].is_valid()
    with pytest.raises(FrameFileError, match=r"no usable frame in a whole pass over bad.jsonl \(2 entries.*frame 0"):
        src.read()                                       # where the loop would start again
    with pytest.raises(StopIteration):
        src.read()
    # one usable frame among them: it loops as before
    path.write_text("\n".join(json.dumps(e) for e in ({"hists": "garbage"}, negative, synthetic_frames[1].to_dict())))
    src = FileReplaySource(path, realtime=False, loop=True)
    assert [src.read().extra["replay_index"] for _ in range(10)] == list(range(10))


def test_replay_missing_or_broken_file_fails_at_open(tmp_path):
    with pytest.raises(FrameFileError):
        FileReplaySource(tmp_path / "missing.json")
    bad = tmp_path / "bad.json"
    bad.write_text("not json")
    with pytest.raises(FrameFileError):
        FileReplaySource(bad)
    with pytest.raises(ValueError):
        FileReplaySource(tmp_path / "missing.json", rate_hz=0)


# -- run_live -----------------------------------------------------------------------------------
def test_run_live_fast_consumer_keeps_every_frame(synthetic_file):
    got = []
    with FileReplaySource(synthetic_file, rate_hz=100.0) as src:  # a queue as long as the file: nothing to drop
        stats = run_live(src, SlowEstimator(0.0), lambda i, f, e, lat: got.append((i, e.ok, lat)), queue_size=16)
    assert isinstance(stats, StreamStats)
    assert stats.received == stats.estimated == 8
    assert stats.dropped == 0 and stats.no_plane == 0 and stats.timeouts == 0
    assert [g[0] for g in got] == list(range(8))
    assert all(ok for _, ok, _ in got)
    assert 0 <= stats.latency_median <= stats.latency_p95 <= stats.latency_max
    assert stats.ended_by == "source ended"
    d = stats.to_dict()
    assert set(d["latency_ms"]) == {"median", "p95", "max"} and d["fps"] > 0


def test_run_live_slow_consumer_drops_old_frames_and_stays_current(synthetic_file):
    est = SlowEstimator(0.06)  # 60 ms per frame against a frame every 10 ms
    with FileReplaySource(synthetic_file, rate_hz=100.0, loop=True) as src:
        stats = run_live(src, est, max_frames=30, queue_size=1)
    assert stats.received == 30
    assert stats.dropped > 0
    assert stats.estimated + stats.dropped == stats.received
    assert est.seen == sorted(est.seen)                      # arrival order


def test_run_live_gaps_bad_frames_and_crashes_do_not_stall(tmp_path, synthetic_frames):
    entries = [f.to_dict() for f in synthetic_frames]
    entries[2] = {"hists": "garbage"}
    path = tmp_path / "faulty.json"
    path.write_text(json.dumps(entries))
    est = SlowEstimator(0.0, crash_on=6)
    results = {}
    with FileReplaySource(path, rate_hz=100.0, gaps={3: 0.25}, corrupt=[5]) as src:
        stats = run_live(src, est, lambda i, f, e, lat: results.__setitem__(f.extra["replay_index"], e),
                         read_timeout=0.05, max_timeouts=20, queue_size=16)
    assert stats.received == 8 and stats.estimated == 8
    assert stats.timeouts >= 1
    assert stats.ended_by == "source ended"
    assert results[2].plane is None and "hists" in results[2].reason           # unparseable entry
    assert results[5].plane is None and "NaN" in results[5].reason             # corrupted counts
    assert results[6].plane is None and "boom" in results[6].reason            # estimator crash
    assert all(results[i].ok for i in (0, 1, 3, 4, 7))
    assert stats.bad_frames == 2 and stats.no_plane == 3


def test_run_live_ends_after_consecutive_timeouts(synthetic_file):
    with FileReplaySource(synthetic_file, rate_hz=100.0, gaps={2: 60.0}) as src:
        stats = run_live(src, SlowEstimator(), read_timeout=0.05, max_timeouts=4)
    assert stats.received == 2 and stats.timeouts == 4
    assert "timeouts" in stats.ended_by


def test_run_live_can_be_stopped_from_outside(synthetic_file):
    stop = threading.Event()
    with FileReplaySource(synthetic_file, rate_hz=20.0, loop=True) as src:
        timer = threading.Timer(0.3, stop.set)
        timer.start()
        stats = run_live(src, SlowEstimator(), stop=stop, read_timeout=0.2)
        timer.cancel()
    assert stats.received >= 1 and stats.ended_by == "stopped"


def test_run_live_with_the_peak_estimator(synthetic_file, synthetic_frames):
    from place_safe.recovery import make_estimator

    planes = []
    est = make_estimator("peak")
    est.estimate(synthetic_frames[0])  # warm-up: the first call pays for imports
    with FileReplaySource(synthetic_file, rate_hz=200.0) as src:  # queue as long as the file: no drops by design
        stats = run_live(src, est, lambda i, f, e, lat: planes.append((f.truth, e)), queue_size=16)
    assert stats.estimated == 8 and stats.dropped == 0
    ok = [(t, e) for t, e in planes if e.ok]
    assert len(ok) >= 6
    for truth, e in ok:
        assert isinstance(e.plane, Plane)
        assert abs(e.plane.z0 - truth.z0) < 0.05                # peak is coarse; 5 cm bounds a wrong frame
    assert stats.latency_median is not None


def test_stream_command(synthetic_file, capsys):
    from place_safe.cli.app import main

    # a queue as long as the file: no frame is dropped by design, however busy the machine (no timing in tests)
    rc = main(["stream", str(synthetic_file), "--method", "peak", "--rate", "100", "--jsonl", "--queue", "8"])
    cap = capsys.readouterr()
    assert rc == 0
    lines = [json.loads(line) for line in cap.out.splitlines()]
    assert [line["index"] for line in lines] == list(range(8))
    assert all("latency_ms" in line and "normal" in line for line in lines)
    assert "dropped" in cap.err and "latency" in cap.err and "median" in cap.err


def test_stream_loop_over_a_file_without_a_usable_frame_ends_with_one_line(tmp_path, capsys):
    from place_safe.cli.app import main

    path = tmp_path / "bad.jsonl"
    path.write_text('{"hists": "garbage"}\n{"hists": [[1, 2]]}\n')
    done: list[int] = []
    run = threading.Thread(target=lambda: done.append(main(["stream", str(path), "--method", "peak", "--loop",
                                                               "--rate", "10000"])), daemon=True)
    run.start()
    run.join(60.0)
    assert done == [2]                                   # it ended (it looped for ever), as an input error
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("place-safe: error: no usable frame in a whole pass over bad.jsonl")
