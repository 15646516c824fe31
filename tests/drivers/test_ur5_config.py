"""The robot file's TOML writer (place_safe/drivers/ur5/config.py): what it writes reads back as it was."""

from __future__ import annotations

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
