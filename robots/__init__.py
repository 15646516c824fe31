"""Robot description files shipped with place_safe (package data, found after a plain ``pip install .``).

``ur5/config.json`` is the single source of truth for the UR5 + gripper + TMF8820 mount + held cup;
``ur5/ur5.xml`` (MuJoCo MJCF) and ``ur5/ur5.urdf`` are generated from it by
``python -m place_safe.robots.ur5.generate``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

_UR5_DIR = Path(__file__).resolve().parent / "ur5"


def ur5_dir() -> Path:
    """Directory holding the UR5 model files."""
    return _UR5_DIR


def ur5_mjcf_path() -> Path:
    """Path of the generated MJCF (arm on a base body at the world origin, gripper, sensor site, cup)."""
    return _UR5_DIR / "ur5.xml"


def ur5_urdf_path() -> Path:
    """Path of the generated URDF (links ``flange``, ``tcp``, ``tof_sensor``, ``cup`` fixed to the flange)."""
    return _UR5_DIR / "ur5.urdf"


def ur5_config_path() -> Path:
    """Path of ``config.json``, the source of truth for both model files."""
    return _UR5_DIR / "config.json"


def ur5_config() -> dict[str, Any]:
    """The parsed ``config.json`` (a fresh dict on every call)."""
    with open(ur5_config_path(), encoding="utf-8") as fh:
        return json.load(fh)


__all__ = ["ur5_dir", "ur5_mjcf_path", "ur5_urdf_path", "ur5_config_path", "ur5_config"]
