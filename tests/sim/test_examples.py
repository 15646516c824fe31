"""The examples run (CI runs them through this test)."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.mark.slow
def test_simulated_placement_example_refuses_the_tilted_table(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["simulated_placement.py", "place_tilted"])
    with pytest.raises(SystemExit) as done:
        runpy.run_path(str(EXAMPLES / "simulated_placement.py"), run_name="__main__")
    assert done.value.code == 0
    out = capsys.readouterr().out
    assert out.startswith("refused: surface tilted")
