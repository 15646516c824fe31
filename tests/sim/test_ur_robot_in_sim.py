"""The ur_rtde robot passes the same placement tests as SimRobot: URRobot's real code path drives the fake
ur_rtde controller, which moves the MuJoCo arm (SimRobot) that the simulated TMF8820 looks through.
Plane estimates are the simulated sensor's ground truth (the driver, loop and decision are under test,
not plane recovery), as in tests/sim/test_loop_in_sim.py."""

from __future__ import annotations

import pytest

from place_safe import PlacementConfig, PlacementLoop
from place_safe.drivers.ur5 import URConfig, URRobot, packaged_config
from place_safe.drivers.ur5 import fake_rtde
from place_safe.evaluation.contact import TruthEstimator
from place_safe.sim.world import sim_world


def setup(scenario="place_level"):
    world = sim_world(scenario)
    arm, tof = world.robot, world.tof
    fake = fake_rtde.FakeUR(arm)
    robot = URRobot(URConfig.load(packaged_config("sim")), modules=fake_rtde.modules(), out=lambda s: None)
    return arm, tof, fake, robot


def _opened(fake) -> bool:
    return any(name.endswith("DigitalOut") and args[1] is True for _, name, args in fake.commands)


@pytest.mark.slow
def test_level_table_released_through_ur_rtde():
    arm, tof, fake, robot = setup()
    with robot:
        res = PlacementLoop(robot, tof, TruthEstimator(), config=PlacementConfig()).run(timeout=20.0)
    assert res.outcome == "released", res.reason
    assert _opened(fake) and not arm.holding() and arm.liquid_spilled() == 0
    assert any(name == "speedL" for _, name, _ in fake.commands)


@pytest.mark.slow
def test_tilted_table_refused_through_ur_rtde():
    arm, tof, fake, robot = setup("place_tilted")
    with robot:
        res = PlacementLoop(robot, tof, TruthEstimator(), config=PlacementConfig()).run(timeout=20.0)
    assert res.outcome == "refused", res.reason
    assert arm.holding() and not _opened(fake)


@pytest.mark.slow
def test_protective_stop_during_the_descent_aborts_holding_the_cup():
    arm, tof, fake, robot = setup()
    loop = PlacementLoop(robot, tof, TruthEstimator(), config=PlacementConfig())
    fake.inject_protective_stop(lambda f: loop.machine.phase.value == "descend", "collision during descent")
    with robot:
        res = loop.run(timeout=20.0)
    assert res.outcome == "refused" and res.final_phase == "aborted", res.reason
    assert "protective stop" in res.reason or "fault" in res.reason
    assert arm.holding() and not _opened(fake) and robot.is_faulted()
    assert fake.safety_mode == fake_rtde.SAFETY_PROTECTIVE_STOP
