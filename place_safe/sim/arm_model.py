"""The simulated UR5's elements in a MuJoCo model and its frames: the one place that knows the names of
``robots/ur5/ur5.xml`` (joints, actuators, sites, bodies) and turns MuJoCo's world poses into base-frame ones.

Conventions: poses are 4x4 homogeneous transforms, ``a_T_b`` maps b coordinates to a; the robot base frame is
the frame of the ``base`` body (a scene builder may move the base in the world). TCP = site ``tcp``, sensor =
site ``tof_sensor``, flange = site ``flange``. Geom classes: 0 environment, 1 robot arm, 2 gripper, 3 cup,
4 liquid. Rotation vectors are axis * angle in rad.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np

from place_safe.sim.robot_model import ARM_JOINTS, FINGERS

# geom classes (:attr:`ArmModel.geom_class`)
ENVIRONMENT, ARM, GRIPPER, CUP, LIQUID = range(5)


def log_rot(R: np.ndarray) -> np.ndarray:
    """Rotation vector (axis * angle, rad) of a rotation matrix (MuJoCo's C helpers: fast per step)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    v = np.empty(3)
    mujoco.mju_quat2Vel(v, q, 1.0)
    return v


def exp_rot(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of a rotation vector (rad)."""
    angle = math.sqrt(float(w[0] * w[0] + w[1] * w[1] + w[2] * w[2]))
    if angle < 1e-15:
        return np.eye(3)
    q = np.empty(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(w, dtype=np.float64) / angle, angle)
    R = np.empty(9)
    mujoco.mju_quat2Mat(R, q)
    return R.reshape(3, 3)


def _pose(xmat: np.ndarray, xpos: np.ndarray) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = xmat.reshape(3, 3)
    T[:3, 3] = xpos
    return T


class ArmModel:
    """Where the UR5 (named as in ``robots/ur5/ur5.xml``, with an optional name ``prefix``) sits in ``model``:
    joint and actuator addresses, sites, bodies and the class of every geom; its frames on ``data`` (or on
    :attr:`scratch`, a second MjData for planning and the commanded configuration). A missing element or arm
    actuators that are not position servos raise ValueError naming it."""

    def __init__(self, model: mujoco.MjModel, data: mujoco.MjData, prefix: str = "") -> None:
        self.model, self.data = model, data
        m, p = model, prefix

        def _id(kind: mujoco.mjtObj, name: str) -> int:
            i = mujoco.mj_name2id(m, kind, p + name)
            if i < 0:
                raise ValueError(f"model has no {kind.name.lower()[6:]} named {p + name!r}; "
                                 "expected the robot of robots/ur5/ur5.xml")
            return i

        jids = [_id(mujoco.mjtObj.mjOBJ_JOINT, j) for j in ARM_JOINTS]
        self.qadr = np.array([m.jnt_qposadr[j] for j in jids])
        self.vadr = np.array([m.jnt_dofadr[j] for j in jids])
        self.act = np.array([_id(mujoco.mjtObj.mjOBJ_ACTUATOR, j) for j in ARM_JOINTS])
        # position actuators: gain kp, bias (0, -kp, -kv)
        kp = m.actuator_gainprm[self.act, 0]
        if np.any(kp <= 0) or np.any(m.actuator_biasprm[self.act, 1] >= 0):
            raise ValueError("arm actuators must be MuJoCo position servos (kp > 0)")
        self.kv_over_kp = -m.actuator_biasprm[self.act, 2] / kp
        self.finger_act = np.array([_id(mujoco.mjtObj.mjOBJ_ACTUATOR, f) for f in FINGERS])
        self.finger_range = m.actuator_ctrlrange[self.finger_act].copy()
        self.tcp = _id(mujoco.mjtObj.mjOBJ_SITE, "tcp")
        self.sensor = _id(mujoco.mjtObj.mjOBJ_SITE, "tof_sensor")
        self.flange_site = _id(mujoco.mjtObj.mjOBJ_SITE, "flange")
        self.base = _id(mujoco.mjtObj.mjOBJ_BODY, "base")
        self.flange = _id(mujoco.mjtObj.mjOBJ_BODY, "flange")
        self.grip_bodies = {self.flange, _id(mujoco.mjtObj.mjOBJ_BODY, "finger_left"),
                            _id(mujoco.mjtObj.mjOBJ_BODY, "finger_right")}
        robot_bodies = np.flatnonzero(m.body_rootid == self.base)
        self.cup = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, p + "cup")  # -1: no cup
        self.weld = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, p + "cup_grasp")  # -1: no weld
        self.liquid = [b for b in range(m.nbody) if mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b)
                       and mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, b).startswith(p + "liquid_")]
        body_class = np.zeros(m.nbody, dtype=np.int8)
        body_class[robot_bodies] = ARM
        body_class[list(self.grip_bodies)] = GRIPPER
        if self.cup >= 0:
            body_class[self.cup] = CUP
        body_class[self.liquid] = LIQUID
        self.geom_class = body_class[m.geom_bodyid]
        self.scratch = mujoco.MjData(m)

    # frames ------------------------------------------------------------------------------------
    def world_T_body(self, b: int, data: mujoco.MjData | None = None) -> np.ndarray:
        d = self.data if data is None else data
        return _pose(d.xmat[b], d.xpos[b])

    def world_T_site(self, s: int, data: mujoco.MjData | None = None) -> np.ndarray:
        d = self.data if data is None else data
        return _pose(d.site_xmat[s], d.site_xpos[s])

    def world_T_base(self) -> np.ndarray:
        return self.world_T_body(self.base)

    def base_T_site(self, s: int, data: mujoco.MjData | None = None) -> np.ndarray:
        wb = self.world_T_body(self.base, data)
        ws = self.world_T_site(s, data)
        T = np.eye(4)
        T[:3, :3] = wb[:3, :3].T @ ws[:3, :3]
        T[:3, 3] = wb[:3, :3].T @ (ws[:3, 3] - wb[:3, 3])
        return T

    def jac_base(self, data: mujoco.MjData) -> np.ndarray:
        """6x6 TCP Jacobian (linear; angular) in the base frame for the arm dofs."""
        jp = np.zeros((3, self.model.nv))
        jr = np.zeros((3, self.model.nv))
        mujoco.mj_jacSite(self.model, data, jp, jr, self.tcp)
        Rb = data.xmat[self.base].reshape(3, 3)
        return np.vstack([Rb.T @ jp[:, self.vadr], Rb.T @ jr[:, self.vadr]])

    def at_joints(self, q: np.ndarray) -> mujoco.MjData:
        """:attr:`scratch` with the arm at ``q`` (the rest of its state as it was) and its kinematics done."""
        sd = self.scratch
        sd.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, sd)
        mujoco.mj_comPos(self.model, sd)
        return sd


__all__ = ["ArmModel", "log_rot", "exp_rot", "ENVIRONMENT", "ARM", "GRIPPER", "CUP", "LIQUID"]
