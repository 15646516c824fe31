"""The MuJoCo scene: a table (level or tilted), a floor, optional clutter, and either the UR5 or a bare sensor rig.

Conventions
-----------
* World frame: z up, the floor is the plane ``z = 0``; lengths in metres, angles in radians.
* The table is a box slab. ``table.height`` is the world height of its top surface at its centre,
  ``table.center`` the (x, y) of that centre and ``table.size`` its (length along x, width along y,
  thickness). So its near edge (towards the robot at the origin) is at ``x = center[0] - size[0] / 2``.
  ``tilt`` rotates the slab about its centre so the top normal leans by ``tilt`` towards the world
  azimuth ``tilt_direction`` (0 = +x).
* A :class:`Material` describes how a surface looks to the time-of-flight sensor: ``albedo`` is
  relative to the sensor's calibrated ``albedo`` (1.0 = the table of the real sweep), the specular
  lobe as in :mod:`place_safe.recovery.forward`. ``pattern = "checker"`` alternates ``albedo`` and ``albedo2``
  in squares of ``square`` metres on the geom's local x-y plane. A specular weight/exponent of
  ``None`` means the sensor's calibrated values, i.e. a surface like the real sweep's table.
* Surfaces the sensor sees are in geom group :data:`SENSED_GROUP`; the robot's own geoms are moved
  out of it (group 0 -> 1) and the rig's marker is in group 2, so the ray caster never sees them.
* ``with_robot`` starts from ``robots/ur5/ur5.xml`` (which carries the ``tof_sensor`` site) with its
  ``base`` body moved to the robot base pose (the cup, a free body, is re-placed by SimRobot); otherwise a mocap body ``sensor_rig`` carries the ``tof_sensor`` site (+z = optical axis).

Built with :class:`mujoco.MjSpec`; :func:`build_scene` returns the compiled model, the spec and the
per-geom material table the simulated sensor reads.
"""

from __future__ import annotations

import math
import os
from dataclasses import asdict, dataclass, field, is_dataclass
from pathlib import Path
from typing import Any, ClassVar, Optional

import numpy as np
from pydantic import Field, model_validator

from place_safe.config import ParamModel, read_json, vector
from place_safe.exceptions import PlaceSafeError
from place_safe.robot.description import ur5_mjcf_path

if "MUJOCO_GL" not in os.environ and not os.environ.get("DISPLAY"):
    os.environ["MUJOCO_GL"] = "egl"  # offscreen rendering without a display (read when mujoco is imported)

#: Geom group holding every surface the simulated sensor can see.
SENSED_GROUP = 0
#: Group the robot's geoms are moved to (from group 0) so they are invisible to the sensor.
ROBOT_GROUP = 1
#: Group of decorative geoms (the rig marker).
MARKER_GROUP = 2
SENSOR_SITE = "tof_sensor"
RIG_BODY = "sensor_rig"
TABLE_GEOM = "table"
TABLE_BODY = "table_body"  # the mocap body of a movable table (TableConfig.movable)
FLOOR_GEOM = "floor"


class SceneError(PlaceSafeError, ValueError):
    """A scene description is malformed or cannot be built."""


# ---------------------------------------------------------------------------------------------
# Configuration
# ---------------------------------------------------------------------------------------------
class _SceneModel(ParamModel):
    """A scene setting: ranges wide enough for anything a lab bench could hold (m, rad); errors are SceneError."""

    error: ClassVar[type[Exception]] = SceneError


class Material(_SceneModel):
    """Reflectance of a surface for the ToF sensor (see module docstring)."""

    what: ClassVar[str] = "material"

    albedo: float = Field(1.0, ge=0.0, le=100.0, description="(relative to the sensor's calibrated albedo)")
    # None: the sensor's calibrated lobe (as the real sweep's table)
    specular_weight: Optional[float] = Field(None, ge=0.0, le=100.0, description="(relative to the diffuse term)")
    specular_exponent: Optional[float] = Field(None, gt=0.0, le=1000.0, description="(Phong exponent)")
    pattern: str = "uniform"  # "uniform" or "checker"
    # checker square size; one smaller than a millimetre is not a surface pattern
    square: float = Field(0.05, ge=0.001, le=10.0, description="m")
    albedo2: float = Field(0.3, ge=0.0, le=100.0, description="(relative)")  # second checker albedo

    @model_validator(mode="after")
    def _known_pattern(self) -> "Material":
        if self.pattern not in ("uniform", "checker"):
            raise ValueError(f"pattern {self.pattern!r} unknown; expected 'uniform' or 'checker'")
        return self

    def rgba(self) -> list[float]:
        """A grey for the renderer that brightens with albedo (visual only)."""
        g = float(np.clip(0.25 + 0.5 * self.albedo, 0.05, 0.95))
        return [g, g * 0.95, g * 0.9, 1.0]


class TableConfig(_SceneModel):
    what: ClassVar[str] = "table"

    height: float = Field(0.75, ge=0.0, le=3.0, description="m")  # top surface at the centre
    # world x, y of the top's centre (under the UR5's home TCP)
    center: vector(2, ge=-10.0, le=10.0) = Field(default_factory=lambda: [-0.5, -0.1], description="m")
    # x length, y width, thickness
    size: vector(3, gt=0.0, le=10.0) = Field(default_factory=lambda: [0.6, 0.9, 0.04], description="m")
    tilt: float = Field(0.0, gt=-math.pi / 2, lt=math.pi / 2, description="rad")
    # world azimuth the top normal leans towards
    tilt_direction: float = Field(0.0, ge=-2 * math.pi, le=2 * math.pi, description="rad")
    material: Material = Field(default_factory=Material)
    # the top on a mocap body, so that a run can move it (:meth:`Scene.move_table`: a lift table, a tray handed over);
    # a world geom moved by editing the model keeps its old place in the collision broad phase (a cup released on a
    # risen table fell through it to where it had been)
    movable: bool = False


class ClutterItem(_SceneModel):
    """A box (size = half extents x, y, z) or cylinder (size = radius, half height) resting anywhere."""

    what: ClassVar[str] = "clutter item"

    shape: str = "box"
    pos: vector(3, ge=-10.0, le=10.0) = Field(default_factory=lambda: [0.5, 0.2, 0.8], description="m")
    # xyz extrinsic
    euler: vector(3, ge=-2 * math.pi, le=2 * math.pi) = Field(default_factory=lambda: [0.0, 0.0, 0.0],
                                                               description="rad")
    size: vector(gt=0.0, le=5.0) = Field(default_factory=lambda: [0.03, 0.03, 0.05], description="m")
    material: Material = Field(default_factory=lambda: Material(albedo=0.6))

    @model_validator(mode="after")
    def _sizes_fit_the_shape(self) -> "ClutterItem":
        need = {"box": 3, "cylinder": 2}
        if self.shape not in need:
            raise ValueError(f"shape {self.shape!r} unknown; expected 'box' or 'cylinder'")
        if len(self.size) != need[self.shape]:
            raise ValueError(f"a {self.shape} needs {need[self.shape]} positive sizes, got {self.size!r}")
        return self


class SceneConfig(_SceneModel):
    """Everything needed to build a scene; loads from and saves to JSON."""

    what: ClassVar[str] = "scene"

    table: TableConfig = Field(default_factory=TableConfig)
    floor: Material = Field(default_factory=lambda: Material(albedo=0.5))
    clutter: list[ClutterItem] = Field(default_factory=list)
    with_robot: bool = False
    robot_xml: Optional[str] = None  # default: the packaged robots/ur5/ur5.xml
    # a pedestal fills the gap to the floor
    robot_base_pos: vector(3, ge=-10.0, le=10.0) = Field(default_factory=lambda: [0.0, 0.0, 0.8], description="m")
    robot_base_yaw: float = Field(0.0, ge=-2 * math.pi, le=2 * math.pi, description="rad")
    # sensor rig: initial sensor position
    rig_pos: vector(3, ge=-10.0, le=10.0) = Field(default_factory=lambda: [-0.5, -0.1, 0.95], description="m")
    # default looks straight down
    rig_euler: vector(3, ge=-2 * math.pi, le=2 * math.pi) = Field(default_factory=lambda: [math.pi, 0.0, 0.0],
                                                                  description="rad")
    robot_material: Material = Field(default_factory=lambda: Material(albedo=0.4))
    # default: the robot model's (0.002 for the rig); at most the 125 Hz control period (1e-12 s never ended a run)
    timestep: Optional[float] = Field(None, ge=5e-4, le=0.008, description="s")

    @model_validator(mode="after")
    def _robot_model_usable(self) -> "SceneConfig":
        if self.robot_xml is not None:  # checked when the scene is read, not only when it is built
            from place_safe.io.input_file import input_file_problem

            if (why := input_file_problem(self.robot_xml)) is not None:
                raise ValueError(f"robot model {self.robot_xml!r} not found or unusable: it {why}; "
                                 "expected the UR5 MJCF")
        return self

    # -- file form -----------------------------------------------------------------------------
    @classmethod
    def load(cls, path: str | Path) -> "SceneConfig":
        """The scene of a JSON file (a SceneConfig, or a scenario file with a ``scene`` key). A relative ``robot_xml``
        is the file's folder's, made absolute, as a scenario file's (:mod:`place_safe.sim.scenario`): it was the
        working folder's, so the model next to the scene was found only when run from there."""
        d = read_json(path, "scene file", SceneError)
        if isinstance(d, dict) and "scene" in d:  # a scenario file holding a scene
            d = d["scene"]
        return cls.from_dict(robot_xml_from(d, Path(path).parent) if isinstance(d, dict) else d)


def robot_xml_from(scene: dict, folder: str | Path) -> dict:
    """A scene's settings ``scene`` with a relative ``robot_xml`` read from ``folder`` (the folder of the file that
    holds it) and made absolute (so that settings validated again from their dump do not join the folder twice);
    ``scene`` itself where there is nothing to resolve."""
    xml = scene.get("robot_xml")
    if not (isinstance(xml, str) and xml and not Path(xml).is_absolute()):
        return scene
    return {**scene, "robot_xml": str((Path(folder) / xml).absolute())}


def scene_config(path: str | Path | None = None, with_robot: bool | None = None) -> SceneConfig:
    """A scene file's SceneConfig (the default scene without a path); ``with_robot`` overrides the file's."""
    cfg = SceneConfig.load(path) if path else SceneConfig()
    if with_robot is not None:
        cfg.with_robot = with_robot
    return cfg


# ---------------------------------------------------------------------------------------------
# Rotations (MuJoCo quaternions are w, x, y, z)
# ---------------------------------------------------------------------------------------------
def euler_to_quat(euler: tuple[float, float, float]) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_euler("xyz", euler).as_quat(scalar_first=True)


def matrix_to_quat(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat(scalar_first=True)


def tilt_quat(tilt: float, direction: float) -> np.ndarray:
    """Rotation leaning +z by ``tilt`` towards world azimuth ``direction``."""
    axis = np.array([-math.sin(direction), math.cos(direction), 0.0])
    return np.concatenate([[math.cos(tilt / 2)], math.sin(tilt / 2) * axis])


# ---------------------------------------------------------------------------------------------
# Material table
# ---------------------------------------------------------------------------------------------
@dataclass
class MaterialTable:
    """Per-geom reflectance arrays (index = geom id), as the simulated sensor needs them."""

    albedo: np.ndarray
    albedo2: np.ndarray
    specular_weight: np.ndarray  # NaN: the sensor's own value
    specular_exponent: np.ndarray  # NaN: the sensor's own value
    square: np.ndarray  # m; 0 for uniform materials

    @classmethod
    def uniform(cls, ngeom: int, m: Material) -> "MaterialTable":
        def full(v: float) -> np.ndarray:
            return np.full(ngeom, float(v))

        return cls(full(m.albedo), full(m.albedo2), full(_nan(m.specular_weight)), full(_nan(m.specular_exponent)),
                   full(0.0))

    def set(self, gid: int, m: Material) -> None:
        self.albedo[gid] = m.albedo
        self.albedo2[gid] = m.albedo2
        self.specular_weight[gid] = _nan(m.specular_weight)
        self.specular_exponent[gid] = _nan(m.specular_exponent)
        self.square[gid] = m.square if m.pattern == "checker" else 0.0

    def lookup(self, geom_ids: np.ndarray, local_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Albedo, specular weight and exponent at hits on ``geom_ids`` (N,), local points ``local_xy`` (N, 2).

        Checker squares alternate on ``floor(x / square) + floor(y / square)`` being even/odd.
        Ids < 0 (misses) get zeros; NaN specular entries mean "the sensor's own value".
        """
        g = np.asarray(geom_ids)
        ok = g >= 0
        gi = np.where(ok, g, 0)
        sq = self.square[gi]
        checker = sq > 0
        with np.errstate(divide="ignore", invalid="ignore"):
            cell = np.floor(local_xy / np.where(checker, sq, 1.0)[:, None]).sum(axis=1)
        odd = checker & (np.mod(cell, 2.0) == 1.0)
        albedo = np.where(odd, self.albedo2[gi], self.albedo[gi])
        return (np.where(ok, albedo, 0.0), np.where(ok, self.specular_weight[gi], 0.0),
                np.where(ok, self.specular_exponent[gi], 1.0))


def _nan(v: float | None) -> float:
    return float("nan") if v is None else float(v)


# ---------------------------------------------------------------------------------------------
# Builder
# ---------------------------------------------------------------------------------------------
@dataclass
class Scene:
    """A compiled scene: the model, its spec, materials and the ids the sensor needs."""

    config: SceneConfig
    spec: Any  # mujoco.MjSpec
    model: Any  # mujoco.MjModel
    materials: MaterialTable
    sensor_site: int
    table_geom: int
    floor_geom: int
    rig_mocap: int  # mocap index of the sensor rig, -1 with the robot
    robot_geoms: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))
    table_body: int = -1  # body id of a movable table's mocap body (TableConfig.movable), -1 for a fixed table

    @property
    def sensed_groups(self) -> np.ndarray:
        g = np.zeros(6, dtype=np.uint8)
        g[SENSED_GROUP] = 1
        return g

    def make_data(self):
        import mujoco

        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        return data

    def set_sensor_pose(self, data, pos: np.ndarray, R: np.ndarray) -> None:
        """Place the rig so the sensor site is at ``pos`` with rotation ``R`` (world <- sensor); rig scenes only."""
        import mujoco

        if self.rig_mocap < 0:
            raise SceneError("set_sensor_pose needs a sensor-rig scene (with_robot=False)")
        data.mocap_pos[self.rig_mocap] = np.asarray(pos, dtype=float)
        data.mocap_quat[self.rig_mocap] = matrix_to_quat(R)
        mujoco.mj_kinematics(self.model, data)

    def move_table(self, data, shift: Any) -> None:
        """Put a movable table (:attr:`TableConfig.movable`) ``shift`` (3,) m from where it was built, world frame;
        it is there from the next physics step on."""
        if self.table_body < 0:
            raise SceneError("move_table needs a movable table (scene.table.movable = true)")
        data.mocap_pos[self.model.body_mocapid[self.table_body]] = (self.model.body_pos[self.table_body]
                                                                     + np.asarray(shift, dtype=float))

    def table_plane_world(self, data) -> tuple[np.ndarray, np.ndarray]:
        """Unit normal (up) and a point of the table's top surface, in the world frame."""
        R = data.geom_xmat[self.table_geom].reshape(3, 3)
        half = self.model.geom_size[self.table_geom]
        n = R[:, 2]
        return n, data.geom_xpos[self.table_geom] + half[2] * n


def default_robot_xml() -> Path:
    """Path of the packaged UR5 model (robots/ur5/ur5.xml)."""
    return ur5_mjcf_path()


def build_scene(config: SceneConfig | None = None) -> Scene:
    """Compile the scene described by ``config`` (default: level table and a sensor rig)."""
    import mujoco

    cfg = config if config is not None else SceneConfig()
    materials: dict[str, Material] = {}
    if cfg.with_robot:
        spec = _robot_spec(cfg)
    else:
        spec = mujoco.MjSpec()
        spec.modelname = "place_safe_rig_scene"
        rig = spec.worldbody.add_body(name=RIG_BODY, mocap=True, pos=list(cfg.rig_pos),
                                      quat=list(euler_to_quat(cfg.rig_euler)))
        rig.add_site(name=SENSOR_SITE, size=[0.004, 0.004, 0.004], rgba=[1, 0.2, 0.2, 1])
        rig.add_geom(name="rig_marker", type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.01, 0.01, 0.004],
                     pos=[0, 0, -0.006], rgba=[0.1, 0.1, 0.1, 1], group=MARKER_GROUP, contype=0, conaffinity=0)
        spec.option.timestep = cfg.timestep if cfg.timestep else 0.002
    wb = spec.worldbody
    spec.add_texture(name="skygrad", type=mujoco.mjtTexture.mjTEXTURE_SKYBOX,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_GRADIENT, rgb1=[0.6, 0.7, 0.8], rgb2=[0.1, 0.1, 0.15],
                     width=64, height=64)
    wb.add_light(name="scene_light", pos=[0.3, 0.0, 2.5], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8])
    if cfg.with_robot and cfg.robot_base_pos[2] > 0:
        h = cfg.robot_base_pos[2]
        wb.add_geom(name="pedestal", type=mujoco.mjtGeom.mjGEOM_CYLINDER, size=[0.09, h / 2, 0],
                    pos=[cfg.robot_base_pos[0], cfg.robot_base_pos[1], h / 2], rgba=[0.3, 0.3, 0.32, 1],
                    group=SENSED_GROUP)
        materials["pedestal"] = cfg.robot_material
    # floor
    wb.add_geom(name=FLOOR_GEOM, type=mujoco.mjtGeom.mjGEOM_PLANE, size=[3, 3, 0.05], rgba=cfg.floor.rgba(),
                group=SENSED_GROUP)
    materials[FLOOR_GEOM] = cfg.floor
    # table
    t = cfg.table
    if t.height <= 0 or min(t.size) <= 0 or not (0 <= t.tilt < math.pi / 2):
        raise SceneError("table needs height > 0, positive size and 0 <= tilt < 90 deg")
    q = tilt_quat(t.tilt, t.tilt_direction)
    R = _quat_matrix(q)
    top = np.array([t.center[0], t.center[1], t.height])
    centre = top - R[:, 2] * t.size[2] / 2
    holder, pose = wb, dict(pos=list(centre), quat=list(q))
    if t.movable:
        holder, pose = wb.add_body(name=TABLE_BODY, mocap=True, **pose), {}
    table_geom = holder.add_geom(name=TABLE_GEOM, type=mujoco.mjtGeom.mjGEOM_BOX, size=[s / 2 for s in t.size],
                                 rgba=t.material.rgba(), group=SENSED_GROUP, **pose)
    _visual_material(spec, table_geom, TABLE_GEOM, t.material)
    materials[TABLE_GEOM] = t.material
    # clutter
    for i, c in enumerate(cfg.clutter):
        name = f"clutter{i}"
        gtype = mujoco.mjtGeom.mjGEOM_BOX if c.shape == "box" else mujoco.mjtGeom.mjGEOM_CYLINDER
        size = list(c.size) + [0.0] * (3 - len(c.size))
        g = wb.add_geom(name=name, type=gtype, size=size, pos=list(c.pos), quat=list(euler_to_quat(c.euler)),
                        rgba=c.material.rgba(), group=SENSED_GROUP)
        _visual_material(spec, g, name, c.material)
        materials[name] = c.material
    try:
        model = spec.compile()
    except Exception as exc:
        raise SceneError(f"scene does not compile: {exc}") from None
    site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, SENSOR_SITE)
    if site < 0:
        raise SceneError(f"the model has no site {SENSOR_SITE!r}; the robot model must carry the sensor site")
    table = MaterialTable.uniform(model.ngeom, cfg.robot_material)
    for name, m in materials.items():
        table.set(mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, name), m)
    rig_mocap = -1
    if not cfg.with_robot:
        rig_mocap = int(model.body_mocapid[mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, RIG_BODY)])
    table_body = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, TABLE_BODY) if t.movable else -1
    table_id = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, TABLE_GEOM)
    robot_geoms = (np.flatnonzero((model.geom_bodyid != 0) & (np.arange(model.ngeom) != table_id))
                   if cfg.with_robot else np.zeros(0, dtype=int))
    return Scene(cfg, spec, model, table, int(site), table_id,
                 mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, FLOOR_GEOM), rig_mocap, robot_geoms, table_body)


def _visual_material(spec, geom, name: str, m: Material) -> None:
    """Show a checker material as a checker texture in renderings (visual only; the sensor uses the table)."""
    import mujoco

    if m.pattern != "checker":
        return
    a, b = Material(albedo=m.albedo).rgba(), Material(albedo=m.albedo2).rgba()
    spec.add_texture(name=f"{name}_checker", type=mujoco.mjtTexture.mjTEXTURE_2D,
                     builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER, rgb1=a[:3], rgb2=b[:3], width=64, height=64)
    mat = spec.add_material(name=f"{name}_checker")
    mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = f"{name}_checker"
    mat.texuniform = True
    mat.texrepeat = [1.0 / (2 * m.square), 1.0 / (2 * m.square)]  # one texture = 2 x 2 squares
    geom.material = f"{name}_checker"
    geom.rgba = [1.0, 1.0, 1.0, 1.0]


def _robot_spec(cfg: SceneConfig):
    """The UR5 model as the scene's starting spec, base at the configured pose, geoms out of the sensed group.

    The robot's file supplies the simulation options (its servos are tuned for its timestep).
    """
    import mujoco

    from place_safe.io.input_file import input_file_problem

    xml = Path(cfg.robot_xml) if cfg.robot_xml else default_robot_xml()
    if (why := input_file_problem(xml)) is not None:  # also never a FIFO or a device, and a bounded size
        raise SceneError(f"robot model {xml} not found or unusable: it {why}; expected the UR5 MJCF (robots/ur5/ur5.xml)")
    try:
        spec = mujoco.MjSpec.from_file(str(xml))
    except Exception as exc:  # mujoco raises plain ValueError with its parser message
        raise SceneError(f"cannot load robot model {xml}: {exc}") from None
    base = spec.body("base")
    if base is None:
        raise SceneError(f"robot model {xml} has no body 'base'")
    yaw = cfg.robot_base_yaw
    base.pos = list(cfg.robot_base_pos)
    base.quat = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    for geom in spec.geoms:
        if geom.group == SENSED_GROUP:
            geom.group = ROBOT_GROUP
    if cfg.timestep:
        spec.option.timestep = cfg.timestep
    return spec


def _normalised(q: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(q)
    return q / n if n > 0 else np.array([1.0, 0, 0, 0])


def _quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    w1, x1, y1, z1 = a
    w2, x2, y2, z2 = b
    return np.array([w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2, w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
                     w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2, w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2])


def _quat_matrix(q: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_quat(np.asarray(q, dtype=float), scalar_first=True).as_matrix()


def as_plain(obj: Any) -> Any:
    """Dataclasses and parameter models to plain dicts (for JSON)."""
    if isinstance(obj, ParamModel):
        return obj.to_dict()
    return asdict(obj) if is_dataclass(obj) else obj
