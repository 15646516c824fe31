"""The examples run (CI runs them through this test)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.slow
def test_simulated_placement_example_refuses_the_tilted_table(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["simulated_placement.py", "place_tilted"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(EXAMPLES / "simulated_placement.py"), run_name="__main__")
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("refused: surface tilted")


@pytest.mark.slow
def test_real_arm_example_runs_on_the_ur_rtde_stand_in():
    # the real-arm script's placement function, with URRobot on the fake ur_rtde moving the MuJoCo arm
    # and the simulated sensor behind the TMF8820 driver over the register-level emulator
    from place_safe import Calibration, make_estimator
    from place_safe.drivers.ur5 import URConfig, URRobot, fake_rtde, packaged_config
    from place_safe.sources import open_source
    from place_safe.sim.calibration_capture import calibration_file
    from place_safe.sim.world import sim_world

    example = runpy.run_path(str(EXAMPLES / "real_placement.py"), run_name="example")
    world = sim_world("place_tilted", attach=False)  # the emulator over the simulated sensor takes the frames
    arm = world.robot
    sensor = open_source("emu:sim", tof=world.tof)
    fake_rtde.FakeUR(arm)
    robot = URRobot(URConfig.load(packaged_config("sim")), modules=fake_rtde.modules(), out=lambda s: None)
    calibration = Calibration.load(calibration_file("nominal"))  # the simulated user calibration
    result = example["place"](robot, sensor, make_estimator("peak", calibration), timeout=10.0)
    assert result.outcome == "refused" and "tilted" in result.reason and arm.holding()


@pytest.mark.parametrize("gripper", ["digital", "robotiq"])
def test_real_arm_example_releases_and_retreats_on_the_pessimistic_fake(gripper):
    """examples/real_placement.place() on the fake CB3 (force noise 3.6 N per axis, watchdog, one motion thread):
    released and retreated, no watchdog stop, no script error, no command refused -- with either gripper."""
    from urcap import FakeURCap

    from place_safe.drivers.ur5.config import placement_config
    from place_safe.evaluation.contact import TablePlaneSource, TruthEstimator, make_stand_in
    from place_safe.placement.machine import PlacementConfig

    example = runpy.run_path(str(EXAMPLES / "real_placement.py"), run_name="example")
    srv = FakeURCap() if gripper == "robotiq" else None
    robot, fake = make_stand_in("cb3", table_gap=0.4, gripper=gripper, seed=7)
    if srv is not None:
        robot.config.gripper.port = srv.port
    config = placement_config(robot.config, PlacementConfig(footprint_frames=0))
    try:
        result = example["place"](robot, TablePlaneSource(robot, fake.arm.contact_plane[1]), TruthEstimator(),
                                  config=config, timeout=20.0)
    finally:
        if srv is not None:
            srv.close()
    assert result.outcome == "released", result.reason
    assert result.transitions[-1].target.value == "done" and "retreated" in result.transitions[-1].reason
    assert fake.watchdog_stops == 0 and fake.errors == [] and fake.rejected == []
    assert not fake.program_running and not fake.arm.is_moving()  # disconnect stopped the script at rest
    if srv is None:
        assert fake.arm.gripper_is_open()
    else:
        assert "SET POS 0" in srv.lines and srv.lines.index("SET POS 0") > srv.lines.index("SET ACT 1")


def test_real_arm_example_says_in_one_line_what_it_could_not_open(capsys, tmp_path):
    """The real-arm script's command line: --help teaches it, and a calibration or sensor that cannot be opened ends
    it with one line (exit 2) before any robot is contacted."""
    example = runpy.run_path(str(EXAMPLES / "real_placement.py"), run_name="example")
    with pytest.raises(SystemExit) as done:
        example["main"](["--help"])
    assert done.value.code == 0 and "--dry-run" in capsys.readouterr().out
    real = str(Path(__file__).resolve().parents[2] / "robots" / "ur5" / "real.toml")
    assert example["main"]([real, "emu:synthetic", str(tmp_path / "missing.json"), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "missing.json" in err and "Traceback" not in err
    from place_safe.sim.calibration_capture import calibration_file

    assert example["main"]([real, "i2c:/nonexistent/i2c-9@0x41", str(calibration_file("nominal")), "--dry-run"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "i2c" in err.lower()


@pytest.mark.parametrize("scenario, unit", [("place_level", "nominal"), ("level_mismatch_40cm", "mismatch")])
def test_a_simulated_world_gives_its_own_units_calibration(scenario, unit):
    """``SimWorld.user_calibration``: the scenario's simulated unit's packaged user calibration, what the example now
    runs on; it took the nominal unit's for every scenario, the mismatched ones' too (session 83, a new user's
    walkthrough: a calibration of another unit misreads a unit)."""
    from place_safe import sim_world, simulated_calibration

    world = sim_world(scenario, attach=False)
    assert world.user_calibration().to_dict() == simulated_calibration(unit).to_dict()
