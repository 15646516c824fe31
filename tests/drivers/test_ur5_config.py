"""The robot file's TOML writer (place_safe/drivers/ur5/config.py): what it writes reads back as it was."""

from __future__ import annotations

import difflib
import tomllib

from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.drivers.ur5 import URConfig, packaged_config
from place_safe.drivers.ur5.config import _toml

_keys = st.text(st.characters(blacklist_categories=("Cs",)), min_size=1, max_size=12)
_scalars = st.one_of(st.booleans(), st.integers(-10**6, 10**6), st.floats(allow_nan=False, allow_infinity=False),
                     st.text(max_size=20))
_tables = st.recursive(st.dictionaries(_keys, st.one_of(_scalars, st.lists(_scalars, max_size=4)), max_size=4),
                       lambda inner: st.dictionaries(_keys, inner, min_size=1, max_size=3), max_leaves=12)


@settings(max_examples=200, deadline=None)
@given(_tables)
def test_any_nested_table_reads_back_as_written(d):
    """Keys with spaces, dots, quotes or other characters are quoted (a key with a space was written bare, and
    the file no longer read)."""
    assert tomllib.loads(_toml(d)) == d


def test_a_measured_section_with_spaced_keys_survives_a_write_and_a_load(tmp_path):
    cfg = URConfig.load(packaged_config("sim"))
    cfg.contact.measured = {"noise std (N)": 3.6, "at.rest": {"cycles seen": 500}}
    p = tmp_path / "robot.toml"
    p.write_text(cfg.to_toml())
    assert URConfig.load(p).contact.measured == cfg.contact.measured


def _comments(text: str) -> list[str]:
    return [line[line.index("#"):] for line in text.splitlines() if "#" in line]


def test_writing_into_a_users_robot_file_keeps_its_comments_and_layout(tmp_path):
    """The writer rewrote the whole file from the model: the user's comments went, and every default was spelled
    out. Now only the values that changed are set (a fitted mount, a measured noise), in place."""
    from place_safe.drivers.ur5.config import FrameConfig

    mine = tmp_path / "mine.toml"
    original = packaged_config("real").read_text()
    mine.write_text(original.replace('name = "ur5-lab"', 'name = "ur5-lab"  # my arm, bay 3'))
    cfg = URConfig.load(mine)
    cfg.tool.sensor = FrameConfig(xyz=(0.0712, 0.0, 0.1093), rpy=(0.0, 0.01, 0.0))
    cfg.tool.mount_fit = {"capture": "level.jsonl", "frames": 22, "sigma_xyz_mm": [0.1, -1.0, 0.2]}
    cfg.contact.noise_std = 3.61
    text = cfg.to_toml(like=mine)
    assert _comments(text) == _comments(mine.read_text()) and "# my arm, bay 3" in text  # every comment, in order
    diff = list(difflib.ndiff(mine.read_text().splitlines(), text.splitlines()))
    assert [d[2:] for d in diff if d.startswith("- ")] == ["xyz = [0.07, 0.0, 0.11]", "rpy = [0.0, 0.0, 0.0]"]
    assert [d[2:] for d in diff if d.startswith("+ ")] == [
        "xyz = [0.0712, 0.0, 0.1093]", "rpy = [0.0, 0.01, 0.0]", "", "[tool.mount_fit]", 'capture = "level.jsonl"',
        "frames = 22", "sigma_xyz_mm = [0.1, -1.0, 0.2]", "noise_std = 3.61"]
    p = tmp_path / "written.toml"
    p.write_text(text)
    assert URConfig.load(p) == cfg
    assert cfg.to_toml(like=p) == text  # nothing changed: nothing rewritten


def test_a_robot_file_that_is_not_toml_is_written_whole(tmp_path):
    import json

    cfg = URConfig.load(packaged_config("sim"))
    p = tmp_path / "robot.json"
    p.write_text(json.dumps(cfg.model_dump(mode="json", exclude_none=True)))
    cfg.contact.noise_std = 2.0
    assert cfg.to_toml(like=p) == cfg.to_toml()


@settings(max_examples=200, deadline=None)
@given(_tables, _tables)
def test_an_update_reads_back_as_the_new_values_or_is_left_to_the_plain_writer(before, after):
    """:func:`update_toml` changes a file written from ``before`` into one that reads as ``after``; where tomlkit
    cannot do that faithfully (its result is read back) it returns None and the caller writes the whole table."""
    from place_safe.drivers.ur5.config import update_toml

    text = update_toml(_toml(before), before, after)
    assert text is None or tomllib.loads(text) == after


def test_an_update_of_ordinary_keys_is_made_in_place():
    from place_safe.drivers.ur5.config import update_toml

    before = {"a": 1, "t": {"x": [0.5, 1.0], "keep": "yes"}, "gone": True}
    after = {"a": 1, "t": {"x": [0.25, 1.0], "keep": "yes", "new": {"noise std (N)": 3.5}}}
    text = update_toml("# top\n" + _toml(before).replace("a = 1", "a = 1  # one"), before, after)
    assert text is not None and "# top" in text and "a = 1  # one" in text
    assert tomllib.loads(text) == after


# ------------------------------------------------------------------------------------------------
# an incomplete robot file (adversarial finding 5): nothing the arm's safety rests on is taken from a default
# ------------------------------------------------------------------------------------------------
import pytest  # noqa: E402

from place_safe.exceptions import ConfigError  # noqa: E402


def _real() -> dict:
    return tomllib.loads(packaged_config("real").read_text())


def _without(data: dict, path: str) -> dict:
    *tables, key = path.split(".")
    t = data
    for name in tables:
        t = t[name]
    del t[key]
    return data


@pytest.mark.parametrize("path, named", [
    ("tool.sensor", "[tool.sensor]"), ("tool.sensor.rpy", "tool.sensor.rpy"), ("tool.sensor.xyz", "tool.sensor.xyz"),
    ("tool.payload_kg", "tool.payload_kg"), ("tool.payload_cog", "tool.payload_cog"),
    ("tool.tcp", "[tool.tcp]"), ("tool.cup.xyz", "tool.cup.xyz"),
    ("tool", "[tool], [tool.tcp], [tool.sensor], [tool.cup]"),
    ("gripper", "[gripper]"), ("gripper.kind", "gripper.kind"), ("gripper.output", "gripper.output"),
    ("gripper.open_level", "gripper.open_level"), ("gripper.tool_output", "gripper.tool_output"),
    ("limits", "[limits]"), ("limits.max_linear_speed", "limits.max_linear_speed"),
    ("limits.workspace_min", "limits.workspace_min"), ("limits.min_descent_z", "limits.min_descent_z"),
    ("limits.max_contact_force", "limits.max_contact_force"), ("limits.surface_keepout", "limits.surface_keepout"),
    ("connection.controller", "connection.controller"), ("connection", "[connection]"),
])
def test_a_robot_file_without_a_table_or_key_the_arm_needs_is_one_line_naming_it(tmp_path, path, named):
    """A file missing [tool], [tool.sensor], the payload, ... was read with the built-in mount, payload and limits
    in their place: every plane put at a wrong tilt and height, a wrong payload sent to the controller. Now it is
    refused with one line naming the file and everything missing."""
    p = tmp_path / "mine.toml"
    p.write_text(_toml(_without(_real(), path)))
    with pytest.raises(ConfigError) as exc:
        URConfig.load(p)
    msg = str(exc.value)
    assert "\n" not in msg and str(p) in msg and f"missing {named} (" in msg, msg


def test_a_robot_file_cut_short_is_refused_naming_what_it_lacks(tmp_path, capsys):
    """real.toml cut in half (inside [limits]) read as a whole file with the default gripper, payload, tool frames
    and motion; on the command line it got as far as connecting to the arm. Now: exit 2, one line."""
    from place_safe.cli.app import main

    text = packaged_config("real").read_text()
    cut = tmp_path / "cut.toml"
    cut.write_text(text[:text.index("[gripper]")])
    with pytest.raises(ConfigError, match=r"missing \[gripper\], \[tool\], \[tool\.tcp\], \[tool\.sensor\], "
                                          r"\[tool\.cup\] \("):
        URConfig.load(cut)
    for argv in (["place", "--robot", str(cut), "--sensor", "file:x.json", "--dry-run", "--uncalibrated"],
                 ["capture", "--robot", str(cut), "--sensor", "file:x.json", "--table-height", "0", "--dry-run",
                  "-o", str(tmp_path / "c.jsonl")],
                 ["bench", "robot", "--robot", str(cut), "--seconds", "1"],
                 ["calibrate-mount", str(tmp_path / "none.json"), "--robot", str(cut)]):
        assert main(argv) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and str(cut) in err[0] and "missing [gripper]" in err[0], (argv, err)


def test_what_a_robot_file_may_leave_out_takes_the_documented_defaults(tmp_path):
    """Only the connection's timeouts and retries, the watchdog, the name, the gripper's settle time (and the
    Robotiq URCap's settings), [motion], [contact] and the mount fit's record may be left out."""
    data = _real()
    for path in ("name", "watchdog_hz", "connection.connect_timeout_s", "connection.reconnect_attempts",
                 "connection.reconnect_backoff_s", "connection.stale_cycles", "gripper.settle_s", "motion"):
        _without(data, path)
    data.pop("contact", None)
    p = tmp_path / "lean.toml"
    p.write_text(_toml(data))
    cfg = URConfig.load(p)
    assert (cfg.name, cfg.watchdog_hz, cfg.connection.connect_timeout_s, cfg.gripper.settle_s) == ("ur5", 10.0, 5.0, 0.3)
    assert (cfg.motion.near_surface_speed, cfg.motion.near_surface_distance, cfg.motion.emergency_decel) == \
        (0.05, 0.05, 2.0)
    assert cfg.contact.noise_std is None and cfg.tool.mount_fit is None


def test_the_hardest_stop_may_not_be_softer_than_an_ordinary_one(tmp_path):
    """emergency_decel 0.1 below max_linear_accel 0.5 was accepted: the driver caps every stop at emergency_decel,
    so a stop the placement planned at 0.5 m/s^2 would brake at 0.1 and run five times as far."""
    data = _real()
    data["motion"]["emergency_decel"] = 0.1
    p = tmp_path / "soft.toml"
    p.write_text(_toml(data))
    with pytest.raises(ConfigError, match=r"soft\.toml: motion\.emergency_decel \(0\.1 m/s\^2\) must be at least "
                                          r"limits\.max_linear_accel \(0\.5 m/s\^2\)"):
        URConfig.load(p)
    data["motion"]["emergency_decel"] = 0.5  # equal is allowed: every stop at one deceleration
    p.write_text(_toml(data))
    assert URConfig.load(p).motion.emergency_decel == 0.5


@pytest.mark.parametrize("path, value, floor", [
    ("limits.max_linear_accel", 1e-9, "0.1 <= value"), ("limits.max_linear_speed", 1e-9, "0.02 <= value"),
    ("limits.max_angular_speed", 1e-9, "0.05 <= value"), ("limits.max_angular_accel", 1e-9, "0.1 <= value"),
    ("limits.max_joint_speed", 1e-9, "0.05 <= value"), ("limits.max_joint_accel", 1e-9, "0.1 <= value"),
    ("motion.near_surface_speed", 1e-9, "0.01 <= value"),
])
def test_speeds_and_accelerations_have_physical_floors(tmp_path, path, value, floor):
    """max_linear_accel = 1e-9 m/s^2 was accepted: a placement planned with it never ends."""
    data = _real()
    table, key = path.split(".")
    data[table][key] = value
    p = tmp_path / "slow.toml"
    p.write_text(_toml(data))
    with pytest.raises(ConfigError, match=rf"{path}: .*\(expected {floor}"):
        URConfig.load(p)


def test_every_packaged_and_written_robot_file_is_complete(tmp_path):
    """The packaged files, and what to_toml writes from them (calibrate-mount --write, bench robot --write), read."""
    for name in ("real", "sim"):
        cfg = URConfig.load(packaged_config(name))
        p = tmp_path / f"{name}.toml"
        p.write_text(cfg.to_toml())
        assert URConfig.load(p) == cfg
        p.write_text(cfg.to_toml(like=packaged_config(name)))
        assert URConfig.load(p) == cfg


def _with(cfg: URConfig, controller: str | None = None, noise: float | None = None) -> URConfig:
    if controller is not None:
        cfg = cfg.model_copy(update={"connection": cfg.connection.model_copy(update={"controller": controller})})
    if noise is not None:
        cfg = cfg.model_copy(update={"contact": cfg.contact.model_copy(update={"noise_std": noise})})
    return cfg


def test_the_placement_reads_a_touch_as_late_as_the_robots_own_detector_does():
    """``contact_latency`` (how far below a touch the cup is when the touch is read) comes from the robot file's
    contact detector unless the placement settings give it: the CB3's 48 ms, the e-Series' 14 ms, so an e-Series arm
    counts a touch up to 2.7 mm above the sensed surface as arrival (1.9 mm on a CB3); a placement file's own value
    stands where it is longer (a file saved from the defaults holds 48 ms), never below the detector's."""
    import math

    from place_safe.drivers.ur5.config import placement_config
    from place_safe.placement.config import PlacementConfig
    from place_safe.placement.rules import contact_limit

    cb3 = URConfig.load(packaged_config("sim"))
    assert cb3.connection.controller == "cb3"
    assert placement_config(cb3).contact_latency == 0.048
    e = placement_config(_with(cb3, controller="e-series"))
    assert e.contact_latency == 0.014
    assert math.isclose(contact_limit(e), e.cup_radius * math.tan(e.max_tilt) - e.descend_speed * 0.014)
    assert contact_limit(e) > contact_limit(placement_config(cb3)) + 0.0008
    e_series = _with(cb3, controller="e-series")
    assert placement_config(e_series, PlacementConfig(contact_latency=0.05)).contact_latency == 0.05
    assert placement_config(e_series, PlacementConfig(contact_latency=0.005)).contact_latency == 0.014
    assert placement_config(e_series, PlacementConfig().replace(descend_speed=0.02)).contact_latency == 0.048
    assert placement_config(cb3, PlacementConfig(cup_radius=0.0)).contact_latency == 0.048  # no tilt bound, no error


def test_a_detector_too_slow_for_the_descent_is_one_line_naming_it():
    """A CB3 whose force noise was measured at 6 N per axis cannot see a 10 N touch for a third of a second, 8.6 mm
    of descent: no touch could count as arrival. Building the placement says so in one line and how to mend it."""
    import pytest

    from place_safe.drivers.ur5.config import placement_config
    from place_safe.exceptions import ConfigError
    from place_safe.placement.config import PlacementConfig

    with pytest.raises(ConfigError, match=r"contact detector \(cb3.*ms to see a 10 N touch.*near_surface_speed") as e:
        placement_config(_with(URConfig.load(packaged_config("sim")), noise=6.0))
    assert "\n" not in str(e.value)
    with pytest.raises(ConfigError, match=r"contact detector \(cb3.*misses more than 1 in 20 10 N touches") as e:
        placement_config(_with(URConfig.load(packaged_config("sim")), noise=20.0))  # a 41 N threshold
    assert "\n" not in str(e.value) and "nan" not in str(e.value)
    with pytest.raises(ConfigError, match=r"placement settings' contact_latency \(500 ms\).*or the placement") as e:
        placement_config(URConfig.load(packaged_config("sim")), PlacementConfig(contact_latency=0.5))
