"""Kinematics: the MJCF (MuJoCo), the URDF (pytorch-kinematics) and the plain DH formula agree."""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

from place_safe.exceptions import RobotFault
from place_safe.robot.kinematics import Kinematics
from place_safe.robot.description import ur5_config, ur5_mjcf_path
from place_safe.robot import model_generator as gen

POS_TOL_M = 1e-4  # 0.1 mm
ROT_TOL_RAD = np.deg2rad(0.01)
N_CONFIGS = 60
JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint", "wrist_2_joint",
          "wrist_3_joint")


@pytest.fixture(scope="module")
def kin() -> Kinematics:
    return Kinematics()


@pytest.fixture(scope="module")
def configs() -> np.ndarray:
    rng = np.random.default_rng(4)
    lo = np.array([-np.pi, -np.pi, -np.pi, -np.pi, -np.pi, -np.pi])
    return rng.uniform(lo, -lo, size=(N_CONFIGS, 6))


def _rot_err(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def _assert_same(Ta: np.ndarray, Tb: np.ndarray, what: str) -> None:
    dp = float(np.linalg.norm(Ta[:3, 3] - Tb[:3, 3]))
    dr = _rot_err(Ta[:3, :3], Tb[:3, :3])
    assert dp < POS_TOL_M, f"{what}: position differs by {dp * 1e3:.4f} mm"
    assert dr < ROT_TOL_RAD, f"{what}: orientation differs by {np.rad2deg(dr):.5f} deg"


def test_mjcf_urdf_dh_agree(kin: Kinematics, configs: np.ndarray) -> None:
    cfg = ur5_config()
    model = mujoco.MjModel.from_xml_path(str(ur5_mjcf_path()))
    data = mujoco.MjData(model)
    qadr = [model.jnt_qposadr[model.joint(j).id] for j in JOINTS]
    sites = {"flange": np.eye(4), "tcp": gen.flange_T_tcp(cfg), "tof_sensor": gen.flange_T_sensor(cfg)}
    urdf = {name: kin.base_T(configs, name) for name in sites}  # batched
    for i, q in enumerate(configs):
        data.qpos[qadr] = q
        mujoco.mj_kinematics(model, data)
        base_T_flange_dh = gen.dh_fk(cfg, q)
        for name, flange_T in sites.items():
            s = model.site(name).id
            T_mj = np.eye(4)
            T_mj[:3, :3] = data.site_xmat[s].reshape(3, 3)
            T_mj[:3, 3] = data.site_xpos[s]
            T_dh = base_T_flange_dh @ flange_T
            _assert_same(T_mj, T_dh, f"MJCF vs DH, {name}, config {i}")
            _assert_same(urdf[name][i], T_dh, f"URDF vs DH, {name}, config {i}")
            _assert_same(kin.base_T(q, name), urdf[name][i], f"single vs batch, {name}, config {i}")


def test_named_accessors_and_shapes(kin: Kinematics, configs: np.ndarray) -> None:
    q = configs[0]
    assert kin.base_T_sensor(q).shape == (4, 4)
    assert kin.base_T_tcp(configs[:5]).shape == (5, 4, 4)
    np.testing.assert_allclose(kin.base_T_flange(q), kin.fk(q)["flange"])
    np.testing.assert_allclose(kin.base_T_cup(q), kin.fk(q)["cup"])
    assert kin.base_T_sensor(q).dtype == np.float64
    assert kin.joint_names == list(JOINTS)


def test_sensor_looks_along_the_tool_and_sits_beside_it(kin: Kinematics) -> None:
    home = ur5_config()["arm"]["home"]
    S, C = kin.base_T_sensor(home), kin.base_T_tcp(home)
    np.testing.assert_allclose(S[:3, 2], [0, 0, -1], atol=1e-9)  # gripper down -> sensor looks down
    off = S[:3, 3] - C[:3, 3]
    lateral = np.linalg.norm(off - (off @ C[:3, 2]) * C[:3, 2])
    assert 0.06 <= lateral <= 0.075


def test_jacobian_matches_finite_differences(kin: Kinematics, configs: np.ndarray) -> None:
    q = configs[3]
    J = kin.jacobian(q, "tcp")
    eps = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = eps
        Tp, Tm = kin.base_T_tcp(q + dq), kin.base_T_tcp(q - dq)
        np.testing.assert_allclose((Tp[:3, 3] - Tm[:3, 3]) / (2 * eps), J[:3, j], atol=1e-6)
    assert kin.jacobian(configs[:4]).shape == (4, 6, 6)


def test_real_sweep_flange_poses_match_nominal_fk(kin: Kinematics) -> None:
    """The recorded UR5 flange poses agree with nominal DH FK (to about 1.5 mm, shared docs)."""
    path = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"
    frames = json.loads(path.read_text())
    q = np.array([f["joint_angles"] for f in frames])
    P = np.array([f["pose"] for f in frames])
    T = kin.base_T_flange(q)
    assert np.linalg.norm(T[:, :3, 3] - P[:, :3, 3], axis=1).max() < 2e-3
    assert max(_rot_err(a, b) for a, b in zip(T[:, :3, :3], P[:, :3, :3])) < np.deg2rad(1.5)


@pytest.mark.parametrize("bad", [np.zeros(5), np.zeros((2, 7)), np.zeros((2, 3, 6)), "abc"])
def test_wrong_shapes_raise_value_error(kin: Kinematics, bad: object) -> None:
    with pytest.raises(ValueError, match="shape"):
        kin.base_T_sensor(bad)


def test_nan_joints_raise_robot_fault(kin: Kinematics) -> None:
    q = np.zeros(6)
    q[2] = np.nan
    with pytest.raises(RobotFault, match="NaN"):
        kin.base_T_tcp(q)


def test_unknown_link_is_a_clear_error(kin: Kinematics) -> None:
    with pytest.raises(ValueError, match="no_such_link"):
        kin.base_T(np.zeros(6), "no_such_link")
