"""``place-safe demo`` (``place_safe.cli.demo``): the options only one of its two shows reads."""

from __future__ import annotations

import importlib.util

import pytest

from place_safe.cli.app import main


def _nothing_runs(monkeypatch):
    """Neither show may start: a placement or the synthetic frames' drawing fails the test."""
    import place_safe.evaluation.synthetic as synthetic
    import place_safe.sim.placement_run as pr

    def ran(*args, **kwargs):
        raise AssertionError("the demo ran")

    monkeypatch.setattr(pr, "run_placement", ran)
    monkeypatch.setattr(synthetic, "make_frames", ran)


def test_demo_frames_with_the_simulated_placements_is_refused_not_ignored(monkeypatch, capsys):
    """`demo --frames 1` ran both simulated placements and exited 0: they read no frames, and --frames counts the
    synthetic ones (round 15's leftover). One usage line, exit 2, before a placement."""
    pytest.importorskip("mujoco")
    _nothing_runs(monkeypatch)
    assert main(["demo", "--frames", "1"]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.splitlines() == [
        "place-safe: error: demo: --frames counts the synthetic frames, shown only with --synthetic: the simulated "
        "placements run here and read no frames"]


def test_demo_method_with_synthetic_frames_is_refused_not_ignored(monkeypatch, capsys):
    """`demo --synthetic --method peak` recovered the frames with every method, exit 0: --method is the placements'.
    The same where the demo falls back to synthetic frames without MuJoCo. One usage line naming why, exit 2."""
    _nothing_runs(monkeypatch)
    assert main(["demo", "--synthetic", "--method", "peak", "--frames", "2"]) == 2
    cap = capsys.readouterr()
    assert cap.out == ""
    assert cap.err.splitlines() == [
        "place-safe: error: demo: --method is the simulated placements' method: with --synthetic the demo recovers "
        "synthetic frames with every method"]
    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "mujoco" else real(name, *a))
    assert main(["demo", "--method", "peak"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "place-safe: error: demo: --method is the simulated placements' method: here MuJoCo is not installed (install "
        "the [sim] extra), so the demo recovers synthetic frames with every method"]


def test_demo_reads_method_and_frames_in_their_own_shows(monkeypatch, capsys):
    """What stays: --method in the placements (default diff), --frames in the synthetic show (default 20)."""
    import place_safe.evaluation.synthetic as synthetic
    import place_safe.sim.placement_run as pr

    class Result:
        outcome = "refused"

        def summary(self):
            return "summary"

    calls = []
    monkeypatch.setattr(pr, "run_placement", lambda scenario, method, seed: calls.append(method) or Result())
    main(["demo", "-q"])
    main(["demo", "--method", "peak-naive", "-q"])
    assert calls == ["diff", "diff", "peak-naive", "peak-naive"]
    drawn = []
    real = synthetic.make_frames
    monkeypatch.setattr(synthetic, "make_frames", lambda n, seed: drawn.append(n) or real(2, seed=seed))
    assert main(["demo", "--synthetic", "-q"]) == 0
    assert main(["demo", "--synthetic", "--frames", "3", "-q"]) == 0
    assert drawn == [20, 3]
    capsys.readouterr()
