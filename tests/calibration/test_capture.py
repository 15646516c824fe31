"""Capture on the Robot interface: the UR5 driver over the fake ur_rtde (kinematic arm) sweeps above a plane
touched by guarded descents; frames carry the ground truth, flange pose and joints; resumable; poses outside
the robot's limits are refused and listed."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from place_safe.calibration.capture import (TOUCH_HEIGHT_STD, SweepPlan, capture_sweep, level_plane, lowest_tool_point,
                                            plane_in_sensor, sensor_target, touch_plane, touched_reference)
from place_safe.drivers.ur5 import URConfig, URRobot, packaged_config
from place_safe.drivers.ur5 import fake_rtde
from place_safe.drivers.ur5.kinematic_arm import KinematicArm
from place_safe.exceptions import FrameFileError, RobotFault, SensorTimeout
from place_safe.io.frame_file import load_frames
from place_safe.sensor.frame import Frame

TABLE_Z = 0.05  # m, the table top in the base frame (the kinematic arm's TCP starts at 0.29 m)


class ClockSource:
    """A sensor that delivers one blank frame per call, stamped on the robot's clock."""

    def __init__(self, robot):
        self.robot = robot

    def read(self, timeout=1.0):
        return Frame(np.full((9, 128), 100.0), np.full(128, 100.0), timestamp=self.robot.time())

    def close(self):
        pass


@pytest.fixture(scope="module")
def kin():
    from place_safe.robot.kinematics import Kinematics

    return Kinematics()


def _robot(kin, tilt_deg=0.0, **limits):
    n = np.array([math.sin(math.radians(tilt_deg)), 0.0, math.cos(math.radians(tilt_deg))])
    arm = KinematicArm(kinematics=kin, contact_plane=(n, TABLE_Z * n[2] + -0.49 * n[0]))
    fake = fake_rtde.FakeUR(arm, force_noise=3.6, force_offset=(0.0, 0.0, 4.0))  # CB3-like force estimate
    cfg = URConfig.load(packaged_config("sim"))
    for k, v in limits.items():
        setattr(cfg.limits, k, v)
    return URRobot(cfg, modules=fake_rtde.modules(), out=lambda s: None).connect(), fake


@pytest.mark.slow
def test_guarded_descent_touches_a_tilted_plane_at_three_points(kin):
    robot, fake = _robot(kin, tilt_deg=3.0)
    pts = [(-0.46, -0.08), (-0.52, -0.08), (-0.49, -0.14)]
    n, d, P = touch_plane(robot, pts, start_height=0.08, speed=0.005, force_threshold=15.0)
    assert math.degrees(math.acos(n[2])) == pytest.approx(3.0, abs=0.3)
    true_d = TABLE_Z * math.cos(math.radians(3)) - 0.49 * math.sin(math.radians(3))
    assert d == pytest.approx(true_d, abs=0.0015)  # within the spring's give at the threshold
    assert robot.fault() is None and fake.safety_mode == fake_rtde.SAFETY_NORMAL
    names = [c[1] for c in fake.commands]
    # per point a guarded descent and a slow rise until the contact detector lets go (each ended by speedStop)
    assert names.count("speedL") == 6 and names.count("speedStop") >= 6


def test_touch_without_contact_is_an_error(kin):
    robot, _ = _robot(kin)
    with pytest.raises(RobotFault, match="no contact"):
        touch_plane(robot, [(-0.49, -0.1)] * 3, start_height=0.2, speed=0.02, max_depth=0.02)


def test_a_touched_plane_states_how_far_it_may_be_off():
    """Three touches 8 cm apart, each contact's height 0.1 mm uncertain: the normal within 0.124 deg along its worst
    direction (the diagonal), the offset at their centroid within 0.1 / sqrt(3) mm. A fourth touch 0.3 mm off the
    plane of the others shows a larger scatter than the stated one, which then holds; wider touches fix the tilt
    better; points on a line, or not finite, fix no plane."""
    base = np.array([0.4, -0.1, 0.05])
    three = base + np.array([[0.0, 0.0, 0.0], [0.08, 0.0, 0.0], [0.0, 0.08, 0.0]])
    r = touched_reference(three)
    assert TOUCH_HEIGHT_STD == 1e-4 and r.points == 3 and r.height_std == pytest.approx(1e-4)
    assert math.degrees(r.tilt_std) == pytest.approx(math.degrees(math.sqrt(3) * 1e-4 / 0.08), rel=1e-6)
    assert math.degrees(r.tilt_std) == pytest.approx(0.124, abs=5e-4)
    assert r.offset_std == pytest.approx(1e-4 / math.sqrt(3))
    four = np.vstack([three, base + [0.08, 0.08, 3e-4]])
    assert touched_reference(four).height_std > 1e-4 and touched_reference(four).points == 4
    assert touched_reference(base + 2.0 * (three - base)).tilt_std == pytest.approx(r.tilt_std / 2.0)
    for bad in (three[:2], base + np.outer([0.0, 1.0, 2.0], [0.04, 0.0, 0.0]), np.where(three > 0.3, np.nan, three),
                base + [[0.0, 0.0, 0.0], [0.08, 0.0, 0.0], [0.16, 1e-4, 0.0]]):  # the last nearly on a line
        with pytest.raises(ValueError, match="plane"):
            touched_reference(bad)
    with pytest.raises(ValueError, match="disagree by 9.8 mm"):  # a fourth touch on something else
        touched_reference(np.vstack([three, base + [0.08, 0.08, 0.02]]))


def test_sensor_target_geometry():
    plane = level_plane(0.0)
    for inc, az in [(0.0, 0.0), (math.radians(20), math.radians(135))]:
        T = sensor_target(plane, np.array([0.1, 0.2, 0.0]), 0.15, inc, az, np.array([1.0, 0.0, 0.0]))
        p = plane_in_sensor(plane, T)
        assert p.offset == pytest.approx(0.15) and math.acos(p.normal[2]) == pytest.approx(inc, abs=1e-9)
        # the optical axis hits the centre
        hit = T[:3, 3] + T[:3, 2] * (p.offset / p.normal[2])
        np.testing.assert_allclose(hit, [0.1, 0.2, 0.0], atol=1e-9)


@pytest.mark.slow
def test_capture_writes_truth_poses_joints_resumes_and_refuses(kin, tmp_path):
    robot, fake = _robot(kin, min_descent_z=0.11, workspace_min=(-0.9, -0.9, 0.11))  # the TCP may not go below 11 cm
    plan = SweepPlan(distances=[0.10, 0.07], incidences=[0.0, math.radians(15)], azimuths=[0.0, math.pi],
                     settle_s=0.05, speed=0.2)  # the 7 cm poses keep the gripper clear of the table: the box refuses
    out = tmp_path / "cap.jsonl"
    first = SweepPlan(**{**plan.to_dict(), "max_poses": 2})
    res = capture_sweep(robot, ClockSource(robot), first, out, plane=level_plane(TABLE_Z), tool=robot.tool,
                        progress=False, log=lambda s: None)
    assert res.captured == 1 and len(res.refused) == 1  # the subsample is poses 0 and 5; 5 is too low
    res = capture_sweep(robot, ClockSource(robot), plan, out, plane=level_plane(TABLE_Z), tool=robot.tool,
                        progress=False, log=lambda s: None, reference=touched_reference(
                            [(-0.46, -0.08, TABLE_Z), (-0.54, -0.08, TABLE_Z), (-0.46, -0.16, TABLE_Z)]))
    assert res.skipped_done == 1 and res.poses == 6  # pose 0 was in the file (pose 5 of the subsample was not)
    assert len(res.refused) == 3 and all("workspace box" in r["reason"] for r in res.refused)
    assert {r["distance"] for r in res.refused} == {0.07}
    frames = load_frames(out)
    assert len(frames) == 3
    for f in frames:
        flange = np.asarray(f.extra["pose"])
        np.testing.assert_allclose(kin.base_T_flange(f.extra["joint_angles"]), flange, atol=1e-6)
        sensor = flange @ robot.tool.flange_T_sensor
        truth = plane_in_sensor(level_plane(TABLE_Z), sensor)
        assert f.truth.offset == pytest.approx(truth.offset) and f.truth.offset == pytest.approx(
            f.extra["meta"]["distance"], abs=0.002)
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert sorted(d["meta"]["pose_index"] for d in lines) == [0, 1, 2]
    # the frames of the second run carry how far the touched plane may be off; the first run's stated nothing
    refs = [d["meta"]["base_plane"].get("reference") for d in sorted(lines, key=lambda d: d["meta"]["pose_index"])]
    assert refs[0] is None and all(r["points"] == 3 and r["tilt_std"] > 0 for r in refs[1:])


def test_capture_refuses_before_moving_a_pose_that_would_take_the_gripper_into_the_plane(kin, tmp_path):
    """The packaged gripper's tips reach 30 mm past the sensor: a level sweep's 2 and 3 cm poses would press them into
    the table (in simulation a protective stop at 70 N ended the capture at its first pose). They are refused and
    listed with the clearance they would have had, the arm is not sent there, and the sweep goes on."""
    robot, fake = _robot(kin)
    plan = SweepPlan(distances=[0.02, 0.033, 0.036, 0.10], incidences=[0.0], settle_s=0.05, speed=0.2)
    moves = []
    move = robot.move_linear
    robot.move_linear = lambda T, **kw: (moves.append(T[2, 3]), move(T, **kw))[1]
    res = capture_sweep(robot, ClockSource(robot), plan, tmp_path / "c.jsonl", plane=level_plane(TABLE_Z),
                        tool=robot.tool, progress=False, log=lambda s: None)
    assert res.captured == 2 and [r["distance"] for r in res.refused] == [0.02, 0.033]  # 3 mm: within the 5 mm
    assert "-10.0 mm from the plane" in res.refused[0]["reason"] and "5 mm clearance" in res.refused[0]["reason"]
    assert len(moves) == 2 and min(moves) > TABLE_Z + plan.min_clearance  # the TCP was never sent closer
    assert not robot.is_faulted() and fake.arm.contact_force() == 0.0


def test_lowest_tool_point_is_the_lowest_of_the_tcp_the_flange_and_the_sensor():
    """With the TCP 0.2 m out along the flange's z: pointing the TCP up puts the flange below it; pointing it down
    puts the TCP lowest (the sensor, 0.1 m along the flange's z, lies between them either way)."""
    from place_safe.robot.tool import ToolFrames

    tcp, sensor = np.eye(4), np.eye(4)
    tcp[2, 3] = 0.2
    sensor[:3, 3] = [0.05, 0.0, 0.1]
    tool = ToolFrames(tcp, sensor, tcp)
    table = (np.array([0.0, 0.0, 1.0]), 0.0)
    up = np.eye(4)  # the TCP's z, and the flange's, point up, away from the table
    up[:3, 3] = [0.3, 0.0, 0.4]
    part, h = lowest_tool_point(table, up, tool)
    assert part == "flange" and h == pytest.approx(0.2)
    down = np.diag([1.0, -1.0, -1.0, 1.0])  # rotated 180 deg about x: the TCP's z points down at the table
    down[:3, 3] = [0.3, 0.0, 0.4]
    part, h = lowest_tool_point(table, down, tool)
    assert part == "TCP" and h == pytest.approx(0.4)


def test_capture_refuses_a_pose_that_would_take_the_flange_into_the_plane(kin, tmp_path):
    """A sensor mounted looking back up the tool (the optical axis along the flange's -z): to look down at the table
    the arm points the TCP up, and the flange, not the TCP, comes nearest the table. The TCP-only check sent the
    flange into the table (a protective stop); every such pose is now refused before the arm moves, naming the flange."""
    robot, fake = _robot(kin)
    flip = np.diag([1.0, -1.0, -1.0, 1.0])  # rotated 180 deg about x: the sensor looks along the flange's -z
    tool = robot.tool.with_sensor(robot.tool.flange_T_sensor @ flip)
    plan = SweepPlan(distances=[0.10], incidences=[0.0], settle_s=0.05, speed=0.2)
    moves = []
    move = robot.move_linear
    robot.move_linear = lambda T, **kw: (moves.append(T), move(T, **kw))[1]
    res = capture_sweep(robot, ClockSource(robot), plan, tmp_path / "f.jsonl", plane=level_plane(TABLE_Z), tool=tool,
                        progress=False, log=lambda s: None)
    assert res.captured == 0 and len(res.refused) == 1 and not moves
    assert res.refused[0]["reason"].startswith("the flange would come -")
    assert not robot.is_faulted() and fake.arm.contact_force() == 0.0


def test_capture_stops_on_a_latched_fault_and_a_dead_sensor(kin, tmp_path):
    robot, fake = _robot(kin)

    class Dead(ClockSource):
        def read(self, timeout=1.0):
            raise SensorTimeout("no frame")

    plan = SweepPlan(distances=[0.12], incidences=[0.0], settle_s=0.0, frame_timeout_s=0.1)
    with pytest.raises(SensorTimeout):
        capture_sweep(robot, Dead(robot), plan, tmp_path / "a.jsonl", plane=level_plane(TABLE_Z), tool=robot.tool,
                      progress=False)
    fake.inject_protective_stop(fake.time + 0.1)
    with pytest.raises(RobotFault, match="rerun to resume"):
        capture_sweep(robot, ClockSource(robot), SweepPlan(distances=[0.2], incidences=[0.0]), tmp_path / "b.jsonl",
                      plane=level_plane(TABLE_Z), tool=robot.tool, progress=False)


def test_capture_never_appends_to_a_file_that_is_not_a_capture(kin, tmp_path):
    """``-o`` naming a calibration, a JSON list of frames or text: one-line error, the file untouched (frames were
    appended to it and it no longer parsed). A capture interrupted mid-line resumes on a line of its own."""
    from place_safe.exceptions import FrameFileError

    robot, _ = _robot(kin)
    plan = SweepPlan(distances=[0.10, 0.12], incidences=[0.0], settle_s=0.05, speed=0.2)
    frame = json.dumps({"hists": [], "meta": {"pose_index": 0}})
    for name, text in (("cal.json", '{\n "format": "place_safe.calibration/1"\n}\n'), ("list.json", '[{"hists": []}]'),
                       ("notes.txt", "my notes\nmore\n"), ("noted.jsonl", frame + '\n{"note": "a complete line"}'),
                       ("float.jsonl", json.dumps({"meta": {"pose_index": 2.9}}) + "\n")):
        f = tmp_path / name
        f.write_text(text)
        with pytest.raises(FrameFileError, match="not a capture"):
            capture_sweep(robot, ClockSource(robot), plan, f, plane=level_plane(TABLE_Z), tool=robot.tool,
                          progress=False, log=lambda s: None)
        assert f.read_text() == text
    out = tmp_path / "cap.jsonl"
    capture_sweep(robot, ClockSource(robot), SweepPlan(**{**plan.to_dict(), "max_poses": 1}), out,
                  plane=level_plane(TABLE_Z), tool=robot.tool, progress=False, log=lambda s: None)
    out.write_text(out.read_text() + '{"hists": [[1, 2')  # the run after it was cut off mid-frame
    res = capture_sweep(robot, ClockSource(robot), plan, out, plane=level_plane(TABLE_Z), tool=robot.tool,
                        progress=False, log=lambda s: None)
    assert res.skipped_done == 1 and res.captured == 1 and len(load_frames(out)) == 2


def test_a_capture_made_with_another_plan_is_not_resumed(tmp_path):
    """A capture resumed with other --distances (or --poses, which subsamples the grid anew) counted the first plan's
    poses as done by their index: "0 poses captured now, 2 already there", and the new plan's poses 0 and 1 were never
    captured (session 82). A pose there that is not the plan's pose of its index is named; the same plan resumes."""
    from place_safe.calibration.capture import resume_problem

    plan = SweepPlan(distances=[0.08, 0.12], incidences=[0.0, math.radians(12)], azimuths=[0.0, math.pi])
    out = tmp_path / "cap.jsonl"
    assert resume_problem(out, plan) is None  # no file: nothing to resume
    lines = [{"hists": [[0] * 128] * 9, "meta": {"pose_index": i, "distance": d, "incidence": inc, "azimuth": az}}
             for i, (d, inc, az) in enumerate(plan.grid()[:2])]
    out.write_text("".join(json.dumps(x) + "\n" for x in lines))
    assert resume_problem(out, plan) is None
    far = SweepPlan(**{**plan.to_dict(), "distances": [5.0, 0.12]})
    assert resume_problem(out, far) == ("pose 0 there is at 80 mm, incidence 0 deg, azimuth 0 deg; this plan's pose 0 "
                                        "at 5000 mm, 0 deg, 0 deg")
    fewer = SweepPlan(**{**plan.to_dict(), "max_poses": 1})
    assert resume_problem(out, fewer) == "pose 1 there is beyond this plan's 1 poses"
    with pytest.raises(FrameFileError, match="is a capture made with another plan"):
        capture_sweep(None, None, far, out, plane=level_plane(TABLE_Z), tool=None, progress=False)


def test_a_capture_reads_its_output_once(kin, tmp_path, monkeypatch):
    """capture read its output up to four times before capturing (the "is it a capture" check, the resume check in the
    command and again in capture_sweep, then the indices with the cut of an unfinished line: session 83). Read once by
    read_capture and passed on, the sweep reads it no more, and resumes as before: the done pose skipped, the
    interrupted line cut off. A file written to between the reading and the sweep is read again before it is cut."""
    import builtins

    import place_safe.calibration.capture as capture
    from place_safe.calibration.capture import read_capture

    robot, _ = _robot(kin)
    plan = SweepPlan(distances=[0.10, 0.12], incidences=[0.0], settle_s=0.05, speed=0.2)
    out = tmp_path / "cap.jsonl"
    capture_sweep(robot, ClockSource(robot), SweepPlan(**{**plan.to_dict(), "max_poses": 1}), out,
                  plane=level_plane(TABLE_Z), tool=robot.tool, progress=False, log=lambda s: None)
    whole = out.read_text()
    out.write_text(whole + '{"hists": [[1, 2')  # the run after it was cut off mid-frame
    reads = []

    def counting_open(file, mode="r", *args, **kwargs):
        if "r" in mode and "+" not in mode:
            reads.append(str(file))
        return builtins.open(file, mode, *args, **kwargs)

    monkeypatch.setattr(capture, "open", counting_open, raising=False)
    existing = read_capture(out)
    assert existing.done == {0} and existing.cut_at == len(whole.encode()) and reads == [str(out)]
    res = capture_sweep(robot, ClockSource(robot), plan, out, plane=level_plane(TABLE_Z), tool=robot.tool,
                        progress=False, log=lambda s: None, existing=existing)
    assert reads == [str(out)]  # once, by read_capture
    assert res.skipped_done == 1 and res.captured == 1 and len(load_frames(out)) == 2
    # written to after it was read: the offset read then is not cut; the file is read again
    out.write_text(whole + '{"hists": [[1, 2')
    existing = read_capture(out)
    out.write_text(whole + json.dumps(json.loads(whole.splitlines()[0]) | {"meta": {"pose_index": 1}}) + "\n"
                   + '{"hists": [[1')
    after = existing.cut()
    assert after.done == {0, 1} and after.cut_at is None
    assert out.read_text().endswith("\n") and [json.loads(x)["meta"]["pose_index"] for x in
                                               out.read_text().splitlines()] == [0, 1]
