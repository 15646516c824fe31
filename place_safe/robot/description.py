"""The robot descriptions in ``robots/`` (found through :mod:`place_safe.assets`).

``robots/ur5/config.json`` is the single source of truth for the UR5 + gripper + TMF8820 mount + held cup;
``robots/ur5/ur5.xml`` (MuJoCo MJCF) and ``robots/ur5/ur5.urdf`` are generated from it by
``python -m place_safe.robot.model_generator``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from place_safe.assets import robots_dir


def ur5_dir() -> Path:
    """Directory holding the UR5 model files (``robots/ur5``)."""
    return robots_dir() / "ur5"


def ur5_mjcf_path() -> Path:
    """Path of the generated MJCF (arm on a base body at the world origin, gripper, sensor site, cup)."""
    return ur5_dir() / "ur5.xml"


def ur5_urdf_path() -> Path:
    """Path of the generated URDF (links ``flange``, ``tcp``, ``tof_sensor``, ``cup`` fixed to the flange)."""
    return ur5_dir() / "ur5.urdf"


def ur5_config_path() -> Path:
    """Path of ``config.json``, the source of truth for both model files."""
    return ur5_dir() / "config.json"


def ur5_config() -> dict[str, Any]:
    """The parsed ``config.json`` (a fresh dict on every call)."""
    with open(ur5_config_path(), encoding="utf-8") as fh:
        return json.load(fh)


__all__ = ["ur5_dir", "ur5_mjcf_path", "ur5_urdf_path", "ur5_config_path", "ur5_config"]
