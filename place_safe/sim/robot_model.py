"""The packaged UR5 model in MuJoCo: element names and loading it bare or as an editable spec for scenes.

The model (``robots/ur5/ur5.xml``) is generated from ``robots/ur5/config.json``; scene builders add their
geoms to :func:`robot_spec`'s world body and compile it; :class:`place_safe.sim.robot.SimRobot` drives it.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from place_safe.robot.description import ur5_mjcf_path

ARM_JOINTS = ("shoulder_pan_joint", "shoulder_lift_joint", "elbow_joint", "wrist_1_joint",
              "wrist_2_joint", "wrist_3_joint")
FINGERS = ("finger_left", "finger_right")


def load_robot_model() -> tuple[mujoco.MjModel, mujoco.MjData]:
    """The bare packaged robot (UR5 + gripper + TMF8820 site + held cup with liquid), no scene."""
    model = mujoco.MjModel.from_xml_path(str(ur5_mjcf_path()))
    return model, mujoco.MjData(model)


def robot_spec(base_pos: Any = (0.0, 0.0, 0.0), base_quat: Any = (1.0, 0.0, 0.0, 0.0)) -> mujoco.MjSpec:
    """An editable MjSpec of the packaged robot with its base at ``base_pos`` (m) / ``base_quat`` (w, x, y,
    z) in the world. Scene builders add their geoms to ``spec.worldbody`` and call ``spec.compile()``;
    :class:`SimRobot` re-places the cup in the gripper wherever the base ends up."""
    pos, quat = np.asarray(base_pos, dtype=float), np.asarray(base_quat, dtype=float)
    if pos.shape != (3,) or quat.shape != (4,) or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
        raise ValueError(f"base_pos must be 3 and base_quat 4 finite numbers; got {base_pos!r}, {base_quat!r}")
    if not np.linalg.norm(quat) > 0:
        raise ValueError("base_quat must be a non-zero quaternion (w, x, y, z)")
    spec = mujoco.MjSpec.from_file(str(ur5_mjcf_path()))
    base = spec.body("base")
    base.pos = pos
    base.quat = quat / np.linalg.norm(quat)
    return spec


__all__ = ["ARM_JOINTS", "FINGERS", "load_robot_model", "robot_spec"]
