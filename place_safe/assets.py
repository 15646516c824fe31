"""Where the project's data folders are: robot descriptions, scenario files and simulated-sensor files.

The repository keeps them at its top level, beside the package, for users to read and edit:

* ``robots/``    robot descriptions (``robots/ur5/config.json`` and the MJCF / URDF generated from it,
  robot files ``sim.toml`` / ``real.toml``);
* ``scenarios/`` scenario files (``*.json`` scenes, the regression set ``set/*.toml``);
* ``sim/``       the simulation's assets (``sim/sensors/*.json``: simulated-unit and calibration files) and
  its entry-point scripts.

They hold no Python that the library imports: the import graph is what ``place_safe/`` shows. A source
checkout or an editable install (the README's) finds them beside the package; a wheel installs them under
``<prefix>/share/place-safe/`` (``[tool.setuptools.data-files]`` in ``pyproject.toml``), which is searched next.
Set ``PLACE_SAFE_DATA`` to a folder holding the three to use another copy.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

FOLDERS = ("robots", "scenarios", "sim")
"""The data folders, by their names at the repository's top level."""

_ENV = "PLACE_SAFE_DATA"


def _candidates() -> list[Path]:
    roots = []
    if os.environ.get(_ENV):
        roots.append(Path(os.environ[_ENV]).expanduser())
    roots.append(Path(__file__).resolve().parents[1])
    roots.append(Path(sys.prefix) / "share" / "place-safe")
    return roots


def data_root() -> Path:
    """The folder that holds ``robots/``, ``scenarios/`` and ``sim/`` (first of: ``$PLACE_SAFE_DATA``, the source
    checkout, ``<prefix>/share/place-safe``).

    Raises:
        FileNotFoundError: none of them holds the data folders (a one-line message naming where it looked).
    """
    tried = _candidates()
    for root in tried:
        if all((root / name).is_dir() for name in FOLDERS):
            return root
    raise FileNotFoundError(
        "place_safe's data folders (robots/, scenarios/, sim/) were not found in "
        + ", ".join(str(p) for p in tried) + f"; set {_ENV} to the folder that holds them")


def robots_dir() -> Path:
    """``robots/``: robot descriptions and robot files."""
    return data_root() / "robots"


def scenarios_dir() -> Path:
    """``scenarios/``: scenario files and the regression set."""
    return data_root() / "scenarios"


def sim_sensors_dir() -> Path:
    """``sim/sensors/``: simulated-unit forward parameters and the calibrations made for them."""
    return data_root() / "sim" / "sensors"


__all__ = ["FOLDERS", "data_root", "robots_dir", "scenarios_dir", "sim_sensors_dir"]
