"""``place-safe recover``, ``evaluate``, ``stream``, ``bench recovery`` (``place_safe.cli.sensing``): options that
go together."""

from __future__ import annotations

import json

import pytest

from place_safe.cli.app import main


@pytest.mark.parametrize("given,said", [(["--no-fallback"], "--no-fallback applies"),
                                        (["--diff-mode", "paper"], "--diff-mode applies"),
                                        (["--no-fallback", "--diff-mode", "fast"], "--no-fallback and --diff-mode apply")])
def test_evaluate_refuses_diff_options_when_diff_is_not_evaluated(sweep_path, tmp_path, capsys, given, said):
    """`evaluate --methods peak --no-fallback` (or `--diff-mode paper`) printed peak's table as if the option had not
    been given, exit 0; so did a calibration without a diff section, which leaves diff out of the default methods.
    Both options set the diff method: without it they are one usage line, exit 2, before any frame is recovered."""
    rep = tmp_path / "r.json"
    assert main(["evaluate", str(sweep_path), "--methods", "peak", "proprietary", "--no-plots", "--json", str(rep),
                 *given]) == 2
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [f"place-safe: error: evaluate: {said} to the diff method, which is not among "
                                         "the methods evaluated (peak, proprietary): name it in --methods"]
    assert captured.out == "" and not rep.exists()


def test_evaluate_says_when_its_calibration_left_diff_out_of_the_diff_options(sweep_path, tmp_path, capsys):
    """With a calibration that does not calibrate diff and no --methods, diff is left out of the default, and
    `--no-fallback` was refused as if the user had not named diff, "name it in --methods", which would run diff
    uncalibrated (a review, session 85). The line now says the calibration is why."""
    import json

    from place_safe.sim.tof import calibration_file

    d = json.loads(calibration_file("nominal").read_text())
    del d["forward"], d["diff"]
    cal = tmp_path / "peak_only.json"
    cal.write_text(json.dumps(d))
    assert main(["evaluate", str(sweep_path), "--calibration", str(cal), "--no-plots", "--no-fallback"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith(f"place-safe: error: evaluate: --no-fallback applies to the diff method, which {cal} does "
                           "not calibrate (sensor not calibrated for diff (no 'forward' section)")
    assert "name it in --methods" not in line


def test_bench_recovery_refuses_a_memory_method_without_the_memory_measurement(capsys, monkeypatch):
    """`bench recovery --memory-method peak` without --memory-file printed the table and exited 0: the method of a
    measurement not asked for was never read (round 15's leftover). One usage line, exit 2, before any frame; with
    --memory-file it is the measurement's method (default diff)."""
    import place_safe.cli.sensing as sensing

    def no_run(*args, **kwargs):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(sensing, "run_bench", no_run)
    assert main(["bench", "recovery", "--frames", "2", "--methods", "peak", "--memory-method", "peak", "-q"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == ["place-safe: error: bench recovery: --memory-method is the method of "
                                         "--memory-file's measurement, which was not given"]

    class Report:
        file_rss = None

        def table(self):
            return "table"

    measured = []
    monkeypatch.setattr(sensing, "run_bench", lambda *a, **k: Report())
    monkeypatch.setattr(sensing, "measure_file_rss", lambda n, method, calibration: measured.append(method) or {})
    for given in ([], ["--memory-method", "peak"]):
        assert main(["bench", "recovery", "--frames", "2", "--methods", "peak", "--memory-file", "16", "-q",
                     *given]) == 0
    assert measured == ["diff", "peak"]


@pytest.mark.parametrize("given,said", [
    (["--paper-frames", "3"], "--paper-frames counts the frames of the diff-paper run, which is not among --methods "
                              "(peak diff-fast)"),
    (["SWEEP", "--seed", "5"], "--seed draws the synthetic frames, and SWEEP's frames are read instead")])
def test_bench_recovery_refuses_options_its_runs_never_read(sweep_path, given, said, capsys, monkeypatch):
    """`bench recovery --methods peak diff-fast --paper-frames 3` and `bench recovery FILE --seed 5` printed the table,
    exit 0: no diff-paper run counts frames, and a FILE's frames are not drawn from a seed. One usage line, exit 2,
    before any frame; where they are read they still are (default 5 and 0)."""
    import place_safe.cli.sensing as sensing

    def no_run(*args, **kwargs):
        raise AssertionError("the benchmark ran")

    monkeypatch.setattr(sensing, "run_bench", no_run)
    argv = [str(sweep_path) if g == "SWEEP" else g for g in given]
    assert main(["bench", "recovery", "--frames", "2", "--methods", "peak", "diff-fast", "-q", *argv]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.splitlines() == ["place-safe: error: bench recovery: " + said.replace("SWEEP", str(sweep_path))]

    class Report:
        def table(self):
            return "table"

    seen = []
    monkeypatch.setattr(sensing, "run_bench", lambda frames, cal, paper_frames, runs, source, progress:
                        seen.append((paper_frames, source)) or Report())
    assert main(["bench", "recovery", "--frames", "2", "--methods", "diff-paper", "-q"]) == 0
    assert main(["bench", "recovery", "--frames", "2", "--methods", "diff-paper", "--paper-frames", "1", "--seed",
                 "4", "-q"]) == 0
    assert main(["bench", "recovery", "--frames", "2", "--methods", "peak", "--paper-frames", "0", "-q"]) == 0
    assert seen == [(5, "synthetic (make_frames, seed 0)"), (1, "synthetic (make_frames, seed 4)"),
                    (0, "synthetic (make_frames, seed 0)")]  # (0 "skips it": what is so without diff-paper)


def test_calibrate_sim_save_frames_interrupted_says_what_the_capture_kept(tmp_path, monkeypatch, capsys, sweep_path):
    """A Ctrl-C during `calibrate --sim nominal --save-frames F` left a short, readable capture and said nothing of it
    (round 16's leftover): it now says how many whole frames F keeps and how to fit them (or that F is cut and read by
    nothing), and that the calibration was not written; exit 130 as any interrupt."""
    from pathlib import Path

    import place_safe.sim.calibration_capture as cc

    frames = json.loads(Path(sweep_path).read_text())[:3]

    def interrupted(sensor, output=None, n=0, seed=0, frames_out=None, quiet=True):
        Path(frames_out).write_text("".join(json.dumps(f) + "\n" for f in frames))  # JSON Lines, as the arm's capture
        raise KeyboardInterrupt

    monkeypatch.setattr(cc, "calibrate_sim", interrupted)
    monkeypatch.chdir(tmp_path)
    assert main(["calibrate", "--sim", "nominal", "-o", "c.json", "--save-frames", "sweep.jsonl", "-q"]) == 130
    err = capsys.readouterr().err.splitlines()
    assert err == ["calibrate: interrupted: sweep.jsonl keeps the capture's 3 whole frames (fit them with 'place-safe "
                   "calibrate sweep.jsonl --method diff', or delete it); c.json was not written", "place-safe: interrupted"]
    assert not (tmp_path / "c.json").exists()

    def cut(sensor, output=None, n=0, seed=0, frames_out=None, quiet=True):
        Path(frames_out).write_text(json.dumps(frames)[:-40])  # a JSON list without its end
        raise KeyboardInterrupt

    monkeypatch.setattr(cc, "calibrate_sim", cut)
    assert main(["calibrate", "--sim", "nominal", "-o", "c.json", "--save-frames", "cut.json", "-q"]) == 130
    assert "cut.json holds a capture cut short, which no command reads (delete it)" in capsys.readouterr().err


def test_calibrate_sim_save_frames_keeps_a_file_already_there_unless_forced(tmp_path, monkeypatch, capsys):
    """`calibrate --sim nominal --save-frames sweep.json` replaced sweep.json, a frame file already there (the real
    sweep in the trial), with the simulated capture: no word, exit 0. A file there is now kept without --force (one
    usage line naming the option, exit 2, before the capture), as sensor record and synth keep theirs."""
    from pathlib import Path

    import place_safe.sim.calibration_capture as cc
    from place_safe.calibration import Calibration

    written = []

    def fake(sensor, output=None, n=0, seed=0, frames_out=None, quiet=True):
        written.append(frames_out)
        Path(frames_out).write_text("captured\n")
        Calibration().save(output)
        return Path(output)

    monkeypatch.setattr(cc, "calibrate_sim", fake)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "sweep.json").write_text("[]\n")
    assert main(["calibrate", "--sim", "nominal", "-o", "c.json", "--save-frames", "sweep.json", "-q"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "place-safe: error: calibrate: --save-frames sweep.json exists; use --force to overwrite it"]
    assert written == [] and (tmp_path / "sweep.json").read_text() == "[]\n" and not (tmp_path / "c.json").exists()
    assert main(["calibrate", "--sim", "nominal", "-o", "c.json", "--save-frames", "sweep.json", "-q", "--force"]) == 0
    assert written == ["sweep.json"] and (tmp_path / "sweep.json").read_text() == "captured\n"
    assert main(["calibrate", "--sim", "nominal", "-o", "d.json", "--save-frames", "new.jsonl", "-q"]) == 0
