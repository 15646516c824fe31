"""A simulated placement whose sensor is the real I2C driver over the register-level emulator over the
simulated TMF8820 (``emu:sim``): every frame crosses the emulated bus and the driver's decoder, stamped on
the simulation's clock, with the bus latency a real sensor has. The estimator recovers planes from the
histograms that came over the bus (frames carry no ground truth across it)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from place_safe import PlacementConfig, PlacementLoop
from place_safe.drivers.tmf8820.emulator import FaultPlan
from place_safe.sources import open_source
from place_safe.recovery import make_estimator
from place_safe.calibration import Calibration
from place_safe.sim.calibration_capture import calibration_file
from place_safe.sim.world import sim_world


def user_calibration():
    """The packaged simulated user calibration (capture of a level table -> place-safe calibrate)."""
    return Calibration.load(calibration_file("nominal"))


def _setup(scenario: str, **source_options):
    world = sim_world(scenario, attach=False)  # not attached: the emulator takes the sensor's measurements
    source = open_source("emu:sim", tof=world.tof, **source_options)
    return world.robot, source


@pytest.mark.slow
def test_level_table_is_released_through_the_emulated_bus_with_faults():
    robot, source = _setup("place_level", bus_hz=1e6, faults=FaultPlan(rate=0.001, seed=4))
    assert source.clock_domain == "robot"
    estimator = make_estimator("diff", user_calibration())
    with robot:
        loop = PlacementLoop(robot, source, estimator, config=PlacementConfig())
        res = loop.run(timeout=20.0)
    assert res.outcome == "released", res.reason
    assert not robot.holding() and robot.liquid_spilled() == 0
    st = source.stats
    assert st["frames"] >= 10
    assert sum(st["injected"].values()) >= 1
    for kind, n in st["injected"].items():
        assert st[kind] == n, kind
    assert st["frames"] / res.robot_seconds < 26.6  # no faster than a 1 MHz bus allows


@pytest.mark.slow
def test_tilted_table_is_refused_through_the_emulated_bus_at_400_khz():
    robot, source = _setup("place_tilted", bus_hz=400e3)
    estimator = make_estimator("diff", user_calibration())
    with robot:
        res = PlacementLoop(robot, source, estimator, config=PlacementConfig()).run(timeout=20.0)
    assert res.outcome == "refused" and robot.holding(), res.reason
    assert math.isfinite(res.robot_seconds)
    # frames are stamped at their measurement's completion on the sim clock and arrive once their bytes
    # have crossed the bus: 4.4 kB at 400 kHz is ~99 ms
    lag = np.array([e["t"] - e["stamp"] for e in res.frame_log])
    assert len(lag) >= 5 and np.all(lag >= 0) and np.median(lag) > 0.09
    assert source.stats["frames"] / res.robot_seconds < 10.7  # no faster than the bus allows


@pytest.mark.slow
def test_a_dead_bus_during_the_approach_is_refused_with_the_cup_held():
    robot, source = _setup("place_level", bus_hz=1e6, faults=FaultPlan(dead_after=3000))  # ~3 s of frames
    estimator = make_estimator("diff", user_calibration())
    with robot:
        res = PlacementLoop(robot, source, estimator, config=PlacementConfig()).run(timeout=20.0)
    assert res.outcome == "refused" and robot.holding(), res.reason
    assert "does not answer" in res.reason  # refused because the sensor died, and it says so
    assert source.stats["frames"] >= 5
