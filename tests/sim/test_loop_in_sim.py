"""PlacementLoop on the real MuJoCo robot and simulated sensor, with the sensor's ground-truth planes as
the estimate (the loop, clocks, poses and decision are under test here, not plane recovery)."""

from __future__ import annotations

import pytest

from place_safe import PlacementConfig, PlacementLoop
from place_safe.evaluation.contact import TruthEstimator
from place_safe.sim.world import sim_world


class FreezesAtCheck:
    """Wraps a source; once the loop's machine is in CHECK it repeats its last frame forever."""

    clock_domain = "robot"

    def __init__(self, source):
        self.source, self.loop, self.last = source, None, None

    def read(self, timeout=1.0):
        if self.loop is not None and self.loop.machine.phase.value == "check" and self.last is not None:
            return self.last
        self.last = self.source.read(timeout)
        return self.last


def setup(scenario="place_level"):
    world = sim_world(scenario)
    return world.robot, world.tof


@pytest.mark.slow
def test_loop_releases_on_the_level_table_in_simulation():
    robot, tof = setup()
    with robot:
        res = PlacementLoop(robot, tof, TruthEstimator(), config=PlacementConfig()).run(timeout=20.0)
    assert res.outcome == "released", res.reason
    assert not robot.holding() and robot.liquid_spilled() == 0


@pytest.mark.slow
def test_sensor_that_freezes_after_the_stop_is_not_a_release():
    # the house issue's case: a frozen sensor once led to a release from one post-stop measurement
    robot, tof = setup()
    src = FreezesAtCheck(tof)
    loop = PlacementLoop(robot, src, TruthEstimator(), config=PlacementConfig())
    src.loop = loop
    res = loop.run(timeout=20.0)
    assert res.outcome == "refused" and robot.holding(), res.reason
    assert res.dropped.get("repeated", 0) > 0
    assert "stale" in res.reason or "surface planes" in res.reason
