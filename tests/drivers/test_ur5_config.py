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
