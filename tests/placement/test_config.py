"""Placement settings a file may not hold (``PlacementConfig.check_file_settings``)."""

from __future__ import annotations

import pytest

from place_safe.exceptions import ConfigError
from place_safe.placement.config import PlacementConfig
from place_safe.sim.scenario import load_scenario


def test_a_placement_file_may_not_turn_the_footprint_check_off(tmp_path):
    """``footprint_frames = 0`` (no landing-footprint rule) is for test doubles set in code; from a file it is one
    line naming the file and the field. An adversarial review's scenario with it released a cup over a table edge,
    where it tipped (session 89)."""
    assert PlacementConfig(footprint_frames=0).footprint_frames == 0  # in code: as before
    path = tmp_path / "p.json"
    PlacementConfig(footprint_frames=0).save(path)
    with pytest.raises(ConfigError) as err:
        PlacementConfig.load(path)
    assert str(path) in str(err.value) and "footprint_frames" in str(err.value) and "\n" not in str(err.value)
    PlacementConfig(footprint_frames=1).save(path)
    assert PlacementConfig.load(path).footprint_frames == 1


def test_a_scenario_may_not_turn_the_footprint_check_off(tmp_path):
    from pathlib import Path

    base = (Path(__file__).resolve().parents[2] / "scenarios" / "set" / "edge_under_cup.toml").read_text()
    path = tmp_path / "fp0.toml"
    path.write_text(base + "\n[placement]\nfootprint_frames = 0\n")
    with pytest.raises(ValueError, match="footprint_frames: 0 turns the landing-footprint check off"):
        load_scenario(path).placement_config()
