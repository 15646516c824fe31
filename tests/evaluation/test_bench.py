"""Tests of place_safe.evaluation.bench and ``place-safe bench recovery``: timings, errors and memory figures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from place_safe.evaluation.bench import BenchReport, MethodResult, measure_file_rss, peak_rss_bytes, run_bench


def test_run_bench_with_peak_and_diff_fast(synthetic_frames):
    frames = synthetic_frames[:3]
    rep = run_bench(frames, runs=[("diff-fast", "diff", {"mode": "fast"}), ("peak", "peak", {})])
    assert [r.label for r in rep.results] == ["diff-fast", "peak"]
    for r in rep.results:
        assert r.error is None
        assert len(r.latencies) == 3                     # warm-up not counted
        assert r.latency_median > 0 and r.latency_p95 >= r.latency_median and r.fps > 0
        assert len(r.angular_deg) + r.failures == 3
    diff = rep.result("diff-fast")
    assert diff.failures == 0
    # on noisy synthetic frames from the same forward model the diff method is accurate
    assert max(diff.angular_deg) < 3.0 and max(diff.point_mm) < 5.0
    assert rep.speed_ratio is None                       # no paper run
    d = rep.to_dict()
    json.dumps(d)
    assert d["peak_rss_mb"] > 0 and {m["label"] for m in d["methods"]} == {"diff-fast", "peak"}
    table = rep.table()
    assert "median ms" in table and "angular deg" in table and "peak RSS" in table


def test_paper_frames_limit_and_speed_ratio():
    paper = MethodResult("diff-paper", frames=2, latencies=[10.0, 12.0])
    fast = MethodResult("diff-fast", frames=4, latencies=[0.02, 0.02, 0.03, 0.01])
    rep = BenchReport([paper, fast], 4, "test", peak_rss_bytes())
    assert rep.speed_ratio == pytest.approx(11.0 / 0.02)
    assert "speed ratio" in rep.table()


def test_unknown_or_missing_method_is_reported_not_raised(synthetic_frames, monkeypatch):
    import place_safe.evaluation.bench as bench

    def broken(method, calibration=None, **kw):
        raise ImportError("no module named x")

    monkeypatch.setattr(bench, "make_estimator", broken)  # the factory the benchmark calls
    rep = run_bench(synthetic_frames[:1], runs=[("peak", "peak", {})])
    assert rep.results[0].error and "not available" in rep.table()


@pytest.mark.slow
def test_file_rss_is_measured_in_a_fresh_process(tmp_path):
    held = np.ones(40_000_000)  # 320 MB in this process: the measured process's memory is its own, not its parent's
    fr = measure_file_rss(64, method="peak", baseline_frames=16, workdir=tmp_path)
    assert held[-1] == 1.0 and fr["peak_rss_mb"] < 250  # (peak reads 90-100 MB; ru_maxrss from here read 1.3 GB)
    assert fr["frames"] == 64 and fr["peak_rss_mb"] > 10 and fr["baseline_rss_mb"] > 10
    assert fr["file_mb"] > 0.1
    # streaming: four times the frames must not need noticeably more memory
    assert fr["peak_rss_mb"] < fr["baseline_rss_mb"] + 20


def test_bench_command(tmp_path, capsys):
    from place_safe.cli.app import main

    out = tmp_path / "bench.json"
    rc = main(["bench", "recovery", "--frames", "2", "--methods", "peak", "--json", str(out), "-q"])
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert "peak" in cap.out and "frames/s" in cap.out
    data = json.loads(out.read_text())
    assert data["methods"][0]["label"] == "peak" and data["methods"][0]["frames"] == 2


def test_bench_command_on_a_file(sweep_path, capsys):
    from place_safe.cli.app import main

    assert main(["bench", "recovery", str(sweep_path), "--frames", "5", "--methods", "peak", "-q"]) == 0
    assert "5 frames from" in capsys.readouterr().out
