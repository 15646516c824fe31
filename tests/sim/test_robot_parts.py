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


# a fault stops like the real driver: brake at emergency_decel, never kinder (review finding 3) -------------------
def _moving_down(speed: float = 0.1) -> SimRobot:
    robot = SimRobot.load()
    robot.speed_linear([0.0, 0.0, -speed, 0.0, 0.0, 0.0], accel=0.5)
    robot.step(0.5)
    assert robot.tcp_twist()[2] == pytest.approx(-speed, abs=2e-3)
    return robot


def _travel_mm(robot: SimRobot, p0: np.ndarray) -> float:
    return 1000.0 * float(np.linalg.norm(robot.tcp_pose()[:3, 3] - p0))


def test_a_fault_brakes_at_the_emergency_decel_not_at_once():
    robot = _moving_down(0.1)
    theory = 1000.0 * 0.1**2 / (2.0 * robot.emergency_decel)  # 2.5 mm
    p0 = robot.tcp_pose()[:3, 3].copy()
    with pytest.raises(RobotFault, match="protective stop"):
        robot._raise_fault("protective stop (test)")
    travel = _travel_mm(robot, p0)
    assert 0.8 * theory <= travel <= 1.2 * theory
    assert robot.fault() == "protective stop (test)" and not robot.is_moving()
    assert np.linalg.norm(robot.tcp_twist()[:3]) < 0.01
    assert robot.faults_while_stopping == []


def test_a_fault_in_the_step_loop_brakes_after_leaving_it_and_a_second_fault_is_only_recorded():
    robot = _moving_down(0.1)
    theory = 1000.0 * 0.1**2 / (2.0 * robot.emergency_decel)
    p0 = robot.tcp_pose()[:3, 3].copy()
    calls = {"n": 0, "depth": 0, "max_depth": 0}

    def injector(model, data, t):  # like the scenario's injected protective stop, and again while braking
        calls["n"] += 1
        calls["depth"] += 1
        calls["max_depth"] = max(calls["max_depth"], calls["depth"])
        try:
            if calls["n"] == 1:
                robot._raise_fault("protective stop (first)")
            if calls["n"] == 5:
                robot._raise_fault("protective stop (second)")
        finally:
            calls["depth"] -= 1

    robot.add_step_callback(injector)
    with pytest.raises(RobotFault, match="first"):
        robot.step(1.0)
    assert calls["max_depth"] == 1  # never re-entered
    assert robot.fault() == "protective stop (first)" and not robot.is_moving()
    assert robot.faults_while_stopping == ["protective stop (second)"]
    # the second fault held the arm where it was; before it, it braked (not held at once)
    travel = _travel_mm(robot, p0)
    assert 0.0 < travel < 1.2 * theory
    robot.remove_step_callback(injector)


def test_a_loop_fault_during_the_stop_ends_it_without_recursion():
    robot = _moving_down(0.1)
    p0 = robot.tcp_pose()[:3, 3].copy()
    robot.limits = robot.limits.replace(max_tracking_error=1e-9)  # the Cartesian loop faults at every tick
    with pytest.raises(RobotFault, match="cannot follow"):
        robot.step(0.1)
    assert "cannot follow" in robot.fault() and not robot.is_moving()
    assert len(robot.faults_while_stopping) == 1 and "cannot follow" in robot.faults_while_stopping[0]
    assert _travel_mm(robot, p0) < 1.0


def test_a_fault_at_rest_does_not_move_the_arm():
    robot, twin = SimRobot.load(), SimRobot.load()
    robot.step(0.2)
    twin.step(0.2)
    q0 = robot.joint_positions()
    with pytest.raises(RobotFault):
        robot._raise_fault("protective stop (at rest)")
    assert not robot.is_moving() and robot.time() == pytest.approx(0.2, abs=1e-9)  # no braking steps
    assert np.array_equal(robot.joint_positions(), q0)
    robot.step(0.2)
    twin.step(0.2)  # the servos hold it (where it was, as before: only their sag, like an arm that never faulted)
    assert np.abs(robot.joint_positions() - twin.joint_positions()).max() < 2e-4
    assert np.linalg.norm(robot.tcp_pose()[:3, 3] - twin.tcp_pose()[:3, 3]) < 1e-4


def test_the_force_peak_is_recorded_while_braking():
    robot = _moving_down(0.1)
    recorded = []
    orig = robot.forces.overload

    def overload(limit):
        recorded.append(robot.time())
        return orig(limit)

    robot.forces.overload = overload
    with pytest.raises(RobotFault):
        robot._raise_fault("protective stop (test)")
    assert len(recorded) > 10  # the contact-force record goes on through the stop
