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
