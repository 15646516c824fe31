"""The public face: the names a task script needs come from ``place_safe`` itself, loaded on first use.

``import place_safe`` stays light (no torch, MuJoCo, ur_rtde, smbus2 or rerun until a name that needs them is
used); every exported name resolves; the examples and the README's task scripts import only from
``place_safe`` (the tree behind it may move without breaking a user's script).
"""

from __future__ import annotations

import ast
import re
import subprocess
import sys
from pathlib import Path

import pytest

import place_safe

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "mujoco", "rtde_control", "rtde_receive", "rtde_io", "smbus2", "rerun", "scipy")


def test_import_place_safe_is_light():
    code = ("import sys, place_safe; heavy = %r; "
            "print(','.join(m for m in heavy if m in sys.modules))" % (HEAVY,))
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.strip() == ""


def test_the_task_script_names_are_exported():
    for name in ("PlacementLoop", "PlacementConfig", "make_estimator", "Calibration", "open_source", "URRobot",
                 "URConfig", "placement_config", "sim_world", "simulated_calibration", "SensorPipeline"):
        assert name in place_safe.__all__ and name in dir(place_safe)


@pytest.mark.slow
def test_every_exported_name_resolves():
    pytest.importorskip("mujoco")
    for name in place_safe.__all__:
        assert getattr(place_safe, name) is not None, name
    with pytest.raises(AttributeError, match="no attribute 'nothing_here'"):
        place_safe.nothing_here  # noqa: B018


def _project_imports(tree: ast.AST) -> list[str]:
    """Modules below ``place_safe`` that the code imports (``place_safe`` itself is the public face)."""
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("place_safe."):
            out.append(node.module)
        elif isinstance(node, ast.Import):
            out += [a.name for a in node.names if a.name.startswith("place_safe.")]
    return out


@pytest.mark.parametrize("path", sorted((ROOT / "examples").glob("*.py")), ids=lambda p: p.name)
def test_the_examples_import_only_from_place_safe(path):
    assert _project_imports(ast.parse(path.read_text(encoding="utf-8"))) == []


def test_the_readme_task_scripts_import_only_from_place_safe():
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / "README.md").read_text(encoding="utf-8"), re.S)
    assert len(blocks) >= 2  # the MuJoCo and the real-arm script
    for code in blocks:
        tree = ast.parse(code)
        assert _project_imports(tree) == []
        assert any(isinstance(n, ast.ImportFrom) and n.module == "place_safe" for n in ast.walk(tree))
