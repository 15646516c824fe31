"""The parts SimRobot composes (sim/arm_model, arm_motion, payload, force_sensing): each alone on the packaged
robot model, and the robot's faults and forces as the parts keep them."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings, strategies as st

from place_safe.exceptions import RobotFault
from place_safe.robot.interface import RobotLimits
from place_safe.sim.arm_model import ArmModel, exp_rot, log_rot
from place_safe.sim.arm_motion import outside_limits
from place_safe.sim.force_sensing import REARM_MARGIN, ForceSensing
from place_safe.sim.payload import HeldCup
from place_safe.sim.robot import SimRobot
from place_safe.sim.robot_model import load_robot_model

pytestmark = pytest.mark.sim


@pytest.fixture(scope="module")
def arm() -> ArmModel:
    model, data = load_robot_model()
    mujoco.mj_forward(model, data)
    return ArmModel(model, data)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0), min_size=3, max_size=3))
def test_log_rot_inverts_exp_rot(w):
    w = np.asarray(w)
    assert np.allclose(log_rot(exp_rot(w)), w, atol=1e-9) or np.linalg.norm(w) > math.pi - 1e-6


def test_a_model_without_the_robot_names_what_it_misses():
    model = mujoco.MjModel.from_xml_string("<mujoco><worldbody><geom type='plane' size='1 1 1'/></worldbody></mujoco>")
    with pytest.raises(ValueError, match="no joint named 'shoulder_pan_joint'"):
        ArmModel(model, mujoco.MjData(model))


def test_frames_are_in_the_base_frame(arm):
    assert np.allclose(arm.base_T_site(arm.tcp)[3], [0, 0, 0, 1])
    assert np.allclose(arm.world_T_base() @ arm.base_T_site(arm.tcp), arm.world_T_site(arm.tcp), atol=1e-12)
    assert arm.jac_base(arm.data).shape == (6, 6)


def test_outside_limits_names_the_first_joint_out():
    lim = RobotLimits()
    assert outside_limits(np.zeros(6), lim) is None
    q = np.zeros(6)
    q[2] = 4.0  # the elbow turns +-pi
    assert outside_limits(q, lim) == (2, -math.pi, math.pi)


def test_the_cup_is_held_after_a_regrasp_and_free_when_open(arm):
    cup = HeldCup(arm)
    cup.regrasp()
    assert cup.holding() and not cup.is_open
    cup.set_open(True)
    assert not cup.holding() and cup.is_open
    cup.set_open(False)  # the cup has not moved: the fingers close on it again
    assert cup.holding()


def test_force_sensing_rearms_above_the_force_that_stopped_it(arm):
    forces = ForceSensing(arm, HeldCup(arm), controller="cb3", control_period=0.008, sense_ticks=4, force_seed=1)
    assert forces.overload(60.0) is None  # nothing touches
    forces.last_force = 80.0
    forces.rearm(60.0)
    assert forces.grace == 80.0 + REARM_MARGIN
    assert forces.overload(60.0) is None and forces.grace == 0.0  # the force dropped: the normal limit again


def test_sim_robot_composes_the_parts_and_keeps_its_public_face():
    robot = SimRobot.load()
    assert robot.detector is robot.forces.detector and robot.true_force_peak == 0.0
    assert robot.force_noise == pytest.approx(3.6)
    with pytest.raises(RobotFault):
        robot._raise_fault("protective stop (test)")
    assert robot.fault() == "protective stop (test)" and not robot.is_moving()
    with pytest.raises(RobotFault, match="faulted"):
        robot.move_joint(robot.joint_positions())
    robot.clear_fault()
    assert robot.fault() is None
