"""place_safe: put a held object down safely, sensing the surface with a TMF8820's transient histograms.

The names a task script needs are importable from here (each loaded on first use, so ``import place_safe``
stays light and needs neither MuJoCo nor ur_rtde; a name whose extra is not installed fails when it is used)::

    from place_safe import PlacementLoop, PlacementConfig, Calibration, make_estimator, ToolFrames
    from place_safe import open_source, URRobot, URConfig, placement_config     # the real arm ([hw] extra)
    from place_safe import sim_world, simulated_calibration                      # MuJoCo ([sim] extra)

Flow: a :class:`FrameSource` (sensor driver, emulator, simulated sensor or file) gives :class:`Frame` s;
an estimator (:func:`make_estimator`: ``diff``, ``peak``, ``proprietary``) turns each into a plane; a
:class:`PlaneFilter` fuses them in the robot's base frame; :class:`PlacementMachine` decides; and
:class:`PlacementLoop` runs all of it against a :class:`Robot` every control tick.

Conventions: SI units inside (metres, radians, seconds); a plane is ``n . x = d`` in the sensor frame
with unit normal ``n`` pointing away from the sensor (``n_z > 0``) and ``d > 0`` the perpendicular
distance. Degrees appear only at the command line and in reports.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: public name -> module that defines it
_EXPORTS = {
    "Frame": "place_safe.sensor.frame",
    "Plane": "place_safe.geometry",
    "FrameSource": "place_safe.io.source",
    "FileReplaySource": "place_safe.io.replay",
    "load_frames": "place_safe.io.frame_file",
    "write_frames": "place_safe.io.frame_file",
    "iter_frames": "place_safe.io.frame_file",
    "Estimator": "place_safe.recovery.estimator",
    "PlaneEstimate": "place_safe.recovery.estimator",
    "make_estimator": "place_safe.recovery",
    "METHODS": "place_safe.recovery",
    "Calibration": "place_safe.calibration",
    "PlaneFilter": "place_safe.fusion.plane_filter",
    "FusedPlane": "place_safe.fusion.plane_filter",
    "PlacementConfig": "place_safe.placement.config",
    "PlacementMachine": "place_safe.placement.machine",
    "PlacementLoop": "place_safe.placement.loop",
    "LoopResult": "place_safe.placement.loop",
    "Robot": "place_safe.robot.interface",
    "RobotLimits": "place_safe.robot.interface",
    "ToolFrames": "place_safe.robot.tool",
    "SensorPipeline": "place_safe.io.pipeline",
    "open_source": "place_safe.sources",
    "URRobot": "place_safe.drivers.ur5.rtde_robot",
    "URConfig": "place_safe.drivers.ur5.config",
    "placement_config": "place_safe.drivers.ur5.config",
    "sim_world": "place_safe.sim.world",
    "simulated_calibration": "place_safe.sim.tof",
    "PlaceSafeError": "place_safe.exceptions",
    "FrameError": "place_safe.exceptions",
    "CalibrationError": "place_safe.exceptions",
    "ConfigError": "place_safe.exceptions",
    "NoPlaneError": "place_safe.exceptions",
    "SensorError": "place_safe.exceptions",
    "SensorTimeout": "place_safe.exceptions",
    "RobotFault": "place_safe.exceptions",
}

__all__ = ["__version__", *_EXPORTS]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'place_safe' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
