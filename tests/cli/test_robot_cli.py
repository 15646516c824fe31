"""place / capture / calibrate-mount on the command line: one-line usage errors (exit 2) and the mount fit
written back into a robot file."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

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
    (["capture", "--sim", "level_table", "-o", "x", "--table-tilt-std", "0.1"],
     "--table-tilt-std goes with --table-height (how far"),
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


@pytest.mark.parametrize("argv, option", [
    (["capture", "--sim", "level_table", "--incidences", "0,,12"], "--incidences"),
    (["capture", "--sim", "level_table", "--azimuths", ",0"], "--azimuths"),
    (["capture", "--sim", "level_table", "--distances", "80,120,"], "--distances"),
    (["capture", "--sim", "level_table", "--distances", "10:90:2,,100"], "--distances"),
    (["capture", "--sim", "level_table", "--table-height", "0", "--touch", "0.1,,0.2"], "--touch"),
    (["place", "--sim", "place_level", "--sim-mount-error", "1,2,,3,4,5,6"], "--sim-mount-error"),
])
def test_an_empty_item_in_a_comma_list_is_refused_naming_the_option(argv, option, tmp_path, capsys, monkeypatch):
    """``capture --incidences 0,,12`` read as ``0,12``: the empty item was dropped without a word (session 83). An empty
    item in any comma-separated option (between commas or at an end) is one line naming the option, exit 2, and nothing
    written (``place``'s default result files included)."""
    from place_safe.cli.robot import _distances, _floats

    monkeypatch.chdir(tmp_path)
    out = tmp_path / "cap.jsonl"
    assert main([*argv, "-o", str(out)] if argv[0] == "capture" else argv) == 2
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert captured.out == "" and len(err) == 1 and not out.exists(), err
    assert f"argument {option}: expected comma-separated " in err[0] and "with no empty item" in err[0], err
    assert _floats("0, 12") == [0.0, 12.0] and _distances("80 ,120") == [80.0, 120.0]  # spaces are no items
    assert not (tmp_path / "place-result.json").exists() and not (tmp_path / "place-transitions.jsonl").exists()


@pytest.mark.parametrize("argv, option, value", [
    (["--distances", "80,80"], "--distances", "80 mm"),
    (["--distances", "80,80.0"], "--distances", "80 mm"),
    (["--distances", "10:90:2,90:200:10"], "--distances", "90 mm"),  # ranges that overlap
    (["--incidences", "0,12,12"], "--incidences", "12 deg"),
    (["--azimuths", "0,360"], "--azimuths", "360 deg"),  # one direction
    (["--azimuths=-60,300"], "--azimuths", "300 deg"),
])
def test_a_repeated_item_of_a_sweep_plan_is_refused_naming_the_option_and_value(argv, option, value, tmp_path, capsys,
                                                                                 monkeypatch):
    """``capture --distances 80,80`` captured the 80 mm poses twice (round 13's leftover): a plan's distances, incidences
    and azimuths are sets of poses, and a repeat is a typo or ranges that overlap. One line naming the option and the
    repeated value, exit 2, nothing written; as an empty item is (:func:`place_safe.cli.robot._items`)."""
    monkeypatch.chdir(tmp_path)
    out = tmp_path / "cap.jsonl"
    assert main(["capture", "--sim", "level_table", *argv, "-o", str(out)]) == 2
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert captured.out == "" and len(err) == 1 and not out.exists(), err
    assert f"argument {option}: {value} is given twice" in err[0] and "--frames-per-pose" in err[0], err


def test_a_sweep_plan_refuses_a_repeated_pose_axis_value():
    """The library face of the same rule: a :class:`SweepPlan` with a repeated distance, incidence or azimuth (azimuths
    a turn apart are one) is one ConfigError naming the field; the defaults and distinct values are taken."""
    import math

    from place_safe.calibration.capture import SweepPlan
    from place_safe.exceptions import ConfigError

    SweepPlan()
    SweepPlan(distances=[0.08, 0.0800001], azimuths=[0.0, math.pi, -math.pi / 2])
    for field, values in (("distances", [0.08, 0.12, 0.08]), ("incidences", [0.0, 0.2, 0.2]),
                          ("azimuths", [0.0, 2 * math.pi]), ("azimuths", [-math.pi / 2, 3 * math.pi / 2])):
        with pytest.raises(ConfigError, match=f"sweep plan: {field}: .* given twice"):
            SweepPlan(**{field: values})


@pytest.mark.parametrize("argv, dest, value", [
    (["capture", "--sim", "level_table", "-o", "x", "--touch", "-0.45,-0.05"], "touch", [[-0.45, -0.05]]),
    (["capture", "--sim", "level_table", "-o", "x", "--azimuths", "-60,120"], "azimuths", [-60.0, 120.0]),
    (["capture", "--sim", "level_table", "-o", "x", "--sim-mount-error", "-5,0,0,0,2,0"], "sim_mount_error",
     [-0.005, 0.0, 0.0, 0.0, pytest.approx(0.0349066), 0.0]),
    (["capture", "--sim", "level_table", "-o", "x", "--table-height", "-1e-3"], "table_height", -0.001),
    (["place", "--sim", "place_level", "--sim-mount-error", "-1.5,0,0,0,0,-2"], "sim_mount_error",
     [-0.0015, 0.0, 0.0, 0.0, 0.0, pytest.approx(-0.0349066)]),
])
def test_a_value_that_begins_with_a_minus_sign_is_a_value(argv, dest, value):
    """``capture --touch -0.45,-0.05`` (the capture help's own example) ended "argument --touch: expected one argument":
    argparse takes only ``-5`` and ``-0.5`` for values, and read a negative comma list or ``-1e-3`` as an unknown
    option (round 14). They are values now (``cli.common.NEGATIVE_VALUE``)."""
    from place_safe.cli.app import build_parser

    assert getattr(build_parser(load_sim=False).parse_args(argv), dest) == value


def test_minus_inf_is_refused_by_the_option_not_read_as_an_option(capsys):
    assert main(["capture", "--sim", "level_table", "-o", "x", "--table-height", "-inf"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and "argument --table-height: expected a finite number, got '-inf'" in err[0], err


@pytest.mark.parametrize("speed", ["1e-9", "1e-320", "0.001"])
def test_a_capture_speed_that_would_never_arrive_is_refused(speed, capsys):
    """``capture --speed 1e-9`` was taken (any speed above 0) and the first move never ended: a 0.3 m move at 1e-9 m/s
    takes 3e8 s, and in simulation the command ran on with no output until killed (round 14). The plan's speed is at
    least the touch's guarded descent speed (``calibration.capture.MIN_SPEED``), on the command line and in a
    :class:`SweepPlan` (its acceleration too: ``MIN_ACCEL``)."""
    from place_safe.calibration.capture import MIN_ACCEL, MIN_SPEED, SweepPlan
    from place_safe.cli.app import build_parser
    from place_safe.exceptions import ConfigError, UsageError

    with pytest.raises(UsageError, match=f"argument --speed: expected a number >= {MIN_SPEED:g} and <= 1"):
        build_parser(load_sim=False).parse_args(["capture", "--sim", "level_table", "-o", "x", "--speed", speed])
    with pytest.raises(ConfigError, match="sweep plan: speed"):
        SweepPlan(speed=float(speed))
    with pytest.raises(ConfigError, match="sweep plan: accel"):
        SweepPlan(accel=MIN_ACCEL / 10)
    assert SweepPlan(speed=MIN_SPEED, accel=MIN_ACCEL).speed == MIN_SPEED


@settings(max_examples=300, deadline=None)
@given(st.lists(st.floats(-360.0, 360.0, allow_nan=False), min_size=1, max_size=8))
def test_an_azimuth_list_reads_back_exactly_or_is_one_repeat_line(values):
    """Any list of azimuths written as Python writes floats (negative first items, exponents, -0.0 included) reads back
    as the same numbers, or, where two are one direction (a turn apart, within 1e-6 deg), is one line naming the
    repeat; what the command line takes, a :class:`SweepPlan` takes (round 14: a leading minus sign, repeats)."""
    import math

    from place_safe.calibration.capture import SweepPlan
    from place_safe.cli.app import build_parser
    from place_safe.exceptions import UsageError

    text = ",".join(repr(v) for v in values)
    repeat = any(min(abs(a - b) % 360.0, 360.0 - abs(a - b) % 360.0) <= 1e-6
                 for i, a in enumerate(values) for b in values[:i])
    argv = ["capture", "--sim", "level_table", "-o", "x", "--azimuths", text]
    if repeat:
        with pytest.raises(UsageError, match="argument --azimuths: .* is given twice in "):
            build_parser(load_sim=False).parse_args(argv)
    else:
        got = build_parser(load_sim=False).parse_args(argv).azimuths
        assert got == values
        SweepPlan(azimuths=[math.radians(v) for v in got])


def test_place_on_an_unreachable_arm_is_a_one_line_error(capsys, sweep_path, tmp_path):
    cfg = URConfig.load(packaged_config("sim"))
    cfg.connection.connect_timeout_s = 1.0
    robot = tmp_path / "r.toml"
    robot.write_text(cfg.to_toml())
    assert main(["place", "--robot", str(robot), "--sensor", f"file:{sweep_path}", "--dry-run",
                 "--json", str(tmp_path / "r.json"), "--log", str(tmp_path / "t.jsonl")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "RTDE receive at 127.0.0.1" in err[0], err


def test_place_on_the_arm_needs_a_calibration_before_anything_connects(capsys, sweep_path, tmp_path):
    """Built-in constants read a level table degrees off: on the arm a placement without --calibration is a usage
    error before the robot is reached (the UNCALIBRATED note came only after the run); a dry run, which moves
    nothing, and --uncalibrated still run, with the note first on standard output."""
    cfg = URConfig.load(packaged_config("sim"))
    cfg.connection.connect_timeout_s = 1.0
    robot = tmp_path / "r.toml"
    robot.write_text(cfg.to_toml())
    common = ["place", "--robot", str(robot), "--sensor", f"file:{sweep_path}", "--json", str(tmp_path / "r.json"),
              "--log", str(tmp_path / "t.jsonl")]
    assert main(common) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs its calibration" in err[0] and "--uncalibrated" in err[0], err
    for extra in (["--dry-run"], ["--uncalibrated"]):
        assert main(common + extra) == 2  # nothing listens at 127.0.0.1: it got as far as the arm
        captured = capsys.readouterr()
        assert captured.out.startswith("UNCALIBRATED") and "RTDE receive at 127.0.0.1" in captured.err
    assert main(["place", "--sim", "place_level", "--uncalibrated"]) == 2
    assert "is for the arm" in capsys.readouterr().err


def _place_on_the_arm_with_a_cut_calibration(tmp_path, sweep_path, name: str, cut):
    """``place --robot`` arguments with the packaged nominal calibration less what ``cut`` takes out of its dict, written
    to ``tmp_path / name``, the real sweep as the sensor and the simulated robot file (giving up on connecting after
    1 s); with the calibration's path, the robot file's and the cut dict."""
    import json

    from place_safe.sim.tof import calibration_file

    d = json.loads(calibration_file("nominal").read_text())
    cut(d)
    path = tmp_path / name
    path.write_text(json.dumps(d))
    cfg = URConfig.load(packaged_config("sim"))
    cfg.connection.connect_timeout_s = 1.0
    robot = tmp_path / "r.toml"
    robot.write_text(cfg.to_toml())
    common = ["place", "--robot", str(robot), "--sensor", f"file:{sweep_path}", "--calibration", str(path),
              "--json", str(tmp_path / "r.json"), "--log", str(tmp_path / "t.jsonl")]
    return common, path, robot, d


def test_place_on_the_arm_refuses_a_calibration_without_the_uncertainty_its_method_reads(capsys, sweep_path, tmp_path):
    """A calibration without ``uncertainty.diff`` counted as calibrated on the arm: diff's planes carried the fit's
    covariance alone and never fell back to peak. Now it is a usage error naming the file and the entry before the
    robot is reached (``placement_reason``); --dry-run runs with an UNCALIBRATED line that names the entry."""
    common, cut, _, _ = _place_on_the_arm_with_a_cut_calibration(tmp_path, sweep_path, "nounc.json",
                                                                 lambda d: d["uncertainty"].pop("diff"))
    assert main(common) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(cut) in err[0] and "'uncertainty.diff'" in err[0] and "RTDE" not in err[0], err
    assert main(common + ["--dry-run"]) == 2  # nothing listens at 127.0.0.1: it got as far as the arm
    captured = capsys.readouterr()
    first = captured.out.splitlines()[0]
    assert first.startswith(f"UNCALIBRATED: {cut}: sensor's uncertainty not calibrated") and "'uncertainty.diff'" in first
    assert "RTDE receive at 127.0.0.1" in captured.err


def test_place_on_the_arm_refuses_a_calibration_without_the_methods_section(capsys, sweep_path, tmp_path):
    """A calibration with diff's forward section but no peak section (diff's start and fallback) counted as calibrated
    on the arm, where round 15 made the simulated placement, recover and evaluate say otherwise: the arm ran diff on
    peak's built-in constants (14-16 deg off on level real frames) with "calibrated": true (a review, session 85).
    Now it is the same usage error as no calibration, naming the file and the section, before the robot is reached;
    --dry-run runs with the UNCALIBRATED note naming the section. calibrate-mount marks its result the same way."""
    import json

    from place_safe.sim.tof import calibration_file

    common, nopeak, robot, d = _place_on_the_arm_with_a_cut_calibration(tmp_path, sweep_path, "nopeak.json",
                                                                        lambda d: d.pop("peak"))
    assert main(common) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(nopeak) in err[0] and "no 'peak' section" in err[0] and "RTDE" not in err[0], err
    assert main(common + ["--dry-run"]) == 2  # nothing listens at 127.0.0.1: it got as far as the arm
    captured = capsys.readouterr()
    assert captured.out.startswith("UNCALIBRATED") and "no peak section" in captured.out.splitlines()[0]
    assert "RTDE receive at 127.0.0.1" in captured.err
    assert main(common[:1] + ["--robot", str(robot), "--sensor", f"file:{sweep_path}", "--calibration",
                              str(calibration_file("nominal")), "--dry-run"]) == 2  # the whole file: no note
    assert not capsys.readouterr().out.startswith("UNCALIBRATED")
    del d["proprietary"]
    noprop = tmp_path / "noprop.json"
    noprop.write_text(json.dumps(d))
    assert main(["calibrate-mount", str(sweep_path), "--method", "proprietary", "--calibration", str(noprop), "-q",
                 "--json", str(tmp_path / "fit.json"), "--level"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("UNCALIBRATED") and "no proprietary section" in out.splitlines()[0]
    assert json.loads((tmp_path / "fit.json").read_text())["calibrated"] is False


@pytest.mark.slow
def test_calibrate_mount_on_the_real_sweep_writes_a_robot_file(sweep_path, tmp_path, capsys):
    """Uncalibrated planes (5.8 deg residual RMS on the real sweep, 6.9 with --level: the estimator's own bias) pass the
    quality gate only with --force."""
    out = tmp_path / "fitted.toml"
    assert main(["calibrate-mount", str(sweep_path), "--method", "proprietary", "--write", str(out), "-q",
                 "--json", str(tmp_path / "fit.json"), "--force", "--level"]) == 0  # without it nothing is determined
    captured = capsys.readouterr()
    text = captured.out
    assert "mount fit on" in text and "not determined by this sweep" in text
    assert "writing a fit with residual RMS 6." in captured.err and "(--force)" in captured.err
    cfg = URConfig.load(out)
    assert cfg.tool.mount_fit["frames"] >= 40 and "translation x" in cfg.tool.mount_fit["unobserved"]
    assert cfg.tool.sensor.xyz != URConfig.load(packaged_config("sim")).tool.sensor.xyz


def test_calibrate_mount_does_not_write_a_poor_fit(sweep_path, tmp_path, capsys):
    """Flange poses that do not belong to the frames (wrist joints off by up to 34 deg): a fit at 28 deg residual RMS
    was written into the robot file. Now the report is printed, one line says the residuals and the limits, the robot
    file is left untouched and the exit status is 1; --force writes it."""
    import json
    import math
    import random

    from place_safe.calibration.mount import MAX_RMS_ANGLE, MAX_RMS_DISTANCE

    frames = json.loads(sweep_path.read_text())
    rng = random.Random(0)
    for f in frames:
        f["joint_angles"] = [q + (rng.uniform(-0.6, 0.6) if k in (3, 4) else 0.0)
                             for k, q in enumerate(f["joint_angles"])]
    capture = tmp_path / "scrambled.json"
    capture.write_text(json.dumps(frames))
    robot = tmp_path / "robot.toml"
    robot.write_text(packaged_config("sim").read_text())
    before = robot.read_text()
    argv = ["calibrate-mount", str(capture), "--method", "proprietary", "-q", "--write", str(robot),
            "--json", str(tmp_path / "fit.json")]
    assert main(argv) == 1
    captured = capsys.readouterr()
    assert "mount fit on" in captured.out  # the report either way
    fit = json.loads((tmp_path / "fit.json").read_text())
    assert fit["rms_angle"] > MAX_RMS_ANGLE and fit["rms_distance"] > MAX_RMS_DISTANCE
    assert captured.err.splitlines() == [
        f"place-safe: error: calibrate-mount: not writing a fit with residual RMS {math.degrees(fit['rms_angle']):.2f} "
        f"deg (normal) > 1 deg and {fit['rms_distance'] * 1000:.2f} mm (distance) > 2 mm: {robot} left untouched "
        "(check the capture and the sensor's calibration; --force writes it anyway)"]
    assert robot.read_text() == before
    assert main([*argv, "--force"]) == 0
    assert robot.read_text() != before and "(--force)" in capsys.readouterr().err
    commented = [line for line in before.splitlines() if "#" in line]
    assert commented and all(line in robot.read_text().splitlines() for line in commented)  # the file's comments stay


def test_calibrate_mount_on_a_capture_that_determines_nothing_is_one_line_exit_2(sweep_path, tmp_path, capsys):
    """The real sweep (straight down over one table) without --level determines none of the mount's six parameters:
    the command printed the starting mount as the fit, all six "not determined by this sweep", exit 0, and --write
    --force wrote it. Now one line, exit 2, saying which poses and options would determine them; nothing written."""
    robot = tmp_path / "robot.toml"
    robot.write_text(packaged_config("sim").read_text())
    before = robot.read_text()
    fit_json = tmp_path / "fit.json"
    assert main(["calibrate-mount", str(sweep_path), "--method", "proprietary", "-q", "--write", str(robot),
                 "--force", "--json", str(fit_json)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.splitlines() == [
        f"place-safe: error: calibrate-mount: {sweep_path} determines none of the mount's six parameters: poses tilted "
        "at several azimuths would (capture's default --incidences 0,12,24 --azimuths every 60); a straight-down sweep "
        "needs --level for the tilt and, with it, --table-height for the height; the robot file is not written"]
    assert robot.read_text() == before and not fit_json.exists()
    assert main(["calibrate-mount", str(sweep_path), "--method", "proprietary", "-q", "--level"]) == 0  # the tilt
    out = capsys.readouterr().out
    assert "not determined by this sweep" in out and "rotation about x" not in out  # --level determines the tilt


def test_calibrate_mount_force_goes_with_write(sweep_path, capsys):
    assert main(["calibrate-mount", str(sweep_path), "--method", "peak", "--force"]) == 2
    assert capsys.readouterr().err.splitlines() == ["place-safe: error: calibrate-mount: --force goes with --write"]


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
    assert main(["calibrate-mount", str(bad), "--method", "proprietary", "--level"]) == 0  # (--level: the tilt)
    captured = capsys.readouterr()
    assert "4 skipped: 3 bad joint_angles, 1 unreadable" in captured.err and "mount fit on" in captured.out
    for f in frames:
        f["joint_angles"] = None
        f.pop("pose", None)
    bad.write_text(json.dumps(frames))
    assert main(["calibrate-mount", str(bad), "--method", "proprietary", "-q"]) == 2
    err = capsys.readouterr().err.strip()
    assert "no frames with a usable flange pose" in err and "\n" not in err




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
    argv = ["capture", "--sim", "level_table", "--table-height", "-0.05", "--poses", "1", "--settle", "0.01", "-q",
            "-o", str(out)] + ([] if tilt_std is None else ["--table-tilt-std", str(tilt_std)])
    assert main(argv) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    refs = [r["meta"]["base_plane"].get("reference") for r in rows]
    if tilt_std is None:
        assert refs and all(r is None for r in refs)
        assert "taken as exactly level" in capsys.readouterr().err
    else:
        assert refs and all(r["tilt_std"] == pytest.approx(math.radians(0.1)) and r["points"] == 0 for r in refs)


@pytest.mark.parametrize("scenario, height, extra", [("level_table", "0.0", []), ("level_table", "-0.0485", []),
                                                     ("tilted_table", "0.0", ["--table-tilt-std", "1"])])
def test_capture_sim_refuses_a_table_height_the_scene_does_not_have(scenario, height, extra, tmp_path, capsys):
    """capture --sim --table-height 0 over level_table (its table top at z = -0.05 m in the base frame) wrote 0 as
    every frame's ground truth, 50 mm off, and placed the sensor 50 mm off its distances; so did a level table stated
    over a tilted one. Now one usage line before the arm moves, and no capture file."""
    out = tmp_path / "cap.jsonl"
    assert main(["capture", "--sim", scenario, "--table-height", height, *extra, "--poses", "1", "-q",
                 "-o", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"place-safe: error: capture: --table-height {float(height):g} "
                                               "disagrees with the scenario's table (z = "), err
    assert err[0].endswith("leave it out to use the scenario's table") and not out.exists()


def test_capture_into_a_file_that_is_not_a_capture_is_refused_before_the_arm(tmp_path, capsys, monkeypatch):
    """capture -o FILE where FILE is not a capture to resume (a frame file, a calibration) was refused only when the
    sweep began: after the scene was built (or the arm connected, and with --touch after three touches), with the
    scenario's table note as a second line on standard error. Now one line before anything else, the file untouched."""
    import place_safe.sim.world as world

    def no_world(*args, **kwargs):
        raise AssertionError("the scene was built")

    monkeypatch.setattr(world, "sim_world", no_world)
    out = tmp_path / "frames.json"
    out.write_text('[{"hists": []}]\n')
    assert main(["capture", "--sim", "level_table", "--poses", "1", "-q", "-o", str(out)]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"place-safe: error: {out} exists and is not a capture to resume"), err
    assert out.read_text() == '[{"hists": []}]\n'



@pytest.mark.parametrize("given,said", [(["--touch-height", "0.05"], "--touch-height goes"),
                                        (["--touch-force", "20"], "--touch-force goes"),
                                        (["--touch-height", "0.05", "--touch-force", "20"],
                                         "--touch-height and --touch-force go")])
def test_touch_options_without_touch_points_are_refused_not_ignored(given, said, tmp_path, capsys, monkeypatch):
    """`capture --sim level_table --touch-height 0.05` (or --touch-force) captured against the scenario's table, exit
    0, as if the option had not been given; on the arm, against --table-height. They set the touches: without
    --touch they are one usage line, exit 2, before the scene is built or the arm connected."""
    import place_safe.sim.world as world

    def no_world(*args, **kwargs):
        raise AssertionError("the scene was built")

    monkeypatch.setattr(world, "sim_world", no_world)
    out = tmp_path / "cap.jsonl"
    assert main(["capture", "--sim", "level_table", "--poses", "1", "-q", "-o", str(out), *given]) == 2
    assert capsys.readouterr().err.splitlines() == [
        f"place-safe: error: capture: {said} with --touch (the points where the TCP touches the table); without it "
        "the plane is not touched"]
    assert not out.exists()

def test_options_of_the_arm_are_refused_with_sim(capsys):
    """place --sim with --sensor or --dry-run ran the simulation and released without a word about them."""
    for argv in (["place", "--sim", "place_level", "--sensor", "bogus"], ["place", "--sim", "place_level", "--dry-run"],
                 ["capture", "--sim", "level_table", "--dry-run", "-o", "x.jsonl"]):
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert "is for the arm (--robot ROBOT.toml), not --sim" in err and "\n" not in err



@pytest.mark.parametrize("command", ["place", "capture"])
@pytest.mark.parametrize("option", [["--seed", "3"], ["--sim-mount-error", "5,0,0,0,2,0"],
                                    ["--robot-file", "robots/ur5/real.toml"]])
def test_options_of_the_simulation_are_refused_with_the_arm(command, option, capsys, monkeypatch, tmp_path):
    """`place --robot R --seed 3` (or --sim-mount-error, --robot-file) went on to open the sensor and connect to the
    arm as if the option had not been given: the simulation's options were never read there. Now one line naming
    the option, exit 2, before the sensor or the arm is touched (as --oracle and --render were)."""
    import place_safe.sources

    def no_sensor(*args, **kwargs):
        raise AssertionError("the sensor was opened")

    monkeypatch.setattr(place_safe.sources, "open_source", no_sensor)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "robots" / "ur5").mkdir(parents=True)
    (tmp_path / "robots" / "ur5" / "real.toml").write_text(packaged_config("real").read_text())
    extra = ["--json", "r.json", "--log", "t.jsonl"] if command == "place" else ["--table-height", "0", "-o", "c.jsonl"]
    assert main([command, "--robot", "robots/ur5/real.toml", "--sensor", "i2c:/dev/i2c-1", "--dry-run", *option,
                 *extra]) == 2
    assert capsys.readouterr().err.splitlines() == [f"place-safe: error: {command}: {option[0]} is for the simulation "
                                                    "(--sim SCENARIO)"]


@pytest.mark.parametrize("calibration", ["none", "sim", "CAL"])
def test_place_sim_refuses_a_calibration_with_the_oracle_not_ignores_it(calibration, capsys, monkeypatch, tmp_path):
    """`place --sim place_level --oracle --calibration C` checked C, then placed with the simulator's true parameters
    and released, exit 0: the calibration was never read, --calibration none (an uncalibrated run) neither. One usage
    line, exit 2, before the placement."""
    import place_safe.sim.placement_run as pr
    from place_safe.sim.tof import calibration_file

    def no_run(*args, **kwargs):
        raise AssertionError("the placement ran")

    monkeypatch.setattr(pr, "run_placement", no_run)
    cal = str(calibration_file("nominal")) if calibration == "CAL" else calibration
    assert main(["place", "--sim", "place_level", "--oracle", "--calibration", cal, "--json", str(tmp_path / "r.json"),
                 "--log", str(tmp_path / "t.jsonl")]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "place-safe: error: place: --oracle gives the estimator the simulator's true sensor parameters in place of a "
        "calibration: --calibration does not go with it"]
    assert not (tmp_path / "r.json").exists()


def test_a_render_name_pillow_cannot_write_is_refused_before_the_placement(tmp_path, capsys, monkeypatch):
    """`place --sim place_level --render x.txt` ran the whole placement, then ended "invalid input: unknown file
    extension: .txt": no result file and no transition log written, the option not named. Now one line before the
    run, exit 2."""
    import place_safe.sim.placement_run as placement_run

    def no_run(*args, **kwargs):
        raise AssertionError("the placement ran")

    monkeypatch.setattr(placement_run, "run_placement", no_run)
    monkeypatch.chdir(tmp_path)
    assert main(["place", "--sim", "place_level", "--render", "x.txt"]) == 2
    assert capsys.readouterr().err.splitlines() == [
        "place-safe: error: place: --render x.txt names no image format Pillow writes (.txt): give a .png file"]
    assert not (tmp_path / "place-result.json").exists()

class _Source:
    """A stand-in for the sensor: it records how it was opened and that it was closed."""

    opened: list = []

    def __init__(self, uri: str, options: dict) -> None:
        self.uri, self.options, self.closed = uri, options, False
        _Source.opened.append(self)

    def close(self) -> None:
        self.closed = True


@pytest.mark.parametrize("command", ["place", "capture"])
def test_place_and_capture_take_the_sensor_options_of_sensor(command, capsys, monkeypatch, tmp_path):
    """The factory calibration (--calibration-dir) and the INT line (--int-line) could reach only `sensor`: place and
    capture opened the bare URI. Now they take the same sensor options and pass them to open_source (the arm, which
    does not answer here, comes after: exit 2 with its one line), and the sensor is closed when the arm fails."""
    import place_safe.sources

    _Source.opened = []
    monkeypatch.setattr(place_safe.sources, "open_source", lambda uri, **options: _Source(uri, options))
    cfg = URConfig.load(packaged_config("sim"))
    cfg.connection.connect_timeout_s = 1.0
    robot = tmp_path / "r.toml"
    robot.write_text(cfg.to_toml())
    extra = (["--json", str(tmp_path / "r.json"), "--log", str(tmp_path / "t.jsonl")] if command == "place" else
             ["--table-height", "0", "-o", str(tmp_path / "c.jsonl")])
    assert main([command, "--robot", str(robot), "--sensor", "i2c:/dev/i2c-1@0x41", "--dry-run",
                 "--calibration-dir", str(tmp_path / "cal"), "--int-line", "/dev/gpiochip0:17", "--period-ms", "100",
                 *extra]) == 2
    assert "RTDE receive at 127.0.0.1" in capsys.readouterr().err
    [src] = _Source.opened
    assert src.uri == "i2c:/dev/i2c-1@0x41" and src.closed
    assert src.options == {"calibration_dir": str(tmp_path / "cal"), "int_line": "/dev/gpiochip0:17",
                           "period_ms": 100}


@pytest.mark.parametrize("argv, line", [
    (["place", "--robot", "robots/ur5/real.toml", "--sensor", "file:x.json", "--int-line", "/dev/gpiochip0:17"],
     "place: --int-line does not apply to file: sources (only to i2c:)"),
    (["capture", "--robot", "robots/ur5/real.toml", "--sensor", "serial:/dev/ttyACM0", "--table-height", "0",
      "-o", "x.jsonl", "--calibration-dir", "cal"],
     "capture: --calibration-dir does not apply to serial: sources (only to i2c: and emu:)"),
    (["sensor", "info", "emu:synthetic:1", "--int-line", "/dev/gpiochip0:17"],
     "sensor: --int-line does not apply to emu: sources (only to i2c:)"),
    (["place", "--sim", "place_level", "--calibration-dir", "cal"],
     "place: --calibration-dir is for the arm (--robot ROBOT.toml), not --sim"),
])
def test_a_sensor_option_the_source_does_not_take_is_the_same_one_line_error_everywhere(argv, line, capsys,
                                                                                         monkeypatch, tmp_path):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "robots" / "ur5").mkdir(parents=True)
    (tmp_path / "robots" / "ur5" / "real.toml").write_text(packaged_config("real").read_text())
    assert main(argv) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith(f"place-safe: error: {line}"), err


def test_capture_lists_each_refused_pose_once(tmp_path, capsys):
    """Poses the gripper's tips cannot reach were listed on standard error as the sweep met them and again with the
    result on standard output; now once, with the result."""
    out = tmp_path / "cap.jsonl"
    assert main(["capture", "--sim", "level_table", "--table-height", "-0.05", "--incidences", "0", "--azimuths", "0",
                 "--distances", "10,20,100", "--settle", "0.01", "-q", "-o", str(out)]) == 0
    captured = capsys.readouterr()
    both = captured.out + captured.err
    assert both.count("refused pose 0:") == 1 and both.count("refused pose 1:") == 1 and "pose 2" not in both
    assert "pose 0 refused" not in captured.err and "2 refused" in captured.out


def test_a_capture_whose_every_pose_is_refused_is_one_error_line_and_writes_nothing(tmp_path, capsys):
    """Every pose refused (too close for the gripper's tips here; 5 m away, unreachable, in the round that found it):
    exit 0 with an empty output file, which calibrate then called empty (session 82). One line naming the count and
    the first refusal, exit 2, nothing on standard output, no file (one pose captured of three: exit 0, as before:
    test_capture_lists_each_refused_pose_once)."""
    out = tmp_path / "cap.jsonl"
    argv = ["capture", "--sim", "level_table", "--table-height", "-0.05", "--incidences", "0", "--azimuths", "0",
            "--distances", "10,20", "--settle", "0.01", "-q", "-o", str(out)]
    assert main(argv) == 2
    captured = capsys.readouterr()
    err = captured.err.splitlines()
    assert captured.out == "" and len(err) == 1 and not out.exists()
    assert err[0].startswith("place-safe: error: capture: every pose was refused (2 of 2; the first, pose 0: ")
    assert err[0].endswith(f"): nothing captured, {out} not written")


@pytest.mark.sim
def test_a_capture_resumed_with_other_options_is_refused_before_the_arm(tmp_path, capsys):
    """``capture -o C --distances 5000`` on a capture made with the defaults said "2 already there" and captured
    nothing (session 82): one line naming the first pose that differs, exit 2, the file left as it was."""
    out = tmp_path / "cap.jsonl"
    argv = ["capture", "--sim", "level_table", "--poses", "2", "--settle", "0.01", "-q", "-o", str(out)]
    assert main(argv) == 0
    before = out.read_bytes()
    capsys.readouterr()
    assert main([*argv, "--distances", "5000"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and captured.err.splitlines() == [
        f"place-safe: error: capture: {out} was captured with other options (pose 0 there is at 80 mm, incidence 0 "
        "deg, azimuth 0 deg; this plan's pose 0 at 5000 mm, 0 deg, 0 deg): resume it with the --distances, "
        "--incidences, --azimuths and --poses it was made with, or give another output"]
    assert out.read_bytes() == before
    assert main(argv) == 0 and out.read_bytes() == before  # the same options: resumed, nothing left to do


@pytest.mark.sim
def test_capture_reads_its_output_once(tmp_path, capsys, monkeypatch):
    """capture read its output four times before capturing (the "is it a capture" check, the resume check here and in
    capture_sweep, then the indices with the cut of an unfinished line: session 83); once now, the resume unchanged."""
    import builtins
    import json

    import place_safe.calibration.capture as capture

    out = tmp_path / "cap.jsonl"
    argv = ["capture", "--sim", "level_table", "--poses", "2", "--settle", "0.01", "-q", "-o", str(out)]
    first = [*argv[:4], "1", *argv[5:]]
    assert main(first) == 0
    out.write_text(out.read_text() + '{"hists": [[1, 2')  # an interrupted run's last line
    capsys.readouterr()
    reads = []

    def counting_open(file, mode="r", *args, **kwargs):
        if str(file) == str(out) and "r" in mode and "+" not in mode:
            reads.append(mode)
        return builtins.open(file, mode, *args, **kwargs)

    monkeypatch.setattr(capture, "open", counting_open, raising=False)
    assert main(argv) == 0
    assert len(reads) == 1, reads
    assert "1 poses captured now, 1 already there" in capsys.readouterr().out
    lines = out.read_text().splitlines()
    assert lines and all(json.loads(x)["meta"]["pose_index"] in (0, 1) for x in lines)


def test_a_capture_that_ends_early_still_lists_the_poses_it_refused(tmp_path, capsys, monkeypatch):
    """Without a result (a fault, Ctrl-C) the refused poses held back for it are written to standard error."""
    import place_safe.calibration.capture as capture
    from place_safe.exceptions import RobotFault

    def ends_early(*args, on_refused=None, **kw):
        on_refused({"pose_index": 3, "distance": 0.01, "incidence": 0.0, "azimuth": 0.0, "reason": "too close"})
        raise RobotFault("protective stop")

    monkeypatch.setattr(capture, "capture_sweep", ends_early)
    assert main(["capture", "--sim", "level_table", "--table-height", "-0.05", "--incidences", "0", "--azimuths", "0",
                 "--distances", "10,20", "--settle", "0.01", "-q", "-o", str(tmp_path / "cap.jsonl")]) != 0
    captured = capsys.readouterr()
    assert captured.err.count("pose 3 refused: too close\n") == 1 and "pose 3" not in captured.out


def test_capture_help_documents_the_touched_reference_with_units(capsys):
    """--touch, --touch-height and --touch-force: what a touch does (speeds, depth, retract), the reference it
    gives the calibration, and each value's unit."""
    from place_safe.calibration.capture import TOUCH_HEIGHT_STD, touch_plane

    with pytest.raises(SystemExit):
        main(["capture", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "the plane by touching it (the touched table as reference" in text
    d = touch_plane.__kwdefaults__
    assert f"descends at {d['speed'] * 1000:g} mm/s" in text and f"within {d['max_depth'] * 1000:g} mm" in text
    assert f"retracts {d['retract'] * 1000:g} mm" in text and f"each contact {TOUCH_HEIGHT_STD * 1000:g} mm" in text
    assert "'reference'" in text and "--touch-height Z m: base-frame z" in text
    assert f"--touch-force N N: the contact force that ends a touch's descent (default {d['force_threshold']:g}" in text


def test_place_in_simulation_takes_the_robot_files_limits_and_motion(tmp_path, capsys):
    """A robot file given to ``place --sim`` was read and checked, and only its tool frames used: a file that allows
    0.05 m/s released the cup as the packaged 0.5 m/s one did, at 2.5 s (a review's bad-input search). Its speed
    limit and near-surface speed now hold: 5 s is not enough to get down (it takes 10.7), and stderr says what is not
    simulated."""
    import json

    text = packaged_config("sim").read_text()
    assert "max_linear_speed = 0.5 " in text and "near_surface_speed = 0.05\n" in text
    slow = tmp_path / "slow.toml"
    slow.write_text(text.replace("max_linear_speed = 0.5 ", "max_linear_speed = 0.05 ")
                    .replace("near_surface_speed = 0.05\n", "near_surface_speed = 0.01\n"))
    out = tmp_path / "r.json"
    code = main(["place", "--sim", "place_level", "--method", "peak", "--robot-file", str(slow), "--timeout", "5",
                 "--json", str(out), "--log", str(tmp_path / "t.jsonl")])
    err = capsys.readouterr().err
    res = json.loads(out.read_text())
    assert res["outcome"] != "released" and res["robot_config"] == str(slow), (code, res["outcome"], res["reason"])
    assert "workspace box, min_descent_z and surface_keepout are checked on the arm only" in err


def test_calibrate_mount_counts_a_repeated_capture_once(sweep_path, tmp_path, capsys):
    """The real sweep given twice in one capture: every mount direction's stated 1-sigma shrank by sqrt(2) (0.12 ->
    0.08 mm for the height with --level --table-height 0; session 82), so a direction the capture determines only
    loosely could pass the MAX_SIGMA hold. Each measurement now counts once: the fit is the sweep's, and standard
    error says what was left out."""
    import json

    frames = json.loads(sweep_path.read_text())
    twice = tmp_path / "twice.json"
    twice.write_text(json.dumps(frames + frames))
    argv = ["--method", "peak", "--level", "--table-height", "0"]
    code_once = main(["calibrate-mount", str(sweep_path), *argv])
    once = capsys.readouterr().out
    assert main(["calibrate-mount", str(twice), *argv]) == code_once
    captured = capsys.readouterr()
    assert captured.out.replace(str(twice), str(sweep_path)) == once
    assert f"frame {len(frames)} repeats frame 0 exactly" in captured.err


@pytest.mark.parametrize("option, value, line", [
    ("--sigma-angle", "1e-20", "--sigma-angle 1e-20 is below the smallest per-frame noise the fit takes (0.00057 deg)"),
    ("--sigma-mm", "1e-300", "--sigma-mm 1e-300 is below the smallest per-frame noise the fit takes (0.001 mm)")])
def test_calibrate_mount_refuses_a_starting_noise_below_the_fits_floor(sweep_path, option, value, line, capsys):
    """--sigma-angle 1e-20 ended "mount fit did not converge", 1e-160 "invalid input: array must not contain infs or
    NaNs" (session 82): one line naming the option, before any plane is estimated."""
    assert main(["calibrate-mount", str(sweep_path), "--method", "peak", "-q", "--level", option, value]) == 2
    assert capsys.readouterr().err.splitlines() == [f"place-safe: error: calibrate-mount: {line}: it weighs each "
                                                    "frame's residuals"]


def test_calibrate_mount_says_which_frames_are_posed_by_their_recorded_pose(sweep_path, tmp_path, capsys):
    """A capture whose frames had no joint angles was fitted from their recorded poses while the output said "flange
    poses from joints" (round 14): it says how many frames were posed by their recorded pose."""
    import json

    frames = json.loads(sweep_path.read_text())
    for f in frames[::4]:
        del f["joint_angles"]
    bad = tmp_path / "cap.json"
    bad.write_text(json.dumps(frames))
    assert main(["calibrate-mount", str(bad), "--method", "proprietary", "--level", "-q"]) == 0
    out = capsys.readouterr().out
    n = len(frames[::4])
    assert f"flange poses from joints ({n} of {len(frames)} frames without joint angles: from their recorded pose)" \
        in out, out
    assert main(["calibrate-mount", str(sweep_path), "--method", "proprietary", "--level", "-q"]) == 0
    out = capsys.readouterr().out
    assert "flange poses from joints" in out and "without joint angles" not in out


def test_calibrate_mount_with_recorded_poses_says_the_pose_is_missing_not_the_joints(sweep_path, tmp_path, capsys):
    """``--poses recorded`` on frames with joint angles and no pose said "12 no joint_angles or pose" (round 14): it
    says the recorded pose is missing and that poses from joints would read the joint angles."""
    import json

    frames = json.loads(sweep_path.read_text())
    for f in frames:
        del f["pose"]
    bad = tmp_path / "cap.json"
    bad.write_text(json.dumps(frames))
    assert main(["calibrate-mount", str(bad), "--method", "proprietary", "--level", "--poses", "recorded", "-q"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and f"{len(frames)} no recorded pose (poses from joints would read their joint angles)" \
        in err[0], err
