"""URRobot's real code path on the fake ur_rtde: limits before every command, latched faults that never open
the gripper, watchdog, reconnect, dry run."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from place_safe.drivers.ur5 import URRobot
from place_safe.drivers.ur5 import fake_rtde
from place_safe.drivers.ur5.pose import pose_to_vector, vector_to_pose
from place_safe.drivers.ur5 import URConfig, packaged_config
from place_safe.exceptions import RobotFault


@pytest.fixture()
def config() -> URConfig:
    return URConfig.load(packaged_config("sim"))


@pytest.fixture(scope="module")
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



def _down(robot, dz):
    T = robot.tcp_pose()
    T[2, 3] -= dz
    return T


def _gripper_opened(fake) -> bool:
    return any(name.endswith("DigitalOut") and args[1] is True for _, name, args in fake.commands)


def test_connect_sets_tcp_payload_and_the_first_motion_arms_the_watchdog(fake, robot, config):
    names = [c[1] for c in fake.commands]
    assert names[:2] == ["setTcp", "setPayload"] and "setWatchdog" not in names  # at rest by design until a motion
    robot.move_linear(_down(robot, 0.01), speed=0.05, accel=0.5)
    names = [c[1] for c in fake.commands]
    assert names.index("setWatchdog") < names.index("moveL") and fake.watchdog_hz == config.watchdog_hz
    np.testing.assert_allclose(robot.tcp_pose(), fake.arm.tcp_pose(), atol=1e-9)  # controller TCP = ours
    np.testing.assert_allclose(robot.sensor_pose(), fake.arm.sensor_pose(), atol=1e-9)
    assert robot.time() > 0 and robot.contact_force() == pytest.approx(0.0, abs=1e-9)


def test_pose_vector_round_trip():
    T = vector_to_pose([0.1, -0.2, 0.3, 0.5, -1.0, 2.0])
    np.testing.assert_allclose(pose_to_vector(T), [0.1, -0.2, 0.3, 0.5, -1.0, 2.0], atol=1e-12)
    with pytest.raises(ValueError):
        vector_to_pose([0, 0, float("nan"), 0, 0, 0])


def test_move_linear_arrives_and_targets_outside_the_limits_never_reach_the_controller(fake, robot):
    goal = _down(robot, 0.04)
    robot.move_linear(goal, speed=0.1, accel=0.5)
    assert np.linalg.norm(robot.tcp_pose()[:3, 3] - goal[:3, 3]) < 5e-4 and not robot.is_moving()
    n = len(fake.commands)
    far = robot.tcp_pose()
    far[0, 3] = 1.5
    with pytest.raises(RobotFault, match="workspace box"):
        robot.move_linear(far)
    deep = robot.tcp_pose()
    robot.config.limits.min_descent_z = deep[2, 3] - 0.1
    deep[2, 3] -= 0.11
    with pytest.raises(RobotFault, match="deepest allowed descent"):
        robot.move_linear(deep)
    robot.set_surface(([0, 0, 1.0], robot.cup_pose()[2, 3] - 0.02))  # a table 2 cm under the cup
    with pytest.raises(RobotFault, match="below the sensed surface"):
        robot.move_linear(_down(robot, 0.04))
    assert len(fake.commands) == n and robot.fault() is None  # refused on the host, nothing latched
    with pytest.raises(ValueError):
        robot.move_linear(goal, speed=float("nan"))


def test_speedl_stops_itself_before_the_deepest_point(fake, robot, config):
    z0 = robot.tcp_pose()[2, 3]
    robot.config.limits.min_descent_z = z0 - 0.03
    robot.speed_linear([0, 0, -0.05, 0, 0, 0], accel=0.5)
    with pytest.raises(RobotFault, match="deepest allowed descent"):
        for _ in range(200):
            robot.step(0.008)
    assert robot.is_faulted()
    fake.advance(0.5)
    assert robot.tcp_pose()[2, 3] > z0 - 0.03
    assert not fake.arm.is_moving() and not _gripper_opened(fake)


@pytest.mark.slow
@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(vz=st.floats(-0.25, 0.0), vx=st.floats(-0.05, 0.05), a=st.floats(0.1, 1.2))
def test_no_speedl_gets_the_tcp_below_the_deepest_point(fake, robot, vz, vx, a):
    """Invariant: whatever descent is commanded, the TCP never goes below min_descent_z."""
    floor = robot.tcp_pose()[2, 3] - 0.02
    robot.config.limits.min_descent_z = floor
    try:
        robot.speed_linear([vx, 0, vz, 0, 0, 0], accel=a)
        for _ in range(60):
            robot.step(0.008)
            assert robot.tcp_pose()[2, 3] >= floor
    except RobotFault:
        pass
    fake.advance(0.6)  # whatever happened (even the host stalling now), the arm comes to rest above the floor
    assert not fake.arm.is_moving() and fake.arm.tcp_pose()[2, 3] >= floor
    try:  # ready for the next example
        robot.step(0.008)
    except RobotFault:
        pass
    if robot.is_faulted():
        robot.clear_fault()
    robot.config.limits.min_descent_z = -0.3


def test_protective_stop_during_a_move_is_latched_and_the_gripper_stays_shut(fake, robot):
    fake.inject_protective_stop(fake.time + 0.2, "collision")
    with pytest.raises(RobotFault, match="protective stop"):
        robot.move_linear(_down(robot, 0.05), speed=0.05, accel=0.5)
    assert "protective stop" in robot.fault()
    with pytest.raises(RobotFault, match="faulted"):
        robot.speed_linear([0, 0, -0.01, 0, 0, 0])
    with pytest.raises(RobotFault, match="refusing to open the gripper"):
        robot.gripper(open=True)
    assert not _gripper_opened(fake) and not fake.arm.gripper_is_open()
    with pytest.raises(RobotFault, match="teach pendant"):
        robot.clear_fault()  # still stopped on the controller
    fake.unlock_protective_stop()
    robot.clear_fault()
    robot.move_linear(_down(robot, 0.01), speed=0.05, accel=0.5)
    assert robot.fault() is None


def test_asynchronous_stop_ends_in_rest(fake, robot):
    robot.speed_linear([0, 0, -0.02, 0, 0, 0], accel=0.5)
    robot.step(0.1)
    assert robot.is_moving()
    robot.stop(decel=1.0, asynchronous=True)
    for _ in range(100):
        robot.step(0.008)
        if not robot.is_moving():
            break
    assert not robot.is_moving() and not fake.arm.is_moving()


def test_watchdog_stops_a_speedl_when_the_host_stalls(fake, robot):
    robot.speed_linear([0, 0, -0.02, 0, 0, 0], accel=0.5)
    robot.step(0.1)
    assert fake.arm.is_moving()
    fake.advance(0.5)  # the host stops kicking for 500 ms
    assert not fake.arm.is_moving()
    with pytest.raises(RobotFault, match="control script stopped"):
        robot.step(0.008)
    robot.clear_fault()  # restarts the script and the watchdog
    assert fake.program_running and robot.fault() is None


def test_lost_connection_is_latched_and_reconnect_clears_it(fake, robot):
    fake.inject_disconnect(fake.time + 0.05)
    robot.speed_linear([0, 0, -0.01, 0, 0, 0], accel=0.5)
    with pytest.raises(RobotFault, match="lost"):
        robot.step(0.2)
    assert not _gripper_opened(fake)
    robot.clear_fault()
    assert robot.fault() is None and fake.connected


def test_a_connection_that_stays_down_cannot_be_cleared(fake, robot):
    fake.inject_disconnect(fake.time + 0.01, reconnectable=False)
    with pytest.raises(RobotFault, match="lost"):
        robot.step(0.1)
    with pytest.raises(RobotFault, match="cannot reconnect"):
        robot.clear_fault()
    assert robot.is_faulted()


def test_a_stalled_controller_is_a_fault(fake, robot):
    fake.inject_slow(2.0)
    with pytest.raises(RobotFault, match="timestamp stuck"):
        robot.step(1.0)


def test_force_limit_with_the_resting_offset_removed(config, kinematics):
    from place_safe.drivers.ur5.kinematic_arm import KinematicArm

    arm = KinematicArm(kinematics=kinematics)
    z_table = arm.tcp_pose()[2, 3] - 0.01
    arm.contact_plane = (np.array([0, 0, 1.0]), z_table)
    fake = fake_rtde.FakeUR(arm, force_offset=(0, 0, 7.0), force_noise=0.5)  # a mis-set payload
    robot = URRobot(config, modules=fake_rtde.modules()).connect()
    assert robot.contact_force() < 3.0  # the 7 N offset is zeroed at connect
    robot.config.limits.max_contact_force = 20.0
    robot.limits.max_contact_force = 20.0
    robot.speed_linear([0, 0, -0.01, 0, 0, 0], accel=0.5)
    with pytest.raises(RobotFault, match="contact force"):
        robot.step(2.0)
    assert not _gripper_opened(fake)


def test_dry_run_prints_the_plan_and_commands_nothing(fake, config):
    lines = []
    robot = URRobot(config, modules=fake_rtde.modules(), dry_run=True, out=lines.append).connect()
    before = fake.arm.tcp_pose()
    goal = robot.tcp_pose()
    goal[2, 3] -= 0.05
    robot.move_linear(goal, speed=0.05)
    robot.speed_linear([0, 0, -0.01, 0, 0, 0])
    robot.gripper(open=True)
    robot.step(0.2)
    assert fake.commands == [] and fake.outputs == {}
    np.testing.assert_allclose(fake.arm.tcp_pose(), before)
    assert len(lines) == 3 and lines[0].startswith("[dry run] moveL") and "speedL" in lines[1]
    assert "output 0" in lines[2]


def test_connect_times_out_on_a_dead_host(config):
    def hang(*a, **k):
        time.sleep(0.5)

    mods = SimpleNamespace(rtde_receive=SimpleNamespace(RTDEReceiveInterface=hang),
                           rtde_control=SimpleNamespace(RTDEControlInterface=hang),
                           rtde_io=SimpleNamespace(RTDEIOInterface=hang))
    config.connection.connect_timeout_s = 0.05
    with pytest.raises(RobotFault, match="no answer within"):
        URRobot(config, modules=mods).connect()
    config.connection.host = "10.255.255.1"
    with pytest.raises(RobotFault, match="no robot at"):
        URRobot(config, modules=fake_rtde.modules()).connect()


def test_context_manager_connects_and_disconnects(fake, config):
    with URRobot(config, modules=fake_rtde.modules()) as robot:
        robot.speed_linear([0, 0, -0.01, 0, 0, 0])
        robot.step(0.05)
    assert not fake.arm.is_moving() or fake.mode is None
    assert [c[1] for c in fake.commands][-1] == "speedStop"


def test_dry_run_capture_checks_and_prints_every_pose_and_writes_nothing(fake, config, tmp_path):
    from place_safe.calibration.capture import SweepPlan, capture_sweep, level_plane

    lines = []
    robot = URRobot(config, modules=fake_rtde.modules(), dry_run=True, out=lines.append).connect()
    plan = SweepPlan(distances=[0.1, 0.2], incidences=[0.0])
    res = capture_sweep(robot, None, plan, tmp_path / "c.jsonl", plane=level_plane(0.0), tool=robot.tool,
                        progress=False)
    assert res.captured == 2 and res.frames == 0 and fake.commands == []
    assert len(lines) == 2 and all(x.startswith("[dry run] moveL") for x in lines)
    assert (tmp_path / "c.jsonl").read_text() == ""
