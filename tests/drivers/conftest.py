"""Fixtures: a fake UR controller (kinematic arm) and a URRobot connected to it through the fake ur_rtde."""

from __future__ import annotations

import pytest

from place_safe.drivers.ur5 import URConfig, URRobot, packaged_config
from place_safe.drivers.ur5 import fake_rtde


@pytest.fixture()
def config() -> URConfig:
    return URConfig.load(packaged_config("sim"))


@pytest.fixture(scope="session")
def kinematics():
    from place_safe.robot.kinematics import Kinematics

    return Kinematics()


@pytest.fixture()
def fake(kinematics) -> fake_rtde.FakeUR:
    from place_safe.drivers.ur5.kinematic_arm import KinematicArm

    return fake_rtde.FakeUR(KinematicArm(kinematics=kinematics))


@pytest.fixture()
def robot(fake, config):
    r = URRobot(config, modules=fake_rtde.modules(), out=lambda s: None).connect()
    yield r
    r.disconnect()
