"""place / capture / calibrate-mount on the command line: one-line usage errors (exit 2) and the mount fit
written back into a robot file."""

from __future__ import annotations

import pytest

from place_safe.cli.app import main
from place_safe.drivers.ur5 import URConfig, packaged_config


@pytest.mark.parametrize("argv, match", [
    (["place", "--sim", "place_level", "--robot", "x.toml"], "not allowed with"),
    (["place"], "one of the arguments --sim --robot is required"),
    (["place", "--robot", "robots/ur5/real.toml"], "--sensor URI is required"),
    (["capture", "--sim", "level_table", "-o", "x", "--sim-mount-error", "1,2"], "expected 6"),
    (["capture", "--robot", "robots/ur5/real.toml", "--sensor", "file:x", "-o", "x"], "give the plane"),
    (["calibrate-mount", "missing.jsonl"], "missing.jsonl"),
    (["place", "--robot", "nope.toml", "--sensor", "file:x"], "nope.toml"),
    (["capture", "--sim", "level_table", "-o", "x", "--distances", "10:90:0"], "a range START:STOP:STEP"),
    (["capture", "--sim", "level_table", "-o", "x", "--distances", "90:10:2"], "STOP >= START"),
    (["capture", "--sim", "level_table", "-o", "x", "--distances", "5:90:2"], "from 10 to 5000, got '5:90:2'"),
    (["capture", "--sim", "level_table", "-o", "x", "--distances", "10:1000:5"], "at most 100 values"),
    (["capture", "--sim", "level_table", "-o", "x", "--table-tilt-std", "0.1"], "goes with --table-height"),
    (["capture", "--sim", "level_table", "-o", "x", "--table-height", "0", "--table-tilt-std", "0.1", "--touch",
      "0,0", "--touch", "0.1,0", "--touch", "0,0.1"], "not --touch"),
    (["capture", "--sim", "level_table", "-o", "x", "--table-height", "0", "--table-tilt-std", "nan"],
     "--table-tilt-std"),
    (["capture", "--sim", "level_table", "-o", "x", "--table-height", "0", "--table-tilt-std", "9"],
     "--table-tilt-std"),
])
def test_usage_errors_are_one_line(argv, match, capsys, monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    if "robots/ur5/real.toml" in argv:
        (tmp_path / "robots" / "ur5").mkdir(parents=True)
        (tmp_path / "robots" / "ur5" / "real.toml").write_text(packaged_config("real").read_text())
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and match in err[0], err


def test_capture_distances_take_ranges_with_the_stop_included():
    from place_safe.cli.robot import _distances

    assert _distances("80,120") == [80.0, 120.0]
    level = _distances("10:90:2,100:400:10")  # the level sweep of the help: 2 mm steps below 9 cm
    assert len(level) == 41 + 31 and level[:3] == [10.0, 12.0, 14.0] and 90.0 in level and level[-1] == 400.0
    assert _distances("10:15:2") == [10.0, 12.0, 14.0]  # a stop the steps do not reach is not added


def test_place_on_an_unreachable_arm_is_a_one_line_error(capsys, sweep_path, tmp_path):
    cfg = URConfig.load(packaged_config("sim"))
    cfg.connection.connect_timeout_s = 1.0
    robot = tmp_path / "r.toml"
    robot.write_text(cfg.to_toml())
    assert main(["place", "--robot", str(robot), "--sensor", f"file:{sweep_path}", "--dry-run",
                 "--json", str(tmp_path / "r.json"), "--log", str(tmp_path / "t.jsonl")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "RTDE receive at 127.0.0.1" in err[0], err


@pytest.mark.slow
def test_calibrate_mount_on_the_real_sweep_writes_a_robot_file(sweep_path, tmp_path, capsys):
    out = tmp_path / "fitted.toml"
    assert main(["calibrate-mount", str(sweep_path), "--method", "proprietary", "--write", str(out), "-q",
                 "--json", str(tmp_path / "fit.json")]) == 0
    text = capsys.readouterr().out
    assert "mount fit on" in text and "not determined by this sweep" in text
    cfg = URConfig.load(out)
    assert cfg.tool.mount_fit["frames"] >= 40 and "translation x" in cfg.tool.mount_fit["unobserved"]
    assert cfg.tool.sensor.xyz != URConfig.load(packaged_config("sim")).tool.sensor.xyz


def test_calibrate_mount_skips_and_counts_frames_without_a_usable_pose(sweep_path, tmp_path, capsys):
    """A NaN, a string and a short list of joint angles, and an unreadable frame, in a capture of 53: skipped and
    counted (one bad frame ended the fit); a capture with no usable pose at all is one line, exit 2."""
    import json

    frames = json.loads(sweep_path.read_text())
    frames[20]["joint_angles"] = [float("nan")] * 6
    frames[21]["joint_angles"] = "abc"
    frames[22]["joint_angles"] = [0.0, 1.0]
    frames[23]["hists"] = "broken"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(frames))
    assert main(["calibrate-mount", str(bad), "--method", "proprietary"]) == 0
    captured = capsys.readouterr()
    assert "4 skipped: 3 bad joint_angles, 1 unreadable" in captured.err and "mount fit on" in captured.out
    for f in frames:
        f["joint_angles"] = None
        f.pop("pose", None)
    bad.write_text(json.dumps(frames))
    assert main(["calibrate-mount", str(bad), "--method", "proprietary", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no frames with a usable flange pose" in err and "\n" not in err


from hypothesis import given, settings, strategies as st  # noqa: E402


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet="0123456789:.,-+eEinfa ", max_size=40))
def test_capture_distances_are_a_bounded_list_of_millimetres_or_one_clear_error(text):
    import argparse
    import math

    from place_safe.cli.robot import MAX_LIST, _distances

    try:
        values = _distances(text)
    except argparse.ArgumentTypeError as exc:
        assert "\n" not in str(exc) and str(exc).startswith("expected")
        return
    assert 1 <= len(values) <= MAX_LIST and all(math.isfinite(v) and 10.0 <= v <= 5000.0 for v in values)


@pytest.mark.parametrize("tilt_std", [None, 0.1])
def test_a_capture_against_a_table_height_states_the_tables_levelness_only_when_told(tilt_std, tmp_path, capsys):
    """``--table-height`` takes the table as level in the base frame: with ``--table-tilt-std`` the frames say how far
    it may be off (the calibration keeps it as its reference, fusion adds it); without, a note says it is taken as
    exact."""
    import json
    import math

    out = tmp_path / "cap.jsonl"
    argv = ["capture", "--sim", "level_table", "--table-height", "0.0", "--poses", "1", "--settle", "0.01", "-q",
            "-o", str(out)] + ([] if tilt_std is None else ["--table-tilt-std", str(tilt_std)])
    assert main(argv) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    refs = [r["meta"]["base_plane"].get("reference") for r in rows]
    if tilt_std is None:
        assert refs and all(r is None for r in refs)
        assert "taken as exactly level" in capsys.readouterr().err
    else:
        assert refs and all(r["tilt_std"] == pytest.approx(math.radians(0.1)) and r["points"] == 0 for r in refs)


def test_options_of_the_arm_are_refused_with_sim(capsys):
    """place --sim with --sensor or --dry-run ran the simulation and released without a word about them."""
    for argv in (["place", "--sim", "place_level", "--sensor", "bogus"], ["place", "--sim", "place_level", "--dry-run"],
                 ["capture", "--sim", "level_table", "--dry-run", "-o", "x.jsonl"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "is for the arm (--robot ROBOT.toml), not --sim" in err and "\n" not in err
