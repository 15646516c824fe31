"""Scenario files: one simulated placement situation and the outcome it must have (validated schema).

Concept: a :class:`Scenario` says what the world is (``scene``), how the simulated sensor behaves
(``sensor``), where the robot starts and what goes wrong with it (``robot``), which calibration
the estimator gets (``calibration``), which method and placement settings are used, and what the
run must come to (``expect``, with tolerances). Files are TOML (hand-written) or JSON (the older
files and generated ones) and are validated on load by pydantic (:class:`place_safe.config.ConfigModel`):
unknown keys, wrong types and NaN are one-line :class:`~place_safe.exceptions.ConfigError`\\ s naming the
file and the field. ``scenarios/README.md`` documents every field.

Conventions: SI units (m, s, rad) as everywhere in place_safe, except the few fields whose names say
``_deg`` (hand-written tilts read better in degrees; ``tilt`` and ``tilt_deg`` cannot both be given).
World frame z up; the scene part is :class:`place_safe.sim.scene.SceneConfig` (validated by it).

Simulation truth used to judge a run (:class:`RunTruth`, recorded by :class:`TruthRecorder` from the
robot's step callbacks, never shown to the estimator or the machine): the true surface tilt and
height, the cup-bottom height above the surface when the gripper opened, the time the cup bottom
passed 40 cm above the surface, and whether the cup ended upright, on the table, without spilling.
"""

from __future__ import annotations

import math
import unicodedata
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from place_safe.config import CONTROL_CATEGORIES, ConfigModel, field_constraints, parse_config, read_config_file
from place_safe.assets import scenarios_dir
from place_safe.exceptions import ConfigError

from place_safe.sim.tof_mismatch import MismatchConfig
from place_safe.calibration import Calibration
from place_safe.placement.config import PlacementConfig
from place_safe.recovery import METHODS
from place_safe.robot.description import ur5_config
from place_safe.robot.kinematics import Kinematics
from place_safe.sim.scene import SceneConfig, SceneError, robot_xml_from
from place_safe.sim.tof import ToFConfig, calibration_file, sensor_file, simulated_calibration
from place_safe.io.input_file import input_file_problem

#: m, the "time from 40 cm" reference height of the cup bottom above the surface (issue 12).
REFERENCE_HEIGHT = 0.40
#: rad, a released cup tilted more than this at the end has tipped.
TIPPED_TILT = math.radians(10.0)
#: m, a released cup whose bottom ends farther than this from the table top is not standing on it.
ON_TABLE_TOL = 0.005
#: Calibration names that are not files.
CALIBRATION_KINDS = ("sim", "oracle", "none")
SUFFIXES = (".toml", ".json")


class SurfaceMotion(ConfigModel):
    """The table moving along world z during the descent (a lift table, a tray being handed over)."""

    start: float = Field(1.0, ge=0, le=3600, description="sim time the motion starts (s, 0..3600)")
    velocity: float = Field(0.02, ge=-0.5, le=0.5, description="vertical speed (m/s, + rises; -0.5..0.5)")
    duration: float = Field(1.0, ge=0, le=3600, description="how long it moves (s, 0..3600)")


#: m: one component of the sensor's mount offset (:attr:`SensorSection.mount_offset`).
MountShift = Annotated[float, Field(ge=-0.2, le=0.2)]


class SensorSection(ConfigModel):
    """The simulated sensor (``place_safe.sim.tof.ToFConfig`` settings and which simulator)."""

    model: Literal["nominal", "mismatch"] = Field("nominal", description="nominal: renders with the forward "
                                                  "model; mismatch: MismatchedToF, a sensor that is not the model")
    noise: bool = True
    rays: int = Field(8, ge=1, le=32)
    rate_hz: float = Field(30.0, **field_constraints(ToFConfig, "rate_hz"), description="frame rate (Hz)")
    ambient_range: tuple[float, float] = Field((60.0, 180.0), description="per-zone ambient floor range (counts)")
    drop_prob: float = Field(0.0, **field_constraints(ToFConfig, "drop_prob"))
    corrupt_prob: float = Field(0.0, **field_constraints(ToFConfig, "corrupt_prob"))
    spike_prob: float = Field(0.0, **field_constraints(ToFConfig, "spike_prob"),
                              description="probability of a latency spike per frame")
    spike_seconds: float = Field(0.25, ge=0, le=5, description="extra latency of a spike (s)")
    seed: int | None = Field(None, description="noise seed; default: the run's seed")
    mismatch: MismatchConfig | None = Field(None, description="differences of the mismatched sensor")
    mount_offset: tuple[MountShift, MountShift, MountShift] = Field(
        (0.0, 0.0, 0.0), description="where the sensor is mounted, from the packaged bracket (m, flange frame, each "
        "-0.2..0.2; +z towards the cup): moves the simulated sensor and the robot's configured sensor frame alike "
        "(a known mount, e.g. near the jaws; not a mount error)")

    @field_validator("ambient_range")
    @classmethod
    def _range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if not (0 <= v[0] <= v[1]):
            raise ValueError("ambient_range must be [low, high] counts with 0 <= low <= high")
        return v

    @model_validator(mode="after")
    def _mismatch_read(self) -> "SensorSection":
        """A ``mismatch`` table is read by the mismatched sensor alone: with the nominal model it was taken and never
        read, and the run tested the nominal sensor (round 14)."""
        if self.mismatch is not None and self.model != "mismatch":
            raise ValueError('mismatch is read only by the mismatched sensor (model = "mismatch"); with model = '
                             f'"{self.model}" it would be ignored: give the model, or leave the mismatch table out')
        return self

    @model_validator(mode="after")
    def _in_simulator_bounds(self) -> "SensorSection":
        """Every setting within the simulated sensor's own ranges (the fields of sim.tof.ToFConfig), checked on load."""

        try:
            self.tof_config(0)
        except SceneError as exc:
            raise ValueError(str(exc).replace("sensor settings: ", "", 1)) from None
        return self

    def tof_config(self, seed: int) -> ToFConfig:
        return ToFConfig(rays=self.rays, rate_hz=self.rate_hz, noise=self.noise, ambient_range=self.ambient_range,
                         drop_prob=self.drop_prob, corrupt_prob=self.corrupt_prob, spike_prob=self.spike_prob,
                         spike_seconds=self.spike_seconds, seed=seed if self.seed is None else self.seed)


#: rad: one UR5 joint angle (every joint turns -360..360 degrees).
JointAngle = Annotated[float, Field(ge=-2 * math.pi, le=2 * math.pi)]


class RobotSection(ConfigModel):
    """Where the robot starts and what goes wrong with it."""

    start_q: tuple[JointAngle, JointAngle, JointAngle, JointAngle, JointAngle, JointAngle] | None = Field(
        None, description="start joint angles (rad, each -2 pi..2 pi: the UR5's joint range); default: home")
    protective_stop_at: float | None = Field(None, ge=0, le=3600,
                                             description="latch a protective stop at this sim time (s, 0..3600)")
    protective_stop_below: float | None = Field(
        None, gt=0, le=1.0, description="latch a protective stop when the cup bottom is this close to the surface "
                                        "(m, up to 1)")


class Expectation(ConfigModel):
    """What the run must come to, with tolerances (simulation truth)."""

    outcome: Literal["released", "refused", "any"] = "released"
    reason: list[str] = Field(default_factory=list, description="for refusals: the reason must contain one of "
                              "these words (case-insensitive); empty: any reason")
    max_release_height: float = Field(0.010, gt=0, le=1.0, description="cup bottom above the surface at release "
                                      "(m, up to 1)")
    max_spilled: int = Field(0, ge=0, le=10_000, description="liquid spheres allowed outside the cup")
    max_decision_time: float | None = Field(None, gt=0, le=3600,
                                            description="s from 40 cm above the surface to the decision (up to 3600)")
    max_contact_force: float | None = Field(None, gt=0, le=10_000,
                                            description="N: the hardest contact of the cup allowed (up to 10000)")

    @field_validator("reason")
    @classmethod
    def _words(cls, words: list[str]) -> list[str]:
        """An empty word is in every reason: ``reason = [""]`` made the check one that can never fail (an adversarial
        round, session 74)."""
        if any(not w.strip() for w in words):
            raise ValueError("every reason word must be non-empty (an empty one matches any reason; leave the list "
                             "empty for any reason)")
        return words


class Scenario(ConfigModel):
    """One scenario file (see module docstring and scenarios/README.md)."""

    description: str = ""
    name: str = Field("", description="set from the file name when loaded")
    scene: dict = Field(default_factory=dict, description="place_safe.sim.scene.SceneConfig (validated by it); "
                        "table.tilt_deg / tilt_direction_deg accepted; start_height (m) sets the table under the cup")
    surface_motion: SurfaceMotion | None = None
    sensor: SensorSection = Field(default_factory=SensorSection)
    robot: RobotSection = Field(default_factory=RobotSection)
    calibration: str = Field("sim", description="sim: the packaged simulated user calibration of this sensor; "
                             "oracle: the simulator's true parameters (debugging only); none: uncalibrated; "
                             "or a calibration file (relative to the scenario file)")
    method: str = Field("diff", description="plane-recovery method")
    placement: dict = Field(default_factory=dict, description="PlacementConfig overrides (SI units)")
    expect: Expectation | None = None
    labels: dict | None = Field(None, description="generator's truth labels (random scenes): support, clearly_safe")
    base_dir: str = Field("", description="directory of the file (set when loaded)")

    @field_validator("name")
    @classmethod
    def _printable_name(cls, v: str) -> str:
        """No control characters (an escape sequence, a newline, a bidirectional override): the name is printed in
        the scenarios' table and messages and goes into file names."""
        bad = next((c for c in v if unicodedata.category(c) in CONTROL_CATEGORIES), None)
        if bad is not None:
            raise ValueError(f"must not contain control characters, got {bad!r} in {v[:80]!r}")
        return v

    @model_validator(mode="before")
    @classmethod
    def _conveniences(cls, d: Any) -> Any:
        if not isinstance(d, dict):
            return d
        d = dict(d)
        scene = d.get("scene")
        if scene is None:
            scene = {}
        if not isinstance(scene, dict):  # scene = 5, a list, true: the file's error, not an internal one
            raise ValueError(f"scene must be a table of scene settings, got {_kind(scene)}")
        scene = dict(scene)
        if d.get("base_dir"):  # a relative robot model from the file's folder, as its calibration (it was the
            scene = robot_xml_from(scene, d["base_dir"])  # working folder's)
        table = scene.get("table")
        if isinstance(table, dict):
            table = dict(table)
            for deg, rad in (("tilt_deg", "tilt"), ("tilt_direction_deg", "tilt_direction")):
                if deg in table:
                    if rad in table:
                        raise ValueError(f"scene.table: give {rad} (rad) or {deg} (deg), not both")
                    v = table.pop(deg)
                    if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v):
                        raise ValueError(f"scene.table.{deg} must be a finite number of degrees")
                    if deg == "tilt_deg" and not -90.0 < v < 90.0:  # (the field's own bound would be said in rad)
                        raise ValueError(f"scene.table.tilt_deg must be between -90 and 90 deg (exclusive), got {v:g}")
                    if deg == "tilt_direction_deg" and not -360.0 <= v <= 360.0:  # (the same)
                        raise ValueError(f"scene.table.tilt_direction_deg must be between -360 and 360 deg, got {v:g}")
                    table[rad] = math.radians(v)
            _lean_the_other_way(table)
            scene["table"] = table
        d["scene"] = scene
        bad = _non_finite(scene, "scene")
        if bad:
            raise ValueError(f"{bad} must be a finite number")
        return d

    @model_validator(mode="after")
    def _check_parts(self) -> "Scenario":
        self.scene_config()  # raises with the scene's own message
        if not self.calibration.strip():  # (else read as the scenario's own directory)
            raise ValueError(f"calibration is empty; expected one of {', '.join(CALIBRATION_KINDS)} or a calibration "
                             "file")
        if self.calibration not in CALIBRATION_KINDS:  # a calibration file: there and readable before any run

            if (why := input_file_problem(self._calibration_path())) is not None:
                raise ValueError(f"calibration file {self.calibration} {why}")
        if self.method not in METHODS:
            raise ValueError(f"method {self.method!r} unknown; expected one of {', '.join(METHODS)}")
        self.placement_config()
        return self

    # -- the parts as the simulation needs them --------------------------------------------------
    def scene_config(self):
        """The :class:`~place_safe.sim.scene.SceneConfig` (always with the robot)."""
        d = dict(self.scene)
        start_height = d.pop("start_height", None)
        try:
            cfg = SceneConfig.from_dict(d)
        except SceneError as exc:
            raise ValueError(str(exc)) from None
        cfg.with_robot = True
        if self.surface_motion is not None:
            cfg.table.movable = True  # moved by TruthRecorder (a world geom would keep its old place for contacts)
        if start_height is not None:
            if not isinstance(start_height, (int, float)) or not (0.02 <= start_height <= 0.8):
                raise ValueError("scene.start_height must be 0.02..0.8 m (cup bottom above the table at the start)")
            # the table's centre height that puts the (tilted) top start_height below the cup's bottom
            # centre, measured along the vertical under the cup (not at the table's centre)
            cup = home_cup_position(cfg)
            t = cfg.table
            n = np.array([math.sin(t.tilt) * math.cos(t.tilt_direction), math.sin(t.tilt) * math.sin(t.tilt_direction),
                          math.cos(t.tilt)])
            rise = (n[0] * (cup[0] - t.center[0]) + n[1] * (cup[1] - t.center[1])) / n[2]
            cfg.table.height = float(cup[2] - start_height + rise)
        return cfg

    def placement_config(self):
        try:
            cfg = PlacementConfig.from_dict({**PlacementConfig().to_dict(), **self.placement})
            cfg.check_file_settings("")
            return cfg
        except (TypeError, ValueError, OverflowError) as exc:
            raise ValueError(f"placement: {exc}") from None

    def resolve_calibration(self, method: str | None = None) -> tuple[Any, str]:
        """(Calibration or None, note naming where it came from). ``none`` gives (None, 'uncalibrated')."""
        kind = self.calibration
        if kind == "none":
            return None, "uncalibrated"
        if kind == "oracle":
            return oracle_calibration(), ORACLE_NOTE
        if kind == "sim":
            p = calibration_file(self.sensor.model)
            return (simulated_calibration(self.sensor.model),
                    f"simulated user calibration ({p.name}: level sweep -> place-safe calibrate)")
        p = self._calibration_path()
        return Calibration.load(p), str(p)

    def _calibration_path(self) -> Path:
        """The calibration file (relative names from the scenario file's directory)."""
        p = Path(self.calibration)
        if not p.is_absolute() and self.base_dir:
            p = Path(self.base_dir) / p
        return p


def _json_kind(v: Any) -> str:
    return {bool: "boolean", int: "number", float: "number", str: "string", list: "list", type(None): "null"}.get(
        type(v), type(v).__name__)


def _kind(v: Any) -> str:
    return {bool: "a boolean", int: "a number", float: "a number", str: "a string", list: "a list"}.get(
        type(v), type(v).__name__)


def _non_finite(v: Any, where: str) -> str | None:
    """Path of the first NaN/inf number inside nested dicts/lists, or None."""
    if isinstance(v, float) and not math.isfinite(v):
        return where
    if isinstance(v, dict):
        items = v.items()
    elif isinstance(v, (list, tuple)):
        items = ((str(i), x) for i, x in enumerate(v))
    else:
        return None
    for k, x in items:
        found = _non_finite(x, f"{where}.{k}")
        if found:
            return found
    return None


ORACLE_NOTE = "ORACLE: the simulated sensor's true forward parameters (debugging only)"


def oracle_calibration():
    """The simulator's own parameters as a calibration: only for ``--oracle`` debugging runs. Diff starts from the
    peak method's plane and falls back to it, so the file carries the packaged nominal user calibration's ``peak``
    section with them (without one, diff counts as uncalibrated: ``REQUIRED_SECTIONS``), and its ``uncertainty``
    entries (without them a placement refuses: ``REQUIRED_UNCERTAINTY``)."""
    import json

    nominal = json.loads(calibration_file("nominal").read_text())
    return Calibration({"forward": json.loads(sensor_file("tmf8820_real.json").read_text()), "peak": nominal["peak"],
                        "uncertainty": nominal["uncertainty"]})


def home_cup_position(scene_cfg) -> np.ndarray:
    """World position of the cup bottom with the UR5 at home (from the kinematic model, not the simulator)."""
    from scipy.spatial.transform import Rotation

    global _HOME_CUP
    if _HOME_CUP is None:
        _HOME_CUP = Kinematics().base_T_cup(np.asarray(ur5_config()["arm"]["home"], dtype=float))[:3, 3]
    R = Rotation.from_euler("z", scene_cfg.robot_base_yaw).as_matrix()
    return np.asarray(scene_cfg.robot_base_pos, dtype=float) + R @ _HOME_CUP


_HOME_CUP: np.ndarray | None = None


# ---------------------------------------------------------------------------------------------
# files
# ---------------------------------------------------------------------------------------------
def scenario_path(name: str | Path) -> Path:
    """A scenario file: a path, or the name of a packaged one (``place_level``, ``level_30cm.toml``)."""
    if not isinstance(name, (str, Path)):
        raise ConfigError(f"scenario must be a file path or a packaged name, got {type(name).__name__}")
    p = Path(name)
    if p.is_file():
        return p
    if p.exists() or p.is_symlink():  # a directory, a FIFO, a device: never opened, never a packaged name
        raise ConfigError(f"scenario {name} {input_file_problem(p)}")
    root = scenarios_dir()
    cands = [root / p.name] if p.suffix in SUFFIXES else [root / (p.name + s) for s in SUFFIXES]
    cands += [root / "set" / c.name for c in cands]
    for c in cands:
        if c.is_file():
            return c
    raise ConfigError(f"scenario {name} not found (neither a file nor a packaged scenario in scenarios/)")


def load_scenario(name: str | Path) -> Scenario:
    """Read and validate a scenario file (TOML or JSON); one-line ConfigError on any problem."""
    p = scenario_path(name)

    data = read_config_file(p, "scenario")
    if not isinstance(data, dict):  # (a frame file given as a scenario: "Input should be a valid dictionary ...")
        raise ConfigError(f"scenario {p}: expected an object of scenario settings (a TOML table or a JSON object), got "
                          f"{'a JSON ' + _json_kind(data) if p.suffix.lower() == '.json' else _kind(data)}")
    if not set(data) - {"name", "description"}:  # an empty (or truncated) file would run the default scene
        raise ConfigError(f"scenario {p}: the file sets nothing (empty, or a name and description only); a scenario "
                          "gives at least its scene, robot, sensor or expectation (scenarios/README.md)")
    data = {**data, "name": data.get("name") or p.stem, "base_dir": str(p.parent)}
    return parse_config(Scenario, data, f"scenario {p}")


def packaged_scenarios(subdir: str = "set") -> list[Path]:
    """The hand-written set (``scenarios/set/*.toml``) or, with ``subdir=''``, the top-level files."""
    root = scenarios_dir()
    d = root / subdir if subdir else root
    return sorted(p for p in d.iterdir() if p.suffix in SUFFIXES)


def expand_paths(paths: list[str]) -> list[Path]:
    """Files and directories (every *.toml / *.json inside, sorted) as scenario files."""
    out: list[Path] = []
    for s in paths:
        p = Path(s)
        if p.is_dir():
            out += sorted(q for q in p.iterdir() if q.suffix in SUFFIXES)
        else:
            out.append(scenario_path(s))
    return out


# ---------------------------------------------------------------------------------------------
# what happens in the world: moving table, injected faults, truth recording
# ---------------------------------------------------------------------------------------------
#: m above the cup's bottom the truth's rays down to clutter start (a cup standing on a board starts above its top).
GAP_LIFT = 0.01


class TruthRecorder:
    """Robot step callback: moves the table, injects faults and records simulation truth (SI units). The release height
    is the cup bottom's above the surface it would land on: the table, or clutter under its footprint where higher."""

    def __init__(self, scenario: Scenario, scene: Any, robot: Any) -> None:
        self.sc, self.scene, self.robot = scenario, scene, robot
        self.model = scene.model
        self.start_height = math.nan
        self.t_reference: float | None = None  # cup bottom first within REFERENCE_HEIGHT of the surface
        self.release_height = math.nan
        self.release_time: float | None = None
        self.stop_injected: str | None = None
        self.min_height = math.inf
        self.surface_moved = 0.0
        self._first = True
        import mujoco

        names = (f"clutter{i}" for i in range(len(scene.config.clutter)))
        self._clutter_geoms = {g for g in (mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, n) for n in names)
                               if g >= 0}
        r = float(ur5_config()["cup"]["radius"])
        ring = [(rr * math.cos(a), rr * math.sin(a), 0.0) for rr, k in ((r / 2, 8), (r, 16))
                for a in np.linspace(0.0, 2.0 * math.pi, k, endpoint=False)]
        self._disc = np.array([(0.0, 0.0, 0.0), *ring])  # the cup's bottom disc, cup frame

    def cup_height(self) -> float:
        """Cup bottom centre above the table top along its normal (m), simulation truth."""
        n_w, p_w = self.scene.table_plane_world(self.robot.data)
        c = self.robot.world_T_base() @ self.robot.cup_pose()
        return float(n_w @ (c[:3, 3] - p_w))

    def clutter_gap(self) -> float:
        """Cup bottom above the highest clutter under its footprint (m, straight down, simulation truth; inf where no
        clutter lies under it): a cup released onto a board, a tray or a box falls that far, not to the table. Rays
        from :data:`GAP_LIFT` above the cup's bottom disc (its centre and rings at half and full radius) down to the
        first surface the sensor could see (the robot, the cup and its liquid are not in that group)."""
        import mujoco

        if not self._clutter_geoms:
            return math.inf
        c = self.robot.world_T_base() @ self.robot.cup_pose()
        down = np.array([0.0, 0.0, -1.0])
        geom = np.zeros(1, dtype=np.int32)
        groups = self.scene.sensed_groups
        gap = math.inf
        for p in c[:3, 3] + self._disc @ c[:3, :3].T:
            dist = mujoco.mj_ray(self.model, self.robot.data, p + GAP_LIFT * -down, down, groups, 1, -1, geom)
            if dist >= 0 and int(geom[0]) in self._clutter_geoms:
                gap = min(gap, float(dist) - GAP_LIFT)
        return gap

    def support_height(self) -> float:
        """Cup bottom above the surface it would land on (m): the table top (:meth:`cup_height`), or the clutter under
        its footprint where that lies higher (:meth:`clutter_gap`)."""
        return min(self.cup_height(), self.clutter_gap())

    def __call__(self, *_: Any) -> None:
        d = self.robot.data
        t = float(d.time)
        m = self.sc.surface_motion
        if m is not None and t >= m.start:
            dz = m.velocity * min(t - m.start, m.duration)
            self.scene.move_table(d, [0.0, 0.0, dz])
            self.surface_moved = dz
        h = self.cup_height()
        if self._first:
            self.start_height, self._first = h, False
        self.min_height = min(self.min_height, h)
        if self.t_reference is None and h <= REFERENCE_HEIGHT:
            self.t_reference = t
        if self.release_time is None and self.robot.gripper_is_open():
            self.release_time, self.release_height = t, min(h, self.clutter_gap())
        rb = self.sc.robot
        if self.stop_injected is None and self.robot.fault() is None and (
                (rb.protective_stop_at is not None and t >= rb.protective_stop_at)
                or (rb.protective_stop_below is not None and h <= rb.protective_stop_below)):
            self.stop_injected = f"injected protective stop at t={t:.3f} s, cup {h * 1e3:.0f} mm above the surface"
            self.robot._raise_fault(f"protective stop ({self.stop_injected})")  # what the controller latches


def _lean_the_other_way(table: dict) -> None:
    """A negative ``tilt`` (rad) of a scenario's ``scene.table`` (a dict, in place) as the same top leaning by ``-tilt``
    towards the opposite azimuth (``tilt_direction`` + 180 deg, within the field's +-360 deg): the top normal is
    ``(sin t cos a, sin t sin a, cos t)``, which ``-t`` and ``a`` give alike with ``t`` and ``a + pi``. The scene
    builds only tilts of 0 or more; a value that is not a number is left to the scene's own validation."""
    tilt, direction = table.get("tilt"), table.get("tilt_direction", 0.0)
    if not all(isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in (tilt, direction)):
        return
    if -math.pi / 2 < tilt < 0.0 and -2.0 * math.pi <= direction <= 2.0 * math.pi:  # (else the fields' bounds say so)
        direction += math.pi
        table["tilt"] = -tilt
        table["tilt_direction"] = direction - 2.0 * math.pi if direction > 2.0 * math.pi else direction


def surface_truth(scene: Any, data: Any) -> tuple[float, float]:
    """True table tilt (rad) and top height at its centre (world z, m)."""
    n_w, p_w = scene.table_plane_world(data)
    return float(math.acos(min(1.0, abs(n_w[2])))), float(p_w[2])


__all__ = ["Scenario", "SensorSection", "RobotSection", "Expectation", "SurfaceMotion", "TruthRecorder",
           "load_scenario", "scenario_path", "packaged_scenarios", "expand_paths", "oracle_calibration",
           "home_cup_position", "surface_truth", "REFERENCE_HEIGHT", "TIPPED_TILT", "ON_TABLE_TOL", "ORACLE_NOTE"]
