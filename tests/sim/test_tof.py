"""The simulated TMF8820 (place_safe.sim.tof): ray geometry, mixed returns, materials, timing, faults."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from place_safe.exceptions import FrameError, SensorTimeout  # noqa: E402
from place_safe.io.frame_file import load_frames  # noqa: E402
from place_safe.geometry import Plane  # noqa: E402
from place_safe.sensor.frame import Frame  # noqa: E402
from place_safe.sim.scene import Material, SceneConfig, TableConfig, build_scene  # noqa: E402
from place_safe.sensor.histogram import first_return as first_peak  # noqa: E402
from place_safe.sim.tof import SimToF, ToFConfig  # noqa: E402

SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"
H = 0.75  # table top (m)


def rig(table: TableConfig | None = None, pos=(0.0, 0.0, H + 0.2), euler=(math.pi, 0.0, 0.0), **cfg) -> SimToF:
    t = table if table is not None else TableConfig(height=H, center=(0.0, 0.0), size=(1.0, 1.0, 0.04))
    scene = build_scene(SceneConfig(table=t, rig_pos=pos, rig_euler=euler))
    return SimToF(scene, config=ToFConfig(**cfg))


def analytic(tof: SimToF, n_world: np.ndarray, point: np.ndarray) -> tuple[Plane, np.ndarray]:
    """Plane in the sensor frame and the range along every ray, from the geometry alone."""
    pos, R = tof.sensor_pose()
    n_s = R.T @ n_world
    plane = Plane(n_s, float(n_s @ (R.T @ (point - pos))))
    return plane, plane.offset / (tof.directions @ plane.normal)


def test_level_table_ranges_normals_and_truth():
    tof = rig(euler=(math.pi + 0.15, -0.1, 0.3))
    ret = tof.cast()
    assert ret.hit.all() and (ret.geom == tof.scene.table_geom).all()
    plane, ranges = analytic(tof, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, H]))
    np.testing.assert_allclose(ret.ranges, ranges, atol=1e-6)
    np.testing.assert_allclose(np.abs(ret.normals @ np.array([0.0, 0.0, 1.0])), 1.0, atol=1e-6)
    np.testing.assert_allclose(ret.cos_inc, tof.directions @ plane.normal, atol=1e-6)
    truth = tof.measure().truth
    np.testing.assert_allclose(truth.normal, plane.normal, atol=1e-9)
    assert truth.offset == pytest.approx(plane.offset, abs=1e-9)


def test_tilted_table():
    tilt, az = math.radians(20.0), math.radians(45.0)
    table = TableConfig(height=H, center=(0.0, 0.0), size=(1.0, 1.0, 0.04), tilt=tilt, tilt_direction=az)
    tof = rig(table)
    n_w = np.array([math.sin(tilt) * math.cos(az), math.sin(tilt) * math.sin(az), math.cos(tilt)])
    ret = tof.cast()
    plane, ranges = analytic(tof, n_w, np.array([0.0, 0.0, H]))
    np.testing.assert_allclose(ret.ranges, ranges, atol=1e-6)
    np.testing.assert_allclose(np.abs(ret.normals.reshape(-1, 3) @ n_w), 1.0, atol=1e-6)
    assert plane.theta == pytest.approx(tilt, abs=1e-9)  # the sensor looks straight down
    truth = tof.measure(noise=False).truth
    np.testing.assert_allclose(truth.normal, plane.normal, atol=1e-9)
    assert truth.offset == pytest.approx(plane.offset, abs=1e-9)


def test_table_edge_gives_two_peaks():
    # near edge of the table at x = 0, under the sensor: rays with world x < 0 fall to the floor
    table = TableConfig(height=H, center=(0.5, 0.0), size=(1.0, 1.0, 0.04))
    tof = rig(table, pos=(0.0, 0.0, H + 0.2), noise=False)
    frame = tof.measure()
    assert frame.truth is None  # not every ray hits the table
    h = frame.hists[4] - tof.ambient[4]  # centre zone straddles the edge
    p = tof.params
    near = int(round(0.2 / p.bin_size + p.bin_offset))
    far = int(round((H + 0.2) / p.bin_size + p.bin_offset))
    peak_near = h[near - 3:near + 4].max()
    peak_far = h[far - 4:far + 5].max()
    valley = h[near + 12:far - 8].min()
    assert peak_far > 20 * np.sqrt(tof.ambient[4]) and peak_far > 5 * valley
    assert peak_near > peak_far  # the table is 4x closer


def test_checkerboard_albedo_follows_position():
    sq = 0.05  # a zone at 20 cm is about 4 cm wide: it sees one to four squares
    mat = Material(albedo=1.0, albedo2=0.2, pattern="checker", square=sq)
    table = TableConfig(height=H, center=(0.0, 0.0), size=(1.0, 1.0, 0.04), material=mat)
    tof = rig(table, noise=False)
    ret = tof.cast()
    # the level table's local frame is the world's shifted to its centre (0, 0, H - thickness / 2)
    cell = np.floor(ret.points[..., 0] / sq) + np.floor(ret.points[..., 1] / sq)
    expected = np.where(np.mod(cell, 2) == 1, 0.2, 1.0) * tof.params.albedo
    np.testing.assert_allclose(ret.albedo, expected)
    assert len(np.unique(np.round(ret.albedo, 9))) == 2
    # moving the sensor by half a square changes what each zone sees
    before = tof.measure().hists.sum(1)
    tof.scene.set_sensor_pose(tof.data, [sq / 2, 0.0, H + 0.2], tof.sensor_pose()[1])
    after = tof.measure().hists.sum(1)
    assert np.max(np.abs(after - before) / before) > 0.1


def test_streaming_at_30_hz_with_latency():
    tof = rig()
    frames = [tof.read(1.0) for _ in range(31)]
    ts = np.array([f.timestamp for f in frames])
    dt = tof.model.opt.timestep
    np.testing.assert_allclose(np.diff(ts), 1 / 30, atol=dt + 1e-9)
    assert tof.data.time >= ts[-1] + tof.config.latency - 1e-9
    assert tof.config.latency == pytest.approx(4182 * 9 / 400e3)
    for f in frames:
        f.validate()
        assert f.truth is not None and f.truth.offset == pytest.approx(0.2, abs=1e-9)
        assert f.reference is not None and np.all(f.hists >= 0) and np.all(f.hists == np.round(f.hists))
    back = Frame.from_dict(json.loads(json.dumps(frames[0].to_dict())))  # frames can be recorded as files
    np.testing.assert_array_equal(back.hists, frames[0].hists)
    assert back.timestamp == frames[0].timestamp and back.truth.offset == pytest.approx(0.2)


def test_drops_and_corruption_on_demand():
    tof = rig(drop_prob=0.4, seed=3)
    idx = [tof.read(1.0).extra["sim"]["index"] for _ in range(30)]
    assert tof.dropped > 0 and len(set(np.diff(idx))) > 1 and np.all(np.diff(idx) >= 1)
    bad = rig(corrupt_prob=1.0, seed=4)
    kinds = set()
    for _ in range(12):
        f = bad.read(1.0)
        kinds.add(f.extra["sim"]["corrupted"])
        with pytest.raises(FrameError):
            f.validate()
    assert kinds == {"nan", "truncated_hists", "truncated_reference"}
    never = rig(drop_prob=1.0)
    with pytest.raises(SensorTimeout):
        never.read(0.2)


def test_on_sensor_distances_like_the_real_sensor():
    real = [f for f in load_frames(SWEEP) if f.truth is not None and 0.1 < f.truth.z0 < 0.3]
    tof = rig(seed=5)
    for f in real[::3]:
        from scipy.spatial.transform import Rotation

        R = Rotation.align_vectors([[0.0, 0.0, -1.0]], [f.truth.normal])[0].as_matrix()
        tof.scene.set_sensor_pose(tof.data, [0.0, 0.0, H + f.truth.offset], R)
        sim = tof.measure()
        assert np.all(sim.confidences > 0)
        np.testing.assert_allclose(sim.distances, f.distances, atol=0.012)


def test_no_return_gives_zero_confidence():
    tof = rig(pos=(0.0, 0.0, H + 0.2), euler=(0.0, 0.0, 0.0))  # looking up at nothing
    f = tof.measure()
    assert not tof.cast().hit.any()
    assert np.all(f.distances == 0) and np.all(f.confidences == 0)
    assert not first_peak(f.hists)[1].any()


def test_lockstep_with_sim_robot():
    from place_safe.sim.robot import SimRobot

    scene = build_scene(SceneConfig(with_robot=True))
    robot = SimRobot(scene.model)
    tof = SimToF(scene, robot.data).attach(robot)
    with pytest.raises(SensorTimeout):
        tof.read(0.0)
    robot.step(0.3)
    f = tof.read(0.0)
    assert f.timestamp <= robot.data.time - tof.config.latency + 1e-9
    assert tof.overruns >= 1  # several frames finished while the robot stepped; the newest is returned
    sensor_z = robot.data.site_xpos[scene.sensor_site][2]
    assert f.truth is not None and f.truth.offset == pytest.approx(sensor_z - scene.config.table.height, abs=1e-6)


def test_matched_sensor_frames_give_back_the_table_plane():
    """With the estimator's own forward parameters as the true sensor (no noise, no floor), the
    differentiable estimator recovers the tilted table exactly: the simulator's sensor frame, zone
    order and ray geometry agree with the forward model's conventions."""
    from place_safe.recovery import make_estimator
    from place_safe.recovery.forward import ForwardParams
    from place_safe.geometry import rotation_angle_between

    est = make_estimator("diff")
    for tilt_deg, az, d in [(12.0, 0.7, 0.08), (22.0, -2.0, 0.25)]:
        table = TableConfig(height=H, center=(0.0, 0.0), size=(2.0, 2.0, 0.04), tilt=math.radians(tilt_deg),
                            tilt_direction=az)
        scene = build_scene(SceneConfig(table=table, rig_pos=(0.0, 0.0, H + d), rig_euler=(math.pi, 0.0, 0.4)))
        tof = SimToF(scene, config=ToFConfig(noise=False, ambient_range=(0.0, 0.0)), params=ForwardParams())
        frame = tof.measure()
        got = est.estimate(frame).plane
        assert math.degrees(rotation_angle_between(got.normal, frame.truth.normal)) < 0.1
        assert got.z0 == pytest.approx(frame.truth.z0, abs=5e-4)


def test_tilted_mount_is_undone_by_the_calibrated_estimator():
    """A sensor mounted 2.6 deg off its site: the estimator with the same mount tilt reports the site-frame plane."""
    import math

    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.evaluation.metrics import angular_error
    from place_safe.sim.scene import SceneConfig, build_scene
    from place_safe.sim.tof import SimToF, ToFConfig, true_params

    params = true_params().replace(mount_tilt=[0.02, -0.04])
    tof = SimToF(build_scene(SceneConfig()), config=ToFConfig(noise=False), params=params)
    frame = tof.measure()
    est = DifferentiableEstimator(params).estimate(frame)
    assert math.degrees(angular_error(est.plane, frame.truth)) < 0.05
    assert abs(est.plane.offset - frame.truth.offset) < 1e-4
    # without the calibration the tilt shows up as a tilted table
    naive = DifferentiableEstimator(params.replace(mount_tilt=[0.0, 0.0])).estimate(frame)
    assert math.degrees(angular_error(naive.plane, frame.truth)) > 2.0
