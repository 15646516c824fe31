"""The simulated UR5's gripper and what it holds: the cup (welded to the flange by the equality ``cup_grasp``
while held) and the liquid spheres in it.

Opening the gripper deactivates the weld and opens the fingers, so the cup is free (it falls or stands on a
surface); closing it grasps the cup again only if it sits where the fingers close on it (within 5 mm and
5 deg of the nominal grasp). Poses are 4x4 transforms in the robot base frame unless named ``world``.
"""

from __future__ import annotations

import math

import mujoco
import numpy as np
from scipy.spatial.transform import Rotation

from place_safe.exceptions import RobotFault
from place_safe.robot.description import ur5_config
from place_safe.sim.arm_model import ArmModel, log_rot


class HeldCup:
    """The gripper, the cup and its liquid of one :class:`~place_safe.sim.arm_model.ArmModel` (a model without
    a cup and weld has a gripper only: :attr:`flange_T_cup` is None)."""

    def __init__(self, arm: ArmModel) -> None:
        self.arm = arm
        m = arm.model
        if arm.cup >= 0 and arm.weld >= 0:
            rp = m.eq_data[arm.weld]
            self.flange_T_cup: np.ndarray | None = np.eye(4)
            self.flange_T_cup[:3, 3] = rp[3:6]
            qw, qx, qy, qz = rp[6:10]
            self.flange_T_cup[:3, :3] = Rotation.from_quat([qx, qy, qz, qw]).as_matrix()
            # liquid positions in the cup frame as laid out by the model (at qpos0, not the current state)
            ref = mujoco.MjData(m)
            mujoco.mj_kinematics(m, ref)
            cTw = np.linalg.inv(arm.world_T_body(arm.cup, ref))
            self.liquid_in_cup = [cTw @ np.append(ref.xpos[b], 1.0) for b in arm.liquid]
            self.weld_relpose0 = m.eq_data[arm.weld, 3:10].copy()
        else:
            self.flange_T_cup = None
            self.liquid_in_cup = []
        cup_cfg = ur5_config()["cup"]
        self.inner_radius = cup_cfg["radius"] - cup_cfg["wall_thickness"]
        self.height = cup_cfg["height"]
        self.is_open = False

    def regrasp(self) -> None:
        """Put the cup (and its liquid) into the closed gripper at the nominal grasp and weld it."""
        arm = self.arm
        if self.flange_T_cup is None:
            raise RobotFault("this model has no cup with a 'cup_grasp' weld to grasp")
        m, d = arm.model, arm.data
        m.eq_data[arm.weld, 3:10] = self.weld_relpose0  # undo a re-grasp at another relative pose
        wTc = arm.world_T_body(arm.flange) @ self.flange_T_cup
        self._set_free_body(arm.cup, wTc)
        for b, pc in zip(arm.liquid, self.liquid_in_cup):
            T = np.eye(4)
            T[:, 3] = wTc @ pc
            self._set_free_body(b, T)
        d.eq_active[arm.weld] = 1
        d.ctrl[arm.finger_act] = arm.finger_range[:, 0]
        fj = [m.actuator_trnid[a, 0] for a in arm.finger_act]
        d.qpos[[m.jnt_qposadr[j] for j in fj]] = arm.finger_range[:, 0]
        self.is_open = False
        mujoco.mj_forward(m, d)

    def _set_free_body(self, body: int, wT: np.ndarray) -> None:
        m, d = self.arm.model, self.arm.data
        j = m.body_jntadr[body]
        if j < 0 or m.jnt_type[j] != mujoco.mjtJoint.mjJNT_FREE:
            raise ValueError(f"body {mujoco.mj_id2name(m, mujoco.mjtObj.mjOBJ_BODY, body)} is not free")
        a, v = m.jnt_qposadr[j], m.jnt_dofadr[j]
        x, y, z, w = Rotation.from_matrix(wT[:3, :3]).as_quat()
        d.qpos[a:a + 7] = [*wT[:3, 3], w, x, y, z]
        d.qvel[v:v + 6] = 0.0

    def holding(self) -> bool:
        """True while the cup weld is active."""
        return self.arm.weld >= 0 and bool(self.arm.data.eq_active[self.arm.weld])

    def set_open(self, open: bool) -> None:
        """Open (release the cup) or close the gripper (re-grasping a cup that sits in the fingers)."""
        arm = self.arm
        d = arm.data
        if open:
            if arm.weld >= 0:
                d.eq_active[arm.weld] = 0
            d.ctrl[arm.finger_act] = arm.finger_range[:, 1]
            self.is_open = True
        else:
            d.ctrl[arm.finger_act] = arm.finger_range[:, 0]
            self.is_open = False
            if self.flange_T_cup is not None and not self.holding():
                # grasp the cup again if it sits where the fingers close on it (within 5 mm / 5 deg)
                fTc = np.linalg.inv(arm.world_T_body(arm.flange)) @ arm.world_T_body(arm.cup)
                E = np.linalg.inv(self.flange_T_cup) @ fTc
                if np.linalg.norm(E[:3, 3]) < 0.005 and np.linalg.norm(log_rot(E[:3, :3])) < math.radians(5):
                    x, y, z, w = Rotation.from_matrix(fTc[:3, :3]).as_quat()
                    arm.model.eq_data[arm.weld, 3:10] = [*fTc[:3, 3], w, x, y, z]
                    d.eq_active[arm.weld] = 1

    def cup_pose(self) -> np.ndarray:
        """base_T_cup of the cup body (held or not)."""
        arm = self.arm
        if arm.cup < 0:
            raise RobotFault("this model has no cup")
        return np.linalg.inv(arm.world_T_base()) @ arm.world_T_body(arm.cup)

    def liquid_spilled(self) -> int:
        """Number of liquid spheres no longer inside the cup (centre outside the cup's inner cylinder)."""
        arm = self.arm
        if arm.cup < 0 or not arm.liquid:
            return 0
        cTw = np.linalg.inv(arm.world_T_body(arm.cup))
        p = (cTw[:3, :3] @ arm.data.xpos[arm.liquid].T).T + cTw[:3, 3]
        inside = (np.hypot(p[:, 0], p[:, 1]) < self.inner_radius) & (p[:, 2] > 0.0) & (p[:, 2] < self.height)
        return int(np.count_nonzero(~inside))


__all__ = ["HeldCup"]
