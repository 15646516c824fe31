"""The generated UR5 model files: up to date with config.json, complete, sensor field of view clear of the cup."""

from __future__ import annotations

import xml.etree.ElementTree as ET

import mujoco
import numpy as np
import pytest

from place_safe.robot.description import ur5_config, ur5_config_path, ur5_mjcf_path, ur5_urdf_path
from place_safe.robot import model_generator as gen
from place_safe.sensor.frame import ZONE_RECTS


@pytest.fixture(scope="module")
def model() -> mujoco.MjModel:
    return mujoco.MjModel.from_xml_path(str(ur5_mjcf_path()))


def test_regenerating_reproduces_committed_files() -> None:
    for path, text in gen.generate(ur5_config_path()).items():
        assert path.read_text(encoding="utf-8") == text, f"{path.name} is stale: run the generator"
    assert gen.main(["--check"]) == 0


def test_packaged_paths_exist() -> None:
    for p in (ur5_mjcf_path(), ur5_urdf_path(), ur5_config_path()):
        assert p.is_file(), p
    assert set(ur5_config()) >= {"arm", "gripper", "sensor", "cup"}


def test_mjcf_has_the_named_parts(model: mujoco.MjModel) -> None:
    names = {
        mujoco.mjtObj.mjOBJ_JOINT: ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                                    "wrist_2_joint", "wrist_3_joint", "finger_left", "finger_right"],
        mujoco.mjtObj.mjOBJ_ACTUATOR: ["shoulder_pan_joint", "elbow_joint", "wrist_3_joint", "finger_left",
                                       "finger_right"],
        mujoco.mjtObj.mjOBJ_SITE: ["tcp", "tof_sensor", "flange", "cup_bottom"],
        mujoco.mjtObj.mjOBJ_BODY: ["base", "flange", "cup"] + [f"liquid_{i}" for i in range(8)],
        mujoco.mjtObj.mjOBJ_EQUALITY: ["cup_grasp"],
    }
    for kind, ns in names.items():
        for n in ns:
            assert mujoco.mj_name2id(model, kind, n) >= 0, f"missing {kind.name} {n}"
    assert model.opt.timestep == pytest.approx(0.002)
    assert model.nu == 8
    # the arm sits on a base body at the world origin
    assert model.body("base").parentid[0] == 0
    np.testing.assert_allclose(model.body("base").pos, 0.0)


def test_urdf_has_tool_frames() -> None:
    root = ET.parse(ur5_urdf_path()).getroot()
    links = {e.get("name") for e in root.findall("link")}
    assert {"base_link", "flange", "tcp", "tof_sensor", "cup"} <= links
    revolute = [e.get("name") for e in root.findall("joint") if e.get("type") == "revolute"]
    assert revolute == ["shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
                        "wrist_2_joint", "wrist_3_joint"]


def test_masses_follow_published_values(model: mujoco.MjModel) -> None:
    cfg = ur5_config()["arm"]
    for link, m in zip(cfg["link_names"], cfg["masses"]):
        assert model.body(link).mass[0] == pytest.approx(m)
    cup = ur5_config()["cup"]
    assert model.body("cup").mass[0] == pytest.approx(cup["mass"])
    assert 2 * cup["radius"] == pytest.approx(0.07) and cup["height"] == pytest.approx(0.09)


def test_sensor_field_of_view_misses_cup_liquid_and_fingers(model: mujoco.MjModel) -> None:
    """Rays over the whole 33x33 deg field of view (zone rectangles on z=1) hit no part of the held cup,
    the liquid or the fingers, with the fingers closed and open."""
    data = mujoco.MjData(model)
    home = ur5_config()["arm"]["home"]
    qadr = [model.jnt_qposadr[model.joint(j).id] for j in ur5_config()["arm"]["joint_names"]]
    rects = np.asarray(ZONE_RECTS)  # per zone (x0, x1, y0, y1) on the plane z = 1
    xs = np.linspace(rects[:, 0].min(), rects[:, 1].max(), 15)
    ys = np.linspace(rects[:, 2].min(), rects[:, 3].max(), 15)
    assert xs[-1] == pytest.approx(0.294) and ys[-1] == pytest.approx(0.291)
    group = np.array([1, 1, 1, 1, 1, 1], dtype=np.uint8)  # every group: environment, cup + liquid, robot
    flange = model.body("flange").id
    for opening in (0.0, 0.03):
        data.qpos[qadr] = home
        for f in ("finger_left", "finger_right"):
            data.qpos[model.jnt_qposadr[model.joint(f).id]] = opening
        mujoco.mj_forward(model, data)
        s = model.site("tof_sensor").id
        R, p = data.site_xmat[s].reshape(3, 3), data.site_xpos[s].copy()
        geomid = np.zeros(1, dtype=np.int32)
        for x in xs:
            for y in ys:
                v = R @ np.array([x, y, 1.0])
                v /= np.linalg.norm(v)
                dist = mujoco.mj_ray(model, data, p, v, group, 1, flange, geomid)
                hit = "" if geomid[0] < 0 else model.geom(geomid[0]).name
                assert dist < 0, f"ray ({x:.3f}, {y:.3f}) hits {hit} at {dist:.3f} m (opening {opening})"
