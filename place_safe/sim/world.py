"""A simulated UR5 work cell for task scripts: scenario scene + SimRobot + SimToF, optionally with a sensor
mount that differs from the robot file's (the error ``calibrate-mount`` has to find).

Concept: :func:`sim_world` builds what ``place-safe capture --sim`` and ``place-safe place --sim`` drive,
so both run the same code as on the real arm (the task only sees a Robot and a FrameSource).
The scenario's ``sensor.mount_offset`` (m, flange frame) moves the site and the robot's configured sensor frame
alike: a sensor mounted elsewhere on purpose (near the jaws), known to the robot.
``mount_error`` moves the MuJoCo ``tof_sensor`` site -- where the simulated TMF8820 really looks from
-- by ``E`` in the sensor frame (true flange_T_sensor = nominal @ E); the robot's configured tool frames
stay nominal, as a user's would before calibration.

Conventions: SI units; ``mount_error`` is ``(dx, dy, dz, rx, ry, rz)`` in m and a rotation vector in rad.
The table plane is returned in the robot base frame as ``(n, d)`` with ``n . x = d``, n up.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation


@dataclass
class SimWorld:
    scene: Any
    robot: Any  # SimRobot
    tof: Any  # SimToF
    name: str
    mount_error: np.ndarray  # 4x4, nominal_T_true sensor frame
    scenario: Any = None  # the Scenario it was built from

    def table_plane_base(self) -> tuple[np.ndarray, float]:
        """The table top in the robot base frame (what a measured table height gives)."""
        n_w, p_w = self.scene.table_plane_world(self.robot.data)
        wb = self.robot.world_T_base()
        n = wb[:3, :3].T @ n_w
        p = (np.linalg.inv(wb) @ np.append(p_w, 1.0))[:3]
        return n, float(n @ p)

    def user_calibration(self) -> Any:
        """The scenario's calibration for its simulated sensor, as a placement there uses it: normally the packaged
        simulated *user* calibration of that unit (a level sweep fitted with ``place-safe calibrate``; one made on another
        unit misreads this one), never the simulator's own parameters unless the scenario asks for the oracle; None for
        a scenario run uncalibrated (:meth:`~place_safe.sim.scenario.Scenario.resolve_calibration`)."""
        return None if self.scenario is None else self.scenario.resolve_calibration()[0]

    def true_flange_T_sensor(self) -> np.ndarray:
        return self.robot.tool.flange_T_sensor @ self.mount_error


def error_transform(mount_error: Any) -> np.ndarray:
    try:
        e = np.asarray(mount_error if mount_error is not None else np.zeros(6), dtype=float)
    except (TypeError, ValueError, OverflowError):
        e = np.full(1, np.nan)
    if e.shape != (6,) or not np.all(np.isfinite(e)) or np.abs(e[:3]).max() > 1.0 or np.abs(e[3:]).max() > np.pi:
        raise ValueError(f"mount_error must be 6 finite numbers (m, m, m, rad, rad, rad), translations within 1 m "
                         f"and rotations within pi rad; got {str(mount_error)[:80]}")
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(e[3:]).as_matrix()
    E[:3, 3] = e[:3]
    return E


def sim_world(scenario: Any = "level_table", *, seed: int = 0, mount_error: Any = None,
              hold_cup: bool = True, attach: bool = True) -> SimWorld:
    """Build the scenario's scene with the robot (at the scenario's start pose), the scenario's simulated
    sensor (nominal or mismatched) attached to it unless ``attach`` is False, and the mount error.

    ``scenario``: a packaged scenario name, a file (TOML or JSON), or a :class:`~place_safe.sim.scenario.Scenario`.
    """
    import mujoco

    from place_safe.sim.robot import SimRobot
    from place_safe.sim.scenario import Scenario, load_scenario
    from place_safe.sim.scene import build_scene
    from place_safe.sim.tof_mismatch import make_sensor

    sc = scenario if isinstance(scenario, Scenario) else load_scenario(scenario)
    scene = build_scene(sc.scene_config())
    E = error_transform(mount_error)
    m = scene.model
    if not np.array_equal(E, np.eye(4)):  # move the sensor site only when the mount is really off
        s = scene.sensor_site
        R_site = Rotation.from_quat(m.site_quat[s][[1, 2, 3, 0]]).as_matrix()
        m.site_pos[s] = m.site_pos[s] + R_site @ E[:3, 3]
        x, y, z, w = Rotation.from_matrix(R_site @ E[:3, :3]).as_quat()
        m.site_quat[s] = [w, x, y, z]
        m.site_sameframe[s] = 0  # the compiler marked the nominal site as aligned with its body: not any more
    shift = np.asarray(sc.sensor.mount_offset, dtype=float)
    if np.any(shift):  # a known mount elsewhere (e.g. near the jaws): the site and the configured frame move alike
        s = scene.sensor_site
        m.site_pos[s] = m.site_pos[s] + shift  # the site's position is in the flange body's frame
        m.site_sameframe[s] = 0
    robot = SimRobot(m, mujoco.MjData(m), hold_cup=hold_cup)
    if np.any(shift):
        moved = robot.tool.flange_T_sensor.copy()
        moved[:3, 3] += shift
        robot.tool = robot.tool.with_sensor(moved)
    if sc.robot.start_q is not None:
        robot.set_joint_positions(sc.robot.start_q, hold_cup=hold_cup)
    tof = make_sensor(sc.sensor.model, scene, robot.data, sc.sensor.tof_config(seed), sc.sensor.mismatch)
    if attach:
        tof.attach(robot)
    return SimWorld(scene, robot, tof, sc.name or "scenario", E, sc)


__all__ = ["SimWorld", "sim_world", "error_transform"]
