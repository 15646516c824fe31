"""The configuration of one real (or stand-in) UR5: a TOML file validated with pydantic.

Concept: :class:`URConfig` is everything :class:`~place_safe.drivers.ur5.rtde_robot.URRobot` needs that is
not code: where the controller is (host, CB3 or e-Series), how to connect (timeouts, retries), our own
motion limits (checked on the host before every command, tighter than the controller's), the workspace
box the TCP must stay in, the deepest point a descent may reach, the keep-out margin above a sensed
surface, the watchdog rate, the gripper (digital output or Robotiq URCap socket) and the tool frames
(TCP, TMF8820 mount, held cup) on the flange. Files: ``robots/ur5/real.toml`` and ``robots/ur5/sim.toml``
(packaged), or a user's copy after ``place-safe calibrate-mount``.

Conventions: SI units (m, m/s, m/s^2, rad, s, N); rotations as fixed-axis roll-pitch-yaw (x, y, z) in rad;
positions in the robot base frame (the UR controller's base frame).

What a file must give and what may default: a robot file drives a real arm, so whatever decides where the arm
believes things are, what it sends the controller or how hard it may move has no built-in default -- a file cut
short, or a table forgotten, is refused with one line naming the file and every missing table and key
(:data:`REQUIRED`), never silently run on a nominal mount or payload:

* ``[connection]`` ``host`` and ``controller``;
* ``[limits]``: every key (speeds, accelerations, contact force, workspace box, ``min_descent_z``,
  ``surface_keepout``: our own safety envelope, set for the arm and its table);
* ``[gripper]`` ``kind`` and, for a digital one, its wiring: ``output``, ``tool_output``, ``open_level``;
* ``[tool]`` ``payload_kg`` and ``payload_cog`` (sent to the controller: a wrong payload is read as contact);
* ``[tool.tcp]``, ``[tool.sensor]`` (the TMF8820 mount: every plane is placed through it) and ``[tool.cup]``,
  each with ``xyz`` and ``rpy``.

Defaults apply only to: ``name`` ("ur5"), ``watchdog_hz`` (10 Hz), the connection's ``connect_timeout_s`` (5 s),
``reconnect_attempts`` (3), ``reconnect_backoff_s`` (0.5 s) and ``stale_cycles`` (25), the gripper's
``settle_s`` (0.3 s) and the Robotiq URCap's port, positions, speed, force and timeout, ``[motion]`` (50 mm/s
within 50 mm of the surface, emergency stops at most 2 m/s^2: :class:`MotionConfig`), ``[contact]`` (the
controller's detector defaults: :class:`ContactConfig`) and ``tool.mount_fit`` (a record, none). The packaged
files give every key; ``calibrate-mount --write`` and ``bench robot --write`` start from a complete file and keep it so.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from pydantic import AfterValidator, Field, model_validator

from place_safe.config import ConfigModel, field_like, load_config, parse_config, toml_reader
from place_safe.exceptions import ConfigError
from place_safe.placement.config import PlacementConfig
from place_safe.robot.contact_detector import TOUCH_STEP, DetectorSettings, touch_latency
from place_safe.robot.description import ur5_dir
from place_safe.robot.tool import ToolFrames

#: Controller cycle rates (Hz): CB3 125 Hz, e-Series 500 Hz (UR documentation).
CONTROLLER_HZ = {"cb3": 125.0, "e-series": 500.0}

Vec3 = tuple[float, float, float]
#: m: a position on the flange or in the base frame (the UR5 reaches 0.85 m; tools are much shorter).
Metres2 = Annotated[float, Field(ge=-2.0, le=2.0)]
#: m: an offset of a tool frame from the flange.
ToolMetres = Annotated[float, Field(ge=-1.0, le=1.0)]
#: rad: one roll, pitch or yaw angle.
Angle = Annotated[float, Field(ge=-2 * math.pi, le=2 * math.pi)]

#: A host name label (RFC 1123): letters, digits and inner hyphens, 1-63 characters.
_LABEL = re.compile(r"(?!-)[A-Za-z0-9-]{1,63}(?<!-)")


def _short(value: str) -> str:
    return repr(value) if len(value) <= 60 else repr(value[:57]) + "..."


def check_host(value: str) -> str:
    """``value`` if it is an IPv4 or IPv6 address or a host name (RFC 1123 labels, at most 253 characters);
    ValueError otherwise. A port (``host:port``), spaces, shell characters or a URL are not a host."""
    import ipaddress

    if not isinstance(value, str):
        raise ValueError("must be a host name or an IP address (a string)")
    try:
        ipaddress.ip_address(value)
        return value
    except ValueError:
        pass
    name = value[:-1] if value.endswith(".") else value
    if ":" in value and not value.startswith("["):
        raise ValueError(f"{_short(value)} is not a host name or an IP address (give the host alone, no ':port')")
    if not name or len(name) > 253 or not all(_LABEL.fullmatch(label) for label in name.split(".")) \
            or name.replace(".", "").isdigit():
        raise ValueError(f"{_short(value)} is not a host name or an IP address (letters, digits, '-' and '.' only)")
    return value


class DigitalGripperConfig(ConfigModel):
    """A gripper switched by one digital output (pneumatic or simple electric). Its wiring (``output``,
    ``tool_output``, ``open_level``) must be given; ``settle_s`` defaults to 0.3 s."""

    kind: Literal["digital"] = "digital"
    output: int = Field(..., ge=0, le=7, description="output number (standard 0..7, tool 0..1)")
    tool_output: bool = Field(..., description="use a tool digital output instead of a standard one")
    open_level: bool = Field(..., description="output level that opens the gripper")
    settle_s: float = Field(0.3, ge=0, le=5, description="s to wait after switching")


class RobotiqGripperConfig(ConfigModel):
    """A Robotiq 2F gripper through the Robotiq URCap's ASCII socket on the controller."""

    kind: Literal["robotiq"] = "robotiq"
    port: int = Field(63352, ge=1, le=65535, description="URCap socket port")
    host: Annotated[str, AfterValidator(check_host)] | None = Field(
        None, description="host name or IP address; default: the robot's host")
    open_position: int = Field(0, ge=0, le=255, description="POS value for open (0 = fully open on a 2F-85)")
    closed_position: int = Field(255, ge=0, le=255, description="POS value for closed on the cup")
    speed: int = Field(128, ge=0, le=255)
    force: int = Field(64, ge=0, le=255)
    timeout_s: float = Field(2.0, gt=0, le=30, description="s for a reply / for the fingers to stop")


class NoGripperConfig(ConfigModel):
    """No gripper (capture sweeps)."""

    kind: Literal["none"] = "none"


class ConnectionConfig(ConfigModel):
    host: Annotated[str, AfterValidator(check_host)] = Field(
        ..., min_length=1, description="controller IP address or host name (no port, nothing else)")
    controller: Literal["cb3", "e-series"] = Field(..., description="CB3 (125 Hz) or e-Series (500 Hz)")
    connect_timeout_s: float = Field(5.0, gt=0, le=120, description="s to wait for each interface to connect")
    reconnect_attempts: int = Field(3, ge=0, le=20, description="tries after a dropped connection")
    reconnect_backoff_s: float = Field(0.5, ge=0, le=10, description="s between reconnect tries")
    stale_cycles: int = Field(25, ge=2, le=1000,
                              description="controller cycles without a new receive timestamp that count as lost")

    @property
    def frequency(self) -> float:
        return CONTROLLER_HZ[self.controller]


class LimitsConfig(ConfigModel):
    """Our own limits, checked on the host before every command (tighter than the controller's). Every key must be
    given (no defaults: this is the arm's safety envelope). The lower bounds keep a placement finite: its deadlines
    (:class:`~place_safe.placement.config.PlacementConfig`: the 0.6 m ``max_travel`` within the 30 s
    ``descent_timeout``, the 0.1 m retreat within 6 s) and braking within the 50 mm near-surface band need at least
    20 mm/s and 0.1 m/s^2; a limit of 1e-9 m/s^2 was accepted and made a placement that never ends."""

    max_linear_speed: float = Field(..., ge=0.02, le=1.0,
                                    description="m/s, TCP (at least 0.02: slower, the 0.6 m max_travel of a "
                                                "descent outlasts its 30 s descent_timeout)")
    max_linear_accel: float = Field(..., ge=0.1, le=5.0,
                                    description="m/s^2, TCP (at least 0.1: a stop from the 50 mm/s near-surface "
                                                "speed then takes 12.5 mm, a quarter of the 50 mm near band)")
    max_angular_speed: float = Field(..., ge=0.05, le=3.2,
                                     description="rad/s, TCP orientation (at least 0.05: a 90 deg turn of the "
                                                 "tool in about 30 s)")
    max_angular_accel: float = Field(..., ge=0.1, le=20.0,
                                     description="rad/s^2 (at least 0.1: up to 0.5 rad/s within 5 s)")
    max_joint_speed: float = Field(..., ge=0.05, le=3.15,
                                   description="rad/s, leading joint of moveJ (at least 0.05: a quarter turn "
                                               "in about 30 s)")
    max_joint_accel: float = Field(..., ge=0.1, le=40.0,
                                   description="rad/s^2, leading joint of moveJ (at least 0.1: up to 1 rad/s "
                                               "within 10 s)")
    max_contact_force: float = Field(..., gt=0, le=500, description="N: our protective stop on the TCP force")
    workspace_min: tuple[Metres2, Metres2, Metres2] = Field(
        ..., description="m: lower corner of the TCP box (base frame, each -2..2)")
    workspace_max: tuple[Metres2, Metres2, Metres2] = Field(
        ..., description="m: upper corner of the TCP box (base frame, each -2..2)")
    min_descent_z: float = Field(..., ge=-2.0, le=2.0,
                                 description="m: deepest base-frame z a descent may bring the TCP to")
    surface_keepout: float = Field(..., ge=0.0, le=0.05,
                                   description="m: how far below the sensed surface the held object's bottom "
                                               "may be commanded (contact needs a few mm; the rest is keep-out)")

    @model_validator(mode="after")
    def _box(self) -> "LimitsConfig":
        if not all(lo < hi for lo, hi in zip(self.workspace_min, self.workspace_max)):
            raise ValueError("workspace_min must be below workspace_max on every axis")
        if not self.workspace_min[2] <= self.min_descent_z < self.workspace_max[2]:
            raise ValueError("min_descent_z must lie inside the workspace box's z range")
        return self


class FrameConfig(ConfigModel):
    """A frame on the flange; both keys must be given (a mount's tilt left out was read as none)."""

    xyz: tuple[ToolMetres, ToolMetres, ToolMetres] = Field(
        ..., description="m, translation in the flange frame (each -1..1)")
    rpy: tuple[Angle, Angle, Angle] = Field(..., description="rad, fixed-axis roll-pitch-yaw (each -2 pi..2 pi)")

    def matrix(self) -> np.ndarray:
        from scipy.spatial.transform import Rotation

        T = np.eye(4)
        T[:3, :3] = Rotation.from_euler("xyz", self.rpy).as_matrix()
        T[:3, 3] = self.xyz
        return T

    @classmethod
    def from_matrix(cls, T: np.ndarray) -> "FrameConfig":
        from scipy.spatial.transform import Rotation

        T = np.asarray(T, dtype=float)
        return cls(xyz=tuple(float(v) for v in T[:3, 3]),
                   rpy=tuple(float(v) for v in Rotation.from_matrix(T[:3, :3]).as_euler("xyz")))


class ToolConfig(ConfigModel):
    """Frames on the flange: TCP, TMF8820 (+z optical axis), held cup (origin at its bottom, +z up out of it), and
    the payload sent to the controller. All must be given: none has a default."""

    tcp: FrameConfig = Field(..., description="the TCP, between the fingertips")
    sensor: FrameConfig = Field(..., description="the TMF8820 mount (calibrate-mount fits it)")
    cup: FrameConfig = Field(..., description="the held cup, origin at its bottom")
    payload_kg: float = Field(..., ge=0, le=5.0, description="kg: gripper + sensor + cup (UR5 payload 5 kg)")
    payload_cog: tuple[ToolMetres, ToolMetres, ToolMetres] = Field(
        ..., description="m, centre of gravity in the flange frame (each -1..1)")
    mount_fit: dict | None = Field(None, description="written by calibrate-mount: residuals and uncertainty")

    def frames(self):
        """The :class:`place_safe.robot.tool.ToolFrames` of this tool."""
        return ToolFrames(self.tcp.matrix(), self.sensor.matrix(), self.cup.matrix())


class URConfig(ConfigModel):
    """One UR5: connection, limits, watchdog, gripper, tool. What a file must give and what defaults (``name``,
    ``watchdog_hz``, connection timeouts and retries, gripper settle time, ``[motion]``, ``[contact]``): the module
    docstring; a missing table or key is one line naming all of them (:func:`missing_keys`)."""

    name: str = "ur5"
    connection: ConnectionConfig
    limits: LimitsConfig
    watchdog_hz: float = Field(10.0, ge=1, le=500,
                               description="Hz: minimum rate of host updates before the controller stops the arm")
    gripper: DigitalGripperConfig | RobotiqGripperConfig | NoGripperConfig = Field(..., discriminator="kind")
    tool: ToolConfig
    motion: "MotionConfig" = Field(default_factory=lambda: MotionConfig())
    contact: "ContactConfig" = Field(default_factory=lambda: ContactConfig())

    @model_validator(mode="before")
    @classmethod
    def _complete(cls, data):
        """Every table and key without a default present, or one line naming all that are missing."""
        missing = missing_keys(cls, data)
        if missing:
            raise ValueError(f"missing {', '.join(missing)} (a robot file gives its controller, limits, gripper "
                             "wiring, payload and tool frames itself, none from a default: see robots/ur5/real.toml)")
        return data

    @model_validator(mode="after")
    def _stops(self) -> "URConfig":
        """The hardest stop is no softer than an ordinary one: the driver brakes every stop at most at
        ``emergency_decel`` (``rtde_robot._stop_motion``), so below ``max_linear_accel`` a stop the placement plans at
        ``max_linear_accel`` would brake softer and run past where it was planned to end."""
        e, a = self.motion.emergency_decel, self.limits.max_linear_accel
        if e < a:
            raise ValueError(f"motion.emergency_decel ({e:g} m/s^2) must be at least limits.max_linear_accel "
                             f"({a:g} m/s^2): the obstacle and fault stop may not be softer than an ordinary stop")
        return self

    @classmethod
    def load(cls, path: str | Path) -> "URConfig":
        """Read and validate a robot TOML/JSON file; one-line ConfigError otherwise."""
        return load_config(cls, path, "robot config")

    def to_toml(self, like: str | Path | None = None) -> str:
        """The configuration as TOML text (for writing back a fitted mount or a measured noise).

        ``like``: the robot file this configuration was read from (or a copy of it). Its text is kept -- comments,
        order, spacing, quoting -- and only the values that differ from what it says are changed, added or removed
        (:func:`update_toml`). Without it, or when it is not TOML, every field is written in the model's order."""
        data = self.model_dump(mode="json", exclude_none=True)
        if like is not None and Path(like).suffix.lower() == ".toml":
            base = URConfig.load(like)
            text = update_toml(Path(like).read_text(encoding="utf-8"), base.model_dump(mode="json", exclude_none=True),
                               data)
            if text is not None and parse_config(URConfig, toml_reader().loads(text), f"robot config {like}") == self:
                return text
        return _toml(data)


# ------------------------------------------------------------------------------------------------
# motion near the surface, stop decelerations and the contact detector (issue 29)
# ------------------------------------------------------------------------------------------------
class MotionConfig(ConfigModel):
    """Speeds near the surface and stop decelerations (SI units).

    Defaults: ``near_surface_speed`` 0.05 m/s within ``near_surface_distance`` 0.05 m of the sensed surface --
    a careful collaborative approach; UR's collaborative speed limit for a tool near people is 50 mm/s
    (``shared/docs/ur5-rtde.md``), and at 50 mm/s the cup stops in 1.6 mm at 0.8 m/s^2. Every ordinary stop
    decelerates at most at ``limits.max_linear_accel``; a stop asked harder (an obstacle, a fault) is an
    emergency stop at most at ``emergency_decel`` 2.0 m/s^2: from 0.1 m/s it stops in 2.5 mm and 50 ms,
    well under UR's own stopL default of 10 m/s^2 that would slosh a full cup.
    """

    near_surface_speed: float = Field(0.05, ge=0.01, le=0.25,
                                      description="m/s: the fastest approach within near_surface_distance (at "
                                                  "least 0.01: the 50 mm near band in 5 s; slower, a descent "
                                                  "outlasts its deadline)")
    near_surface_distance: float = Field(0.05, ge=0, le=0.5,
                                         description="m of cup clearance above the sensed surface that counts as near")
    emergency_decel: float = Field(2.0, gt=0, le=10.0,
                                   description="m/s^2: the hardest stop (obstacle, fault), at least "
                                               "limits.max_linear_accel; ordinary stops use at most that")


class ContactConfig(ConfigModel):
    """The contact detector on the TCP force estimate (:mod:`place_safe.robot.contact_detector`); each unset
    value takes the controller's default (CB3 about 3.6 N per axis per cycle, e-Series about 1 N).
    ``place-safe bench robot --write`` measures ``noise_std`` on the arm at rest and writes it here."""

    noise_std: float | None = field_like(DetectorSettings, "noise_std", "N per axis per controller cycle at rest")
    window: int | None = field_like(DetectorSettings, "window", "controller cycles averaged")
    sigmas: float | None = field_like(DetectorSettings, "sigmas", "threshold in standard deviations of the average")
    persistence: int | None = field_like(DetectorSettings, "persistence", "consecutive cycles above the threshold")
    min_threshold: float | None = field_like(DetectorSettings, "min_threshold", "N: the least threshold")
    lateral_sigmas: float | None = field_like(DetectorSettings, "lateral_sigmas", "threshold factor for the vector norm")
    measured: dict | None = Field(None, description="written by place-safe bench robot: what it measured")

    def settings(self, controller: str):
        """The :class:`~place_safe.robot.contact_detector.DetectorSettings` for ``controller``."""
        return DetectorSettings.for_controller(
            controller, noise_std=self.noise_std, window=self.window, sigmas=self.sigmas,
            persistence=self.persistence, min_threshold=self.min_threshold, lateral_sigmas=self.lateral_sigmas)


URConfig.model_rebuild()


def _tables(annotation) -> list[type]:
    """The :class:`ConfigModel` classes a field holds (one, or the choices of a union), [] for a plain value."""
    import typing

    args = typing.get_args(annotation) if typing.get_origin(annotation) is not None else (annotation,)
    return [a for a in args if isinstance(a, type) and issubclass(a, ConfigModel)]


def _kinds(choices: list[type]) -> dict:
    """``kind`` value -> class for a union told apart by ``kind`` (the gripper)."""
    return {c.model_fields["kind"].default: c for c in choices if "kind" in c.model_fields}


def missing_keys(cls: type | None = None, data=None, prefix: str = "") -> list[str]:
    """The tables (``[tool.sensor]``) and keys (``tool.payload_kg``) without a default that ``data`` (a robot file's
    contents) lacks, in the model's order; a missing table is named with its missing sub-tables, not each of its
    keys. Values that are not tables, and a gripper of an unknown kind, are left to the model's own checks."""
    cls = URConfig if cls is None else cls
    if not isinstance(data, dict):
        return []
    out: list[str] = []
    for name, field in cls.model_fields.items():
        path = f"{prefix}{name}"
        choices = _tables(field.annotation)
        value = data.get(name, _MISSING)
        if value is _MISSING:
            if field.is_required():
                if choices:
                    out.append(f"[{path}]")
                    if len(choices) == 1:  # its sub-tables, whose keys the user copies with them
                        out += [m for m in missing_keys(choices[0], {}, path + ".") if m.startswith("[")]
                else:
                    out.append(path)
        elif isinstance(value, dict) and choices:
            if len(choices) == 1:
                out += missing_keys(choices[0], value, path + ".")
            elif "kind" not in value:
                out.append(f"{path}.kind")
            elif isinstance(value["kind"], str) and value["kind"] in _kinds(choices):
                out += missing_keys(_kinds(choices)[value["kind"]], value, path + ".")
    return out


def placement_config(robot: URConfig, base=None):
    """``base`` (a :class:`~place_safe.placement.config.PlacementConfig`, default its defaults) with the robot
    file's motion policy: the near-surface speed and distance, stops no harder than ``max_linear_accel`` and
    the obstacle stop no harder than ``emergency_decel``; and ``contact_latency`` from the robot's contact detector
    (:func:`~place_safe.robot.contact_detector.touch_latency` of the file's ``[contact]`` settings for its controller:
    CB3 48 ms, e-Series 14 ms, longer for an arm whose noise is set higher), or ``base``'s own value where it sets a
    longer one. A latency too long for the descent (no touch could then count as arrival: ``rules.contact_limit``
    below zero) is a ConfigError naming where it comes from. The detector raises its threshold at run time to the
    noise it measures at rest beyond the file's setting, and a placement loop then takes the robot's latency at that
    noise (:meth:`URRobot.contact_latency`) where it is longer; ``place-safe bench robot --write`` records an arm's
    noise."""
    base = base if base is not None else PlacementConfig()
    m, lim = robot.motion, robot.limits
    detector = touch_latency(robot.contact.settings(robot.connection.controller))
    # a placement file's own value stands where it is the more cautious (a file saved from the defaults holds the
    # CB3's 48 ms); never below what this arm's detector needs
    given = "contact_latency" in base.model_fields_set
    latency = max(base.contact_latency, detector) if given else detector
    descend = min(base.descend_speed, m.near_surface_speed)
    if base.cup_radius > 0 and not (base.cup_radius * math.tan(base.max_tilt) > descend * latency):
        if given and base.contact_latency >= detector:
            late = (f"the placement settings' contact_latency ({latency * 1e3:.0f} ms) is {descend * latency * 1e3:.1f} "
                    f"mm of travel at {descend * 1e3:.0f} mm/s")
        elif math.isfinite(latency):
            late = (f"the contact detector ({robot.connection.controller}, [contact]) needs {latency * 1e3:.0f} ms to "
                    f"see a {TOUCH_STEP:.0f} N touch, {descend * latency * 1e3:.1f} mm of travel at {descend * 1e3:.0f} "
                    "mm/s")
        else:
            late = (f"the contact detector ({robot.connection.controller}, [contact]) misses more than 1 in 20 "
                    f"{TOUCH_STEP:.0f} N touches for half a second, {descend * 0.5 * 1e3:.1f} mm of travel at "
                    f"{descend * 1e3:.0f} mm/s")
        mend = ("the placement settings' contact_latency" if given and base.contact_latency >= detector else
                "find why the arm's force estimate is this noisy ([contact] noise_std)")
        raise ConfigError(
            f"robot config: {late}, more than the {base.cup_radius * math.tan(base.max_tilt) * 1e3:.1f} mm a cup may "
            "stand on (cup_radius tan(max_tilt)): no touch could count as arrival; lower [motion] near_surface_speed "
            f"(the descent's speed), or {mend}")
    return base.replace(near_surface_speed=m.near_surface_speed, near_surface_distance=m.near_surface_distance,
                        accel=min(base.accel, lim.max_linear_accel),
                        obstacle_decel=min(base.obstacle_decel, m.emergency_decel),
                        descend_speed=descend, contact_latency=latency,
                        approach_speed=min(base.approach_speed, lim.max_linear_speed))


def packaged_config(name: str = "sim") -> Path:
    """Path of a packaged robot file: ``real`` or ``sim`` (``robots/ur5/<name>.toml``)."""
    return ur5_dir() / f"{name}.toml"


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(float(v)) if isinstance(v, float) else str(v)
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as a TOML value")


def _toml_string(s: str) -> str:
    """A TOML basic string: JSON's escapes, but characters beyond the BMP written as they are (JSON's surrogate
    pairs are not TOML) and DEL escaped (TOML, unlike JSON, forbids it raw)."""
    import json

    return json.dumps(s, ensure_ascii=False).replace("\x7f", "\\u007f")


def _toml_key(k) -> str:
    """A TOML key: bare when it is letters, digits, ``_`` and ``-`` only, else quoted (a key with a space or a dot,
    written bare, reads back as another key or not at all)."""
    import re

    k = str(k)
    return k if re.fullmatch(r"[A-Za-z0-9_-]+", k) else _toml_string(k)


def _toml(d: dict, prefix: str = "") -> str:
    """A minimal TOML writer for nested dicts of scalars and lists (tomllib reads, nothing writes)."""
    lines = [f"{_toml_key(k)} = {_toml_value(v)}" for k, v in d.items() if not isinstance(v, dict)]
    for k, v in d.items():
        if isinstance(v, dict):
            name = f"{prefix}{_toml_key(k)}"
            body = _toml(v, name + ".")
            lines.append(f"\n[{name}]\n{body}" if body.strip() else f"\n[{name}]")
    return "\n".join(lines).strip("\n") + "\n" if not prefix else "\n".join(lines)


_MISSING = object()


def update_toml(text: str, before: dict, after: dict) -> str | None:
    """``text``, a TOML file whose values (with defaults for what it leaves out) are ``before``, changed to say
    ``after``: only the keys whose values differ are set, added (in the table they belong to, made where the file
    has none) or removed, so the file's comments, order and layout stay (tomlkit). None when tomlkit is not installed
    or did not do it faithfully (the result is read back and compared with the same change made to the file's
    data); the caller then writes the whole table (:func:`_toml`)."""
    tomllib = toml_reader()
    try:
        import tomlkit

        expected = tomllib.loads(text)
        _update(expected, before, after, None)
        doc = tomlkit.parse(text)
        _update(doc, before, after, tomlkit)
        out = tomlkit.dumps(doc)
        return out if tomllib.loads(out) == expected else None
    except Exception:  # noqa: BLE001 - tomlkit missing or tripped on the file: the plain writer is always right
        return None


def _update(table, before: dict, after: dict, tomlkit) -> None:
    """Change ``table`` (a tomlkit container, or a plain dict when ``tomlkit`` is None) where ``after`` differs from
    ``before``, recursing into sub-tables; a sub-table the file does not have is made, with what differs only."""
    for key, new in after.items():
        old = before.get(key, _MISSING)
        if old == new:
            continue
        if isinstance(new, dict) and (isinstance(old, dict) or old is _MISSING):
            made = key not in table
            if made:
                table[key] = {} if tomlkit is None else tomlkit.table()
            _update(table[key], old if isinstance(old, dict) else {}, new, tomlkit)
            if made and tomlkit is not None:
                table[key].add(tomlkit.nl())  # a blank line before the next table
        else:
            table[key] = new
    for key in [k for k in before if k not in after and k in table]:
        del table[key]


__all__ = ["check_host", "update_toml", "missing_keys", "URConfig", "MotionConfig", "ContactConfig", "placement_config", "ConnectionConfig",
           "LimitsConfig", "ToolConfig", "FrameConfig", "DigitalGripperConfig", "RobotiqGripperConfig",
           "NoGripperConfig", "CONTROLLER_HZ", "packaged_config"]
