"""Generate the UR5 + gripper + TMF8820 + cup models (MJCF and URDF) from ``config.json``.

One source of truth: ``robots/ur5/config.json``. Both ``ur5.xml`` (MuJoCo) and ``ur5.urdf``
(pytorch-kinematics, ROS tools) are written from it, so their kinematics agree by construction.

Conventions
-----------
* Standard (distal) Denavit-Hartenberg: ``T_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i)``, ``theta_i = q_i``.
  The body (MJCF) / link (URDF) of joint ``i`` has the frame ``i-1`` rotated by ``q_i``; its child sits at
  ``(a_i, 0, d_i)`` rotated by ``Rx(alpha_i)``. The base frame is DH frame 0 (the UR controller's base
  frame), the ``flange`` frame is DH frame 6 (z out of the tool flange).
* Fixed frames hung from the flange: ``tcp`` (between the fingertips), ``tof_sensor`` (+z optical axis,
  x/y as in the TMF8820 zone table) and ``cup`` (the held cup's frame: origin at the centre of its
  bottom face, +z up through the opening, i.e. against the tool direction).
* MJCF geom groups: 0 environment (scene builders), 1 held cup and liquid, 2 robot (all three drawn
  by default viewers); the simulated sensor sees group 0 only. Contact bits (config ``contact``): robot geoms touch the environment but
  not each other or the cup; the cup is held by the ``cup_grasp`` weld (flange -> cup), not by friction.

Run ``python -m place_safe.robot.model_generator`` to rewrite
both files; ``--check`` only reports whether the committed files are up to date (exit status 1 if not).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import warnings
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from scipy.spatial.transform import Rotation

from place_safe.robot.description import ur5_config_path, ur5_mjcf_path, ur5_urdf_path

CONFIG_PATH = ur5_config_path()
MJCF_PATH = ur5_mjcf_path()
URDF_PATH = ur5_urdf_path()

ROBOT_GROUP = 2
HELD_GROUP = 1


def _f(x: float) -> str:
    """Format one number reproducibly (9 significant digits, no negative zero)."""
    v = float(x)
    if abs(v) < 1e-12:
        v = 0.0
    return f"{v:.9g}"


def _v(xs: Sequence[float]) -> str:
    return " ".join(_f(x) for x in xs)


def load_config(path: Path = CONFIG_PATH) -> dict[str, Any]:
    with open(path, encoding="utf-8") as fh:
        return json.load(fh)


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------


def transform(xyz: Sequence[float], rpy: Sequence[float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """4x4 homogeneous transform from a translation and fixed-axis roll-pitch-yaw (URDF convention)."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", rpy).as_matrix()
    T[:3, 3] = xyz
    return T


def dh_transform(theta: float, d: float, a: float, alpha: float) -> np.ndarray:
    """Standard DH link transform ``Rz(theta) Tz(d) Tx(a) Rx(alpha)``."""
    ct, st, ca, sa = math.cos(theta), math.sin(theta), math.cos(alpha), math.sin(alpha)
    return np.array(
        [
            [ct, -st * ca, st * sa, a * ct],
            [st, ct * ca, -ct * sa, a * st],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )


def dh_fk(cfg: dict[str, Any], q: Sequence[float]) -> np.ndarray:
    """base_T_flange by the plain DH product (reference implementation for the tests)."""
    arm = cfg["arm"]
    T = np.eye(4)
    for qi, d, a, al in zip(q, arm["dh_d"], arm["dh_a"], arm["dh_alpha"]):
        T = T @ dh_transform(float(qi), d, a, al)
    return T


def flange_T_tcp(cfg: dict[str, Any]) -> np.ndarray:
    return transform(cfg["gripper"]["tcp_xyz"])


def flange_T_sensor(cfg: dict[str, Any]) -> np.ndarray:
    s = cfg["sensor"]
    return transform(s["flange_T_sensor_xyz"], s["flange_T_sensor_rpy"])


def flange_T_cup(cfg: dict[str, Any]) -> np.ndarray:
    c = cfg["cup"]
    return transform(c["flange_T_cup_xyz"], c["flange_T_cup_rpy"])


def _quat_wxyz(R: np.ndarray) -> list[float]:
    x, y, z, w = Rotation.from_matrix(R).as_quat()
    if w < 0:
        x, y, z, w = -x, -y, -z, -w
    return [w, x, y, z]


def _rpy(R: np.ndarray) -> list[float]:
    with warnings.catch_warnings():  # gimbal lock (pitch +-90 deg) still gives a valid triple
        warnings.simplefilter("ignore", UserWarning)
        return list(Rotation.from_matrix(R).as_euler("xyz"))


def _z_to(direction: np.ndarray) -> np.ndarray:
    """A rotation taking +z onto ``direction`` (for URDF cylinders)."""
    d = np.asarray(direction, float)
    d = d / np.linalg.norm(d)
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    s, c = np.linalg.norm(v), float(z @ d)
    if s < 1e-12:
        return np.eye(3) if c > 0 else Rotation.from_euler("x", math.pi).as_matrix()
    return Rotation.from_rotvec(v / s * math.atan2(s, c)).as_matrix()


# ---------------------------------------------------------------------------------------------
# Geometry and inertia of the parts (shared by both writers)
# ---------------------------------------------------------------------------------------------


def _cylinder_inertia(m: float, r: float, length: float) -> np.ndarray:
    """Principal inertia of a solid cylinder about its centre, axis = local z."""
    ixx = m * (3 * r * r + length * length) / 12.0
    return np.array([ixx, ixx, 0.5 * m * r * r])


def _box_inertia(m: float, half: Sequence[float]) -> np.ndarray:
    x, y, z = (2 * h for h in half)
    return m / 12.0 * np.array([y * y + z * z, x * x + z * z, x * x + y * y])


def arm_links(cfg: dict[str, Any]) -> list[dict[str, Any]]:
    """Per arm link: segment end (child origin in the link frame), radius, mass, COM, inertia (3x3)."""
    arm = cfg["arm"]
    out = []
    for i in range(6):
        end = np.array([arm["dh_a"][i], 0.0, arm["dh_d"][i]])
        length = float(np.linalg.norm(end))
        r = arm["link_radius"][i]
        m = arm["masses"][i]
        R = _z_to(end) if length > 0 else np.eye(3)
        I_local = np.diag(_cylinder_inertia(m, r, length))
        out.append(
            {
                "name": arm["link_names"][i],
                "joint": arm["joint_names"][i],
                "end": end,
                "length": length,
                "radius": r,
                "mass": m,
                "com": end / 2.0,
                "inertia": R @ I_local @ R.T,
                "axis_R": R,
                "child": (end, Rotation.from_euler("x", arm["dh_alpha"][i]).as_matrix()),
            }
        )
    return out


def cup_walls(cfg: dict[str, Any]) -> list[tuple[np.ndarray, float, list[float]]]:
    """Wall boxes of the cup in the cup frame: (centre, yaw, half sizes)."""
    c = cfg["cup"]
    n, R, t, h = c["wall_segments"], c["radius"], c["wall_thickness"], c["height"]
    half_w = (R * math.tan(math.pi / n)) * 1.05  # a little overlap so the wall has no gaps
    walls = []
    for k in range(n):
        yaw = 2 * math.pi * k / n
        rc = R - t / 2
        centre = np.array([rc * math.cos(yaw), rc * math.sin(yaw), h / 2])
        walls.append((centre, yaw, [t / 2, half_w, h / 2]))
    return walls


def liquid_positions(cfg: dict[str, Any]) -> list[np.ndarray]:
    """Initial positions of the liquid spheres in the cup frame (layers of rings above the bottom)."""
    c = cfg["cup"]
    r, R, t = c["liquid_radius"], c["radius"], c["wall_thickness"]
    per_ring = 4
    ring = R - t - r - 0.003
    pos = []
    for k in range(c["liquid_count"]):
        layer, j = divmod(k, per_ring)
        ang = 2 * math.pi * j / per_ring + layer * math.pi / per_ring
        z = t + r + 0.001 + layer * (2 * r + 0.002)
        pos.append(np.array([ring * math.cos(ang), ring * math.sin(ang), z]))
    return pos


# ---------------------------------------------------------------------------------------------
# MJCF
# ---------------------------------------------------------------------------------------------


def _full_inertia(I: np.ndarray) -> str:
    return _v([I[0, 0], I[1, 1], I[2, 2], I[0, 1], I[0, 2], I[1, 2]])


def build_mjcf(cfg: dict[str, Any]) -> str:
    arm, grip, sens, cup, con, sim = (cfg[k] for k in ("arm", "gripper", "sensor", "cup", "contact", "sim"))
    robot_geom = (
        f'group="{ROBOT_GROUP}" contype="{con["robot_contype"]}" conaffinity="{con["robot_conaffinity"]}"'
    )
    inert_geom = f'group="{ROBOT_GROUP}" contype="0" conaffinity="0"'
    lines: list[str] = []
    w = lines.append
    w('<mujoco model="ur5_gripper_tmf8820">')
    w("  <!-- GENERATED by place_safe/robot/model_generator.py from robots/ur5/config.json; do not edit by hand. -->")
    w('  <compiler angle="radian" autolimits="true"/>')
    w(f'  <option timestep="{_f(sim["timestep"])}" integrator="{sim["integrator"]}"/>')
    w("  <visual><global offwidth=\"640\" offheight=\"480\"/></visual>")
    w("  <asset>")
    w('    <material name="ur5_grey" rgba="0.7 0.72 0.75 1"/>')
    w('    <material name="ur5_blue" rgba="0.25 0.45 0.75 1"/>')
    w('    <material name="ur5_dark" rgba="0.15 0.15 0.17 1"/>')
    w('    <material name="sensor_green" rgba="0.1 0.6 0.2 1"/>')
    w('    <material name="cup_white" rgba="0.93 0.93 0.9 1"/>')
    w('    <material name="liquid_blue" rgba="0.2 0.4 0.95 1"/>')
    w("  </asset>")
    w("  <worldbody>")
    bh, br = arm["base_height"], arm["base_radius"]
    w('    <body name="base" pos="0 0 0">')
    w(f'      <inertial pos="0 0 {_f(bh / 2)}" mass="{_f(arm["base_mass"])}" '
      f'diaginertia="{_v(_cylinder_inertia(arm["base_mass"], br, bh))}"/>')
    w(f'      <geom name="base_geom" type="cylinder" size="{_f(br)} {_f(bh / 2)}" pos="0 0 {_f(bh / 2)}" '
      f'material="ur5_dark" {inert_geom}/>')
    w('      <site name="base" size="0.005"/>')
    links = arm_links(cfg)
    indent = "      "
    parent_pos, parent_R = np.zeros(3), np.eye(3)
    lo_hi = arm["joint_limits"]
    for i, L in enumerate(links):
        w(f'{indent}<body name="{L["name"]}" pos="{_v(parent_pos)}" quat="{_v(_quat_wxyz(parent_R))}" '
          f'gravcomp="1">')
        ind2 = indent + "  "
        w(f'{ind2}<inertial pos="{_v(L["com"])}" mass="{_f(L["mass"])}" fullinertia="{_full_inertia(L["inertia"])}"/>')
        w(f'{ind2}<joint name="{L["joint"]}" type="hinge" axis="0 0 1" range="{_v(lo_hi[i])}" '
          f'armature="{_f(arm["armature"][i])}" damping="{_f(arm["damping"][i])}"/>')
        geom_attr = inert_geom if i == 0 else robot_geom  # the shoulder turns in place: no collisions
        mat = "ur5_blue" if i % 2 == 0 else "ur5_grey"
        # joint housing (along the joint axis) and the link segment to the next joint
        w(f'{ind2}<geom name="{L["name"]}_housing" type="cylinder" size="{_f(L["radius"])} {_f(L["radius"] * 0.9)}" '
          f'material="ur5_blue" {inert_geom}/>')
        w(f'{ind2}<geom name="{L["name"]}_geom" type="capsule" fromto="0 0 0 {_v(L["end"])}" '
          f'size="{_f(L["radius"] * 0.85)}" material="{mat}" {geom_attr}/>')
        parent_pos, parent_R = L["child"]
        indent = ind2
    # flange (DH frame 6) and everything fixed to it
    w(f'{indent}<body name="flange" pos="{_v(parent_pos)}" quat="{_v(_quat_wxyz(parent_R))}" gravcomp="1">')
    f2 = indent + "  "
    gl, gr = grip["body_length"], grip["body_radius"]
    gm = grip["mass"] + sens["mass"]
    w(f'{f2}<inertial pos="0 0 {_f(gl / 2)}" mass="{_f(gm)}" diaginertia="{_v(_cylinder_inertia(gm, gr, gl))}"/>')
    w(f'{f2}<site name="flange" size="0.004" rgba="1 0 0 1"/>')
    w(f'{f2}<geom name="gripper_body" type="cylinder" size="{_f(gr)} {_f(gl / 2)}" pos="0 0 {_f(gl / 2)}" '
      f'material="ur5_dark" {robot_geom}/>')
    w(f'{f2}<geom name="gripper_palm" type="box" size="{_f(gr)} {_f(grip["finger_closed_y"] + 0.03)} 0.006" '
      f'pos="0 0 {_f(gl - 0.006)}" material="ur5_dark" {robot_geom}/>')
    # sensor bracket hanging from the gripper body down to the sensor board
    st = flange_T_sensor(cfg)
    bx, by, bz = sens["bracket_half_size"]
    sp = st[:3, 3]
    w(f'{f2}<geom name="tof_bracket" type="box" size="{_v(sens["bracket_half_size"])}" '
      f'pos="{_f(sp[0])} {_f(sp[1])} {_f(sp[2] - sens["board_half_size"][2] - bz)}" material="ur5_grey" {robot_geom}/>')
    w(f'{f2}<geom name="tof_arm" type="box" size="{_f((sp[0] - gr) / 2 + 0.005)} {_f(by)} 0.005" '
      f'pos="{_f((sp[0] + gr) / 2)} {_f(sp[1])} {_f(sp[2] - 2 * bz - 0.005)}" material="ur5_grey" {robot_geom}/>')
    w(f'{f2}<geom name="tof_board" type="box" size="{_v(sens["board_half_size"])}" '
      f'pos="{_v(sp - st[:3, :3] @ np.array([0, 0, sens["board_half_size"][2]]))}" '
      f'quat="{_v(_quat_wxyz(st[:3, :3]))}" material="sensor_green" {inert_geom}/>')
    w(f'{f2}<site name="tof_sensor" pos="{_v(sp)}" quat="{_v(_quat_wxyz(st[:3, :3]))}" size="0.003" rgba="0 1 0 1"/>')
    w(f'{f2}<site name="tcp" pos="{_v(grip["tcp_xyz"])}" size="0.004" rgba="0 0 1 1"/>')
    fh = grip["finger_half_size"]
    fI = _box_inertia(grip["finger_mass"], fh)
    for name, sign in (("finger_left", 1.0), ("finger_right", -1.0)):
        w(f'{f2}<body name="{name}" pos="0 {_f(sign * grip["finger_closed_y"])} {_f(grip["finger_center_z"])}" gravcomp="1">')
        w(f'{f2}  <inertial pos="0 0 0" mass="{_f(grip["finger_mass"])}" diaginertia="{_v(fI)}"/>')
        w(f'{f2}  <joint name="{name}" type="slide" axis="0 {_f(sign)} 0" range="{_v(grip["finger_range"])}" '
          f'armature="0.01" damping="5"/>')
        w(f'{f2}  <geom name="{name}_geom" type="box" size="{_v(fh)}" material="ur5_grey" {robot_geom}/>')
        w(f"{f2}</body>")
    w(f"{indent}</body>")
    for i in range(len(links) - 1, -1, -1):
        w("      " + "  " * i + "</body>")
    w("    </body>")
    # the held cup and its liquid, placed at the home pose (SimRobot re-places them at the grasp)
    home = arm["home"]
    base_T_cup = dh_fk(cfg, home) @ flange_T_cup(cfg)
    cup_geom = f'group="{HELD_GROUP}" contype="{con["cup_contype"]}" conaffinity="{con["cup_conaffinity"]}"'
    R, t, h = cup["radius"], cup["wall_thickness"], cup["height"]
    walls = cup_walls(cfg)
    # mass split: bottom disc and walls share the cup mass by area
    area_bottom = math.pi * R * R
    area_walls = 2 * math.pi * R * h
    m_bottom = cup["mass"] * area_bottom / (area_bottom + area_walls)
    m_wall = (cup["mass"] - m_bottom) / len(walls)
    w(f'    <body name="cup" pos="{_v(base_T_cup[:3, 3])}" quat="{_v(_quat_wxyz(base_T_cup[:3, :3]))}">')
    w('      <freejoint name="cup_joint"/>')
    w(f'      <geom name="cup_bottom" type="cylinder" size="{_f(R)} {_f(t / 2)}" pos="0 0 {_f(t / 2)}" '
      f'mass="{_f(m_bottom)}" material="cup_white" {cup_geom}/>')
    for k, (centre, yaw, half) in enumerate(walls):
        q = _quat_wxyz(Rotation.from_euler("z", yaw).as_matrix())
        w(f'      <geom name="cup_wall_{k}" type="box" size="{_v(half)}" pos="{_v(centre)}" quat="{_v(q)}" '
          f'mass="{_f(m_wall)}" material="cup_white" {cup_geom}/>')
    w('      <site name="cup_bottom" size="0.004" rgba="1 0.5 0 1"/>')
    w(f'      <site name="cup_top" pos="0 0 {_f(h)}" size="0.004" rgba="1 0.5 0 1"/>')
    w("    </body>")
    liq_geom = (f'group="{HELD_GROUP}" contype="{con["liquid_contype"]}" '
                f'conaffinity="{con["liquid_conaffinity"]}"')
    for k, p in enumerate(liquid_positions(cfg)):
        pw = base_T_cup[:3, :3] @ p + base_T_cup[:3, 3]
        w(f'    <body name="liquid_{k}" pos="{_v(pw)}">')
        w(f'      <freejoint name="liquid_{k}_joint"/>')
        w(f'      <geom name="liquid_{k}_geom" type="sphere" size="{_f(cup["liquid_radius"])}" '
          f'mass="{_f(cup["liquid_mass"])}" friction="0.2 0.005 0.0001" material="liquid_blue" {liq_geom}/>')
        w("    </body>")
    w("  </worldbody>")
    fc = flange_T_cup(cfg)
    w("  <equality>")
    w(f'    <weld name="cup_grasp" body1="flange" body2="cup" relpose="{_v(fc[:3, 3])} {_v(_quat_wxyz(fc[:3, :3]))}" '
      f'solref="0.004 1" active="true"/>')
    w("  </equality>")
    w("  <contact>")
    w('    <exclude body1="finger_left" body2="cup"/>')
    w('    <exclude body1="finger_right" body2="cup"/>')
    w("  </contact>")
    w("  <actuator>")
    for i, L in enumerate(links):
        tq = arm["max_joint_torque"][i]
        w(f'    <position name="{L["joint"]}" joint="{L["joint"]}" kp="{_f(arm["servo_kp"][i])}" '
          f'kv="{_f(arm["servo_kv"][i])}" ctrlrange="{_v(lo_hi[i])}" forcerange="{_f(-tq)} {_f(tq)}"/>')
    for name in ("finger_left", "finger_right"):
        w(f'    <position name="{name}" joint="{name}" kp="{_f(grip["finger_kp"])}" kv="{_f(grip["finger_kv"])}" '
          f'ctrlrange="{_v(grip["finger_range"])}" forcerange="-40 40"/>')
    w("  </actuator>")
    w("</mujoco>")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------------------------
# URDF
# ---------------------------------------------------------------------------------------------


def _urdf_inertial(mass: float, com: Sequence[float], I: np.ndarray) -> list[str]:
    return [
        "    <inertial>",
        f'      <origin xyz="{_v(com)}" rpy="0 0 0"/>',
        f'      <mass value="{_f(mass)}"/>',
        f'      <inertia ixx="{_f(I[0, 0])}" ixy="{_f(I[0, 1])}" ixz="{_f(I[0, 2])}" '
        f'iyy="{_f(I[1, 1])}" iyz="{_f(I[1, 2])}" izz="{_f(I[2, 2])}"/>',
        "    </inertial>",
    ]


def _urdf_shape(kind: str, origin: np.ndarray, shape: str) -> list[str]:
    return [
        f"    <{kind}>",
        f'      <origin xyz="{_v(origin[:3, 3])}" rpy="{_v(_rpy(origin[:3, :3]))}"/>',
        f"      <geometry>{shape}</geometry>",
        f"    </{kind}>",
    ]


def _urdf_fixed(name: str, parent: str, child: str, T: np.ndarray) -> list[str]:
    return [
        f'  <joint name="{name}" type="fixed">',
        f'    <parent link="{parent}"/>',
        f'    <child link="{child}"/>',
        f'    <origin xyz="{_v(T[:3, 3])}" rpy="{_v(_rpy(T[:3, :3]))}"/>',
        "  </joint>",
    ]


def build_urdf(cfg: dict[str, Any]) -> str:
    arm, grip, sens = cfg["arm"], cfg["gripper"], cfg["sensor"]
    out: list[str] = ['<?xml version="1.0"?>', '<robot name="ur5_gripper_tmf8820">',
                      "  <!-- GENERATED by place_safe/robot/model_generator.py from robots/ur5/config.json; do not edit by hand. -->"]
    bh, br = arm["base_height"], arm["base_radius"]
    out.append('  <link name="base_link">')
    out += _urdf_inertial(arm["base_mass"], [0, 0, bh / 2], np.diag(_cylinder_inertia(arm["base_mass"], br, bh)))
    cyl = f'<cylinder radius="{_f(br)}" length="{_f(bh)}"/>'
    out += _urdf_shape("visual", transform([0, 0, bh / 2]), cyl)
    out.append("  </link>")
    parent, parent_T = "base_link", np.eye(4)
    for i, L in enumerate(arm_links(cfg)):
        out.append(f'  <link name="{L["name"]}">')
        out += _urdf_inertial(L["mass"], L["com"], L["inertia"])
        seg = np.eye(4)
        seg[:3, :3] = L["axis_R"]
        seg[:3, 3] = L["com"]
        shape = f'<cylinder radius="{_f(L["radius"] * 0.85)}" length="{_f(L["length"])}"/>'
        out += _urdf_shape("visual", seg, shape)
        out += _urdf_shape("collision", seg, shape)
        out.append("  </link>")
        lo, hi = arm["joint_limits"][i]
        out += [
            f'  <joint name="{L["joint"]}" type="revolute">',
            f'    <parent link="{parent}"/>',
            f'    <child link="{L["name"]}"/>',
            f'    <origin xyz="{_v(parent_T[:3, 3])}" rpy="{_v(_rpy(parent_T[:3, :3]))}"/>',
            '    <axis xyz="0 0 1"/>',
            f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" effort="{_f(arm["max_joint_torque"][i])}" '
            f'velocity="{_f(arm["max_joint_velocity"][i])}"/>',
            "  </joint>",
        ]
        parent = L["name"]
        parent_T = np.eye(4)
        parent_T[:3, :3] = L["child"][1]
        parent_T[:3, 3] = L["child"][0]
    # flange = DH frame 6
    gl, gr = grip["body_length"], grip["body_radius"]
    gm = grip["mass"] + sens["mass"]
    out.append('  <link name="flange">')
    out += _urdf_inertial(gm, [0, 0, gl / 2], np.diag(_cylinder_inertia(gm, gr, gl)))
    cyl = f'<cylinder radius="{_f(gr)}" length="{_f(gl)}"/>'
    out += _urdf_shape("visual", transform([0, 0, gl / 2]), cyl)
    out += _urdf_shape("collision", transform([0, 0, gl / 2]), cyl)
    out.append("  </link>")
    out += _urdf_fixed("flange_joint", parent, "flange", parent_T)
    for name in ("tcp", "tof_sensor", "cup"):
        out.append(f'  <link name="{name}"/>')
    out += _urdf_fixed("tcp_joint", "flange", "tcp", flange_T_tcp(cfg))
    out += _urdf_fixed("tof_sensor_joint", "flange", "tof_sensor", flange_T_sensor(cfg))
    out += _urdf_fixed("cup_joint", "flange", "cup", flange_T_cup(cfg))
    fh = grip["finger_half_size"]
    for name, sign in (("finger_left", 1.0), ("finger_right", -1.0)):
        out.append(f'  <link name="{name}_link">')
        out += _urdf_inertial(grip["finger_mass"], [0, 0, 0], np.diag(_box_inertia(grip["finger_mass"], fh)))
        box = f'<box size="{_v([2 * h for h in fh])}"/>'
        out += _urdf_shape("visual", np.eye(4), box)
        out += _urdf_shape("collision", np.eye(4), box)
        out.append("  </link>")
        lo, hi = grip["finger_range"]
        out += [
            f'  <joint name="{name}" type="prismatic">',
            '    <parent link="flange"/>',
            f'    <child link="{name}_link"/>',
            f'    <origin xyz="0 {_f(sign * grip["finger_closed_y"])} {_f(grip["finger_center_z"])}" rpy="0 0 0"/>',
            f'    <axis xyz="0 {_f(sign)} 0"/>',
            f'    <limit lower="{_f(lo)}" upper="{_f(hi)}" effort="40" velocity="0.1"/>',
            "  </joint>",
        ]
    out.append("</robot>")
    return "\n".join(out) + "\n"


def generate(config_path: Path = CONFIG_PATH) -> dict[Path, str]:
    """Return {output path: text} for both model files (does not write)."""
    cfg = load_config(config_path)
    return {MJCF_PATH: build_mjcf(cfg), URDF_PATH: build_urdf(cfg)}


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--check", action="store_true", help="only check the committed files are up to date")
    args = ap.parse_args(argv)
    stale = []
    for path, text in generate().items():
        current = path.read_text(encoding="utf-8") if path.exists() else None
        if current != text:
            stale.append(path)
            if not args.check:
                path.write_text(text, encoding="utf-8")
    if args.check:
        for p in stale:
            print(f"out of date: {p} (run python -m place_safe.robot.model_generator)", file=sys.stderr)
        return 1 if stale else 0
    for p in stale:
        print(f"wrote {p}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
