"""SimRobot: the Robot interface on MuJoCo physics (moves, speeds, stop, gripper, faults, speed)."""

from __future__ import annotations

import json

import mujoco
import numpy as np
import pytest

from place_safe.exceptions import RobotFault
from place_safe.robot.interface import RobotLimits, TrapezoidProfile
from place_safe.robot.description import ur5_mjcf_path
from place_safe.sim.robot import SimRobot


@pytest.fixture()
def robot() -> SimRobot:
    return SimRobot.load()


def _table_robot(gap: float = 0.05) -> SimRobot:
    """Robot over a table whose top is ``gap`` below the held cup's bottom."""
    probe = SimRobot.load()
    cup_z = probe.cup_pose()[2, 3]
    top = cup_z - gap
    xml = f"""<mujoco><include file="{ur5_mjcf_path()}"/>
      <worldbody><geom name="floor" type="plane" size="3 3 0.1"/>
        <body name="table" pos="-0.49 -0.11 {top - 0.05}">
          <geom name="table_top" type="box" size="0.3 0.3 0.05"/></body></worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    return SimRobot(model, mujoco.MjData(model))


def _record_speed(robot: SimRobot) -> list[float]:
    speeds: list[float] = []
    robot.add_step_callback(lambda m, d, t: speeds.append(float(np.linalg.norm(robot.tcp_twist()[:3]))))
    return speeds


def test_starts_at_rest_holding_the_cup(robot: SimRobot) -> None:
    T0 = robot.tcp_pose()
    np.testing.assert_allclose(T0[:3, 2], [0, 0, -1], atol=1e-6)  # gripper points down
    robot.step(0.5)
    assert np.linalg.norm(robot.tcp_pose()[:3, 3] - T0[:3, 3]) < 2e-4
    assert robot.holding() and not robot.gripper_is_open()
    fTc = np.linalg.inv(robot.flange_pose()) @ robot.cup_pose()
    np.testing.assert_allclose(fTc[:3, 3], [0, 0, 0.18], atol=5e-4)


def test_move_linear_reaches_target_on_a_line_within_speed_limit(robot: SimRobot) -> None:
    T0 = robot.tcp_pose()
    goal = T0.copy()
    goal[:3, 3] += [0.12, 0.08, -0.10]
    speeds = _record_speed(robot)
    positions: list[np.ndarray] = []
    robot.add_step_callback(lambda m, d, t: positions.append(robot.tcp_pose()[:3, 3]))
    t0 = robot.time()
    robot.move_linear(goal, speed=0.1, accel=0.5)
    assert not robot.is_moving()
    assert np.linalg.norm(robot.tcp_pose()[:3, 3] - goal[:3, 3]) < 1e-3
    assert max(speeds) <= 0.1 * 1.03, f"peak TCP speed {max(speeds):.4f} m/s for a 0.1 m/s move"
    assert max(speeds) > 0.09
    L = np.linalg.norm(goal[:3, 3] - T0[:3, 3])
    assert robot.time() - t0 < TrapezoidProfile(L, 0.1, 0.5).duration + 1.0
    # straight line: distance of every sample from the segment
    d = goal[:3, 3] - T0[:3, 3]
    u = d / np.linalg.norm(d)
    off = [np.linalg.norm((p - T0[:3, 3]) - ((p - T0[:3, 3]) @ u) * u) for p in positions]
    assert max(off) < 2e-3
    assert robot.holding()


def test_move_linear_with_rotation(robot: SimRobot) -> None:
    T0 = robot.tcp_pose()
    goal = T0.copy()
    c, s = np.cos(0.3), np.sin(0.3)
    goal[:3, :3] = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]) @ T0[:3, :3]
    goal[:3, 3] += [0.0, 0.05, 0.05]
    robot.move_linear(goal, speed=0.2, accel=1.0)
    T = robot.tcp_pose()
    assert np.linalg.norm(T[:3, 3] - goal[:3, 3]) < 1e-3
    assert np.arccos(np.clip((np.trace(T[:3, :3].T @ goal[:3, :3]) - 1) / 2, -1, 1)) < np.deg2rad(0.2)


def test_asynchronous_move_progresses_with_step(robot: SimRobot) -> None:
    goal = robot.tcp_pose()
    goal[2, 3] += 0.05
    robot.move_linear(goal, speed=0.1, accel=0.5, asynchronous=True)
    assert robot.is_moving()
    for _ in range(300):
        if not robot.is_moving():
            break
        robot.step(0.01)
    assert not robot.is_moving()
    assert abs(robot.tcp_pose()[2, 3] - goal[2, 3]) < 1e-3


def test_speed_linear_moves_at_commanded_speed_and_stop_halts(robot: SimRobot) -> None:
    v = np.array([0.03, -0.04, 0.0, 0.0, 0.0, 0.0])  # 0.05 m/s
    robot.speed_linear(v, accel=0.5)
    robot.step(0.5)  # ramp (0.1 s) and settle
    p1, t1 = robot.tcp_pose()[:3, 3], robot.time()
    robot.step(1.0)
    p2, t2 = robot.tcp_pose()[:3, 3], robot.time()
    vel = (p2 - p1) / (t2 - t1)
    np.testing.assert_allclose(vel, v[:3], atol=0.001)
    robot.stop(decel=1.0)
    assert not robot.is_moving()
    p3 = robot.tcp_pose()[:3, 3]
    robot.step(0.5)
    assert np.linalg.norm(robot.tcp_pose()[:3, 3] - p3) < 5e-4
    assert np.linalg.norm(robot.tcp_twist()[:3]) < 2e-3


def test_speed_linear_with_duration_then_rests(robot: SimRobot) -> None:
    p0 = robot.tcp_pose()[:3, 3]
    robot.speed_linear([0, 0, 0.05, 0, 0, 0], accel=1.0, duration=1.0)
    assert not robot.is_moving()
    dz = robot.tcp_pose()[2, 3] - p0[2]
    assert 0.045 < dz < 0.055  # 0.05 m/s for about 1 s, plus ramps


def test_speed_linear_is_clamped_to_limits() -> None:
    robot = SimRobot.load(limits=RobotLimits(max_linear_speed=0.05))
    speeds = _record_speed(robot)
    robot.speed_linear([0, 0, 0.5, 0, 0, 0], accel=1.0, duration=0.5)
    assert max(speeds) < 0.05 * 1.05


def test_gripper_open_releases_the_cup(robot: SimRobot) -> None:
    z0 = robot.cup_pose()[2, 3]
    robot.gripper(open=True)
    assert not robot.holding()
    robot.step(0.3)
    assert robot.cup_pose()[2, 3] < z0 - 0.2  # free fall for 0.3 s: 0.44 m
    assert robot.data.qpos[robot.model.jnt_qposadr[robot.model.joint("finger_left").id]] > 0.02


def test_place_on_table_and_release(robot: SimRobot) -> None:
    r = _table_robot(gap=0.05)
    top = r.cup_pose()[2, 3] - 0.05
    goal = r.tcp_pose()
    goal[2, 3] -= 0.05 - 0.002
    forces = []
    r.add_step_callback(lambda m, d, t: forces.append(r.true_contact_force()))
    r.move_linear(goal, speed=0.05, accel=0.5)
    assert max(forces) == 0.0  # 2 mm above the table: no contact yet
    r.speed_linear([0, 0, -0.01, 0, 0, 0], accel=0.5)  # guarded move: touch down gently
    for _ in range(500):
        r.step(0.002)
        if r.true_contact_force() > 1.0:
            break
    assert r.true_contact_force() > 1.0
    r.stop(decel=1.0)
    assert 0.0 < r.true_contact_force() < r.limits.max_contact_force  # resting on the table, not pressing
    assert not r.is_faulted()
    r.gripper(open=True)
    up = r.tcp_pose()
    up[2, 3] += 0.1
    r.move_linear(up, speed=0.1)
    r.step(0.5)
    cup = r.cup_pose()
    assert abs(cup[2, 3] - top) < 3e-3 and cup[2, 2] > 0.99  # standing upright on the table
    liquid_z = [r.data.body(f"liquid_{i}").xpos[2] for i in range(8)]
    assert min(liquid_z) > top  # nothing spilled


def test_collision_protective_stop_keeps_holding() -> None:
    r = _table_robot(gap=0.05)
    T0 = r.tcp_pose()
    goal = T0.copy()
    goal[2, 3] -= 0.15  # 10 cm into the table
    with pytest.raises(RobotFault, match="protective stop"):
        r.move_linear(goal, speed=0.05, accel=0.5)
    assert r.is_faulted() and "contact force" in r.fault()
    assert r.holding() and not r.gripper_is_open()
    assert not r.is_moving()
    z = r.tcp_pose()[2, 3]
    r.step(0.3)
    assert abs(r.tcp_pose()[2, 3] - z) < 2e-3  # stays put
    assert r.holding()
    with pytest.raises(RobotFault, match="faulted"):
        r.move_linear(T0)
    r.clear_fault()
    r.move_linear(T0, speed=0.05)  # backing off is allowed after acknowledging
    assert np.linalg.norm(r.tcp_pose()[:3, 3] - T0[:3, 3]) < 1e-3
    assert r.true_contact_force() == 0.0 and r.contact_force() == 0.0 and not r.is_faulted()


@pytest.mark.parametrize("bad", [np.full((4, 4), np.nan), np.eye(3), "x"])
def test_malformed_targets_raise_without_moving(robot: SimRobot, bad: object) -> None:
    q0 = robot.joint_positions()
    with pytest.raises(ValueError):
        robot.move_linear(bad)
    robot.step(0.05)
    np.testing.assert_allclose(robot.joint_positions(), q0, atol=1e-4)
    assert not robot.is_faulted()


def test_nan_twist_and_bad_speed_raise(robot: SimRobot) -> None:
    with pytest.raises(ValueError, match="NaN"):
        robot.speed_linear([0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="speed"):
        robot.move_linear(robot.tcp_pose(), speed=-1.0)
    assert not robot.is_moving()


def test_unreachable_target_raises_without_moving(robot: SimRobot) -> None:
    q0 = robot.joint_positions()
    far = robot.tcp_pose()
    far[:3, 3] = [1.5, 0.0, 0.3]  # beyond the 0.85 m reach
    with pytest.raises(RobotFault, match="unreachable"):
        robot.move_linear(far)
    robot.step(0.05)
    np.testing.assert_allclose(robot.joint_positions(), q0, atol=1e-4)
    assert not robot.is_faulted() and robot.holding()


def test_step_callbacks_run_in_lockstep(robot: SimRobot) -> None:
    ts: list[float] = []
    cb = lambda m, d, t: ts.append(t)  # noqa: E731
    robot.add_step_callback(cb)
    robot.step(0.1)
    assert len(ts) == 50 and np.allclose(np.diff(ts), 0.002)
    robot.remove_step_callback(cb)
    robot.step(0.01)
    assert len(ts) == 50


def test_robot_limits_json_roundtrip(tmp_path) -> None:
    lim = RobotLimits(max_linear_speed=0.1, max_contact_force=30.0)
    p = tmp_path / "limits.json"
    lim.save(p)
    assert RobotLimits.load(p) == lim
    assert json.loads(p.read_text())["max_contact_force"] == 30.0
    with pytest.raises(ValueError, match="max_linear_speed"):
        RobotLimits(max_linear_speed=-1)
    with pytest.raises(ValueError, match="unknown"):
        RobotLimits.from_dict({"speed": 1})


def test_trapezoid_profile() -> None:
    p = TrapezoidProfile(1.0, 0.5, 1.0)
    assert p.duration == pytest.approx(2.5)
    assert p.at(p.duration) == (1.0, 0.0)
    assert p.at(1.0)[1] == pytest.approx(0.5)
    tri = TrapezoidProfile(0.1, 1.0, 1.0)  # never reaches v_max
    assert tri.v_peak == pytest.approx(np.sqrt(0.1))


def test_speed_linear_past_the_workspace_edge_faults_and_holds(robot: SimRobot) -> None:
    with pytest.raises(RobotFault, match="cannot follow"):
        robot.speed_linear([-0.2, 0, 0, 0, 0, 0], accel=1.0, duration=4.0)  # outward, beyond the reach
    assert robot.is_faulted() and robot.holding() and not robot.gripper_is_open()
    p = robot.tcp_pose()[:3, 3]
    robot.step(0.3)
    assert np.linalg.norm(robot.tcp_pose()[:3, 3] - p) < 2e-3
    with pytest.raises(RobotFault):
        robot.speed_linear([0.05, 0, 0, 0, 0, 0])


def test_moved_base_poses_stay_in_the_base_frame() -> None:
    from place_safe.robot.kinematics import Kinematics
    from place_safe.sim.robot import robot_spec

    spec = robot_spec(base_pos=[0.3, -0.2, 0.5], base_quat=[np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)])
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[2, 2, 0.1])
    model = spec.compile()
    r = SimRobot(model, mujoco.MjData(model))
    kin = Kinematics()
    q = r.joint_positions()
    np.testing.assert_allclose(r.tcp_pose(), kin.base_T_tcp(q), atol=1e-6)
    np.testing.assert_allclose(r.sensor_pose(), kin.base_T_sensor(q), atol=1e-6)
    np.testing.assert_allclose(r.world_T_base()[:3, 3], [0.3, -0.2, 0.5], atol=1e-9)
    assert r.holding()
    np.testing.assert_allclose(r.cup_pose(), kin.base_T_cup(q), atol=1e-3)
    goal = r.tcp_pose()
    goal[:3, 3] += [0.05, 0.05, 0.05]
    r.move_linear(goal, speed=0.1)
    assert np.linalg.norm(r.tcp_pose()[:3, 3] - goal[:3, 3]) < 1e-3


def test_move_joint_reaches_target(robot: SimRobot) -> None:
    q0 = robot.joint_positions()
    goal = q0 + np.array([0.6, 0.2, -0.2, 0.1, 0.0, 0.5])
    t0 = robot.time()
    robot.move_joint(goal, speed=1.0, accel=1.4)
    assert np.abs(robot.joint_positions() - goal).max() < 1e-3
    assert robot.time() - t0 < 2.5
    with pytest.raises(ValueError, match="finite"):
        robot.move_joint([0, 0, np.nan, 0, 0, 0])
    with pytest.raises(RobotFault, match="elbow_joint"):
        robot.move_joint([0, -1.5, 4.0, -1.5, -1.5, 0])  # elbow limit is +-pi
    assert not robot.is_faulted()


def test_cup_stays_in_the_gripper_and_liquid_in_the_cup_at_placement_speeds(robot: SimRobot) -> None:
    offsets: list[float] = []
    grasp = np.array([0.0, 0.0, 0.18])
    robot.add_step_callback(lambda m, d, t: offsets.append(
        float(np.linalg.norm((np.linalg.inv(robot.flange_pose()) @ robot.cup_pose())[:3, 3] - grasp))))
    T0 = robot.tcp_pose()
    goal = T0.copy()
    goal[:3, 3] += [0.2, 0.15, -0.1]
    robot.move_linear(goal, speed=0.25, accel=1.2)  # the RobotLimits maxima
    robot.move_linear(T0, speed=0.25, accel=1.2)
    assert max(offsets) < 1e-3
    assert robot.liquid_spilled() == 0


def test_tilting_the_cup_spills_the_liquid(robot: SimRobot) -> None:
    q = robot.joint_positions()
    q[4] += 2.2  # tilt the tool by about 126 deg
    robot.move_joint(q, speed=1.0)
    robot.step(1.0)
    assert robot.holding()
    assert robot.liquid_spilled() >= 6


def test_reset_restores_home_holding_the_cup(robot: SimRobot) -> None:
    home_tcp = robot.tcp_pose()
    robot.gripper(open=True)
    goal = robot.tcp_pose()
    goal[2, 3] += 0.05
    robot.move_linear(goal)
    assert not robot.holding()
    robot.reset()
    assert robot.time() == 0.0 and robot.holding() and not robot.is_faulted()
    np.testing.assert_allclose(robot.tcp_pose(), home_tcp, atol=1e-9)
    robot.step(0.3)
    fTc = np.linalg.inv(robot.flange_pose()) @ robot.cup_pose()
    np.testing.assert_allclose(fTc[:3, 3], [0, 0, 0.18], atol=5e-4)
    assert robot.liquid_spilled() == 0


def test_joint_limit_during_speed_linear_faults_and_holds() -> None:
    upper = [6.2832, 6.2832, 3.1416, 6.2832, 6.2832, 0.5]  # wrist_3 limited to 0.5 rad
    robot = SimRobot.load(limits=RobotLimits(joint_upper=upper))
    with pytest.raises(RobotFault, match="wrist_3_joint"):
        robot.speed_linear([0, 0, 0, 0, 0, -0.8], accel=2.0, duration=2.0)  # tool points down: -wz turns wrist_3 up
    assert robot.is_faulted() and robot.holding()
    assert robot.joint_positions()[5] < 0.5 + 0.02


def test_a_stop_asked_harder_than_the_arm_allows_is_an_emergency_stop_at_its_decel(robot: SimRobot) -> None:
    """Like the ur_rtde driver: a stop asked harder than max_linear_accel decelerates at most at the robot
    file's emergency_decel (2 m/s^2), never kinder (shorter) than the real arm's."""
    robot.speed_linear([0, 0, 0.2, 0, 0, 0], accel=1.2)
    robot.step(0.4)
    p0 = robot.tcp_pose()[:3, 3].copy()
    robot.stop(decel=10.0)
    braking = float(np.linalg.norm(robot.tcp_pose()[:3, 3] - p0))
    assert robot.emergency_decel == 2.0
    assert braking >= 0.9 * 0.2 ** 2 / (2 * 2.0)  # 10 mm at 2 m/s^2 (1 mm at the 10 m/s^2 asked)


def test_the_contact_latency_follows_the_force_noise_at_rest() -> None:
    """The simulated CB3 at its documented 3.6 N reports a 10 N touch 48 ms late; one whose force estimate is noisier
    (6 N) raised its detector's threshold when it zeroed and reports it later (what the placement loop takes)."""
    assert SimRobot.load().contact_latency() == 0.048
    noisy = SimRobot.load(force_noise=6.0)
    assert noisy.contact_latency() > 0.2  # (inf: a detector that misses more than 1 in 20 such touches)
