"""The simulated user's calibration: a level-table capture sweep, then ``place-safe calibrate`` on it.

Concept: the estimators in simulation must be calibrated the way a user calibrates a real sensor,
never handed the simulator's true parameters. :func:`capture_level_sweep` is a minimal stand-in
for a robot-driven capture: the simulated sensor (nominal or mismatched, see
:mod:`place_safe.sim.tof_mismatch`) on a free rig is placed over a level table at heights and
tilts a user would sweep, and one noisy frame with ground truth is taken at each pose (the rig
puts the sensor where the capture asks; there is no arm in this sweep). :func:`calibrate_sim`
writes the frames to a frame file and runs the ordinary ``place-safe calibrate`` command on it
(``--method diff``, which fits the ``peak`` section first, then ``--method proprietary``).

The packaged results, ``sim/sensors/calibration_<sensor>.json``, are what placements use by
default; ``place-safe scenarios calibrate`` regenerates them (deterministic for a seed).

Conventions: heights in metres from the sensor to the table along the vertical; tilts in radians
(sensor optical axis away from straight down), directions uniformly spread.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

#: Frames in the default sweep (the issue's user-style calibration used 48).
SWEEP_FRAMES = 48
#: m, sensor-to-table heights of the sweep (the placement works from 40 cm down to contact).
SWEEP_HEIGHTS = (0.05, 0.42)
#: rad, largest tilt of the sensor over the level table in the sweep.
SWEEP_MAX_TILT = math.radians(12.0)


def calibration_file(sensor: str = "nominal") -> Path:
    """Path of the packaged simulated calibration for the simulated sensor ``sensor``."""
    from place_safe.sim.tof import sensor_file

    return sensor_file(f"calibration_{sensor}.json")


def capture_level_sweep(sensor: str = "nominal", n: int = SWEEP_FRAMES, seed: int = 0) -> list:
    """``n`` noisy frames with ground truth of a level table, sensor at varied heights and tilts."""
    from scipy.spatial.transform import Rotation

    from place_safe.sim.scene import SceneConfig, build_scene
    from place_safe.sim.tof import ToFConfig
    from place_safe.sim.tof_mismatch import make_sensor

    cfg = SceneConfig()  # level table, sensor rig
    scene = build_scene(cfg)
    data = scene.make_data()
    tof = make_sensor(sensor, scene, data, ToFConfig(seed=seed))
    rng = np.random.default_rng(seed)
    top = cfg.table.height
    cx, cy = cfg.table.center
    down = Rotation.from_euler("xyz", cfg.rig_euler)
    frames = []
    tries = 0
    heights = np.linspace(*SWEEP_HEIGHTS, n)
    rng.shuffle(heights)
    for h in heights:
        while True:
            tries += 1
            if tries > 20 * n:
                raise RuntimeError("calibration sweep: too few poses see only the table")
            tilt = SWEEP_MAX_TILT * math.sqrt(rng.uniform())
            az = rng.uniform(0, 2 * math.pi)
            lean = Rotation.from_rotvec(tilt * np.array([math.cos(az), math.sin(az), 0.0]))
            R = (lean * down).as_matrix()
            pos = np.array([cx + rng.uniform(-0.1, 0.1), cy + rng.uniform(-0.1, 0.1), top + h])
            scene.set_sensor_pose(data, pos, R)
            data.time += 1.0 / 30.0  # the mismatched sensor warms up over the capture like a real one
            f = tof.measure()
            if f.truth is not None:
                frames.append(f)
                break
    return frames


def calibrate_sim(sensor: str = "nominal", output: str | Path | None = None, n: int = SWEEP_FRAMES,
                  seed: int = 0, frames_out: str | Path | None = None, quiet: bool = True) -> Path:
    """Capture a sweep and run ``place-safe calibrate`` (diff, then proprietary) on it; returns the file."""
    from place_safe.cli.app import main as cli_main
    from place_safe.io.frame_file import write_frames

    out = Path(output) if output is not None else calibration_file(sensor)
    frames = capture_level_sweep(sensor, n, seed)
    with tempfile.TemporaryDirectory() as tmp:
        ff = Path(frames_out) if frames_out is not None else Path(tmp) / f"sweep_{sensor}.json"
        write_frames(ff, frames)
        if out.exists():
            out.unlink()  # a fresh calibration, not an update of the old one
        q = ["--quiet"] if quiet else []
        for method in ("diff", "proprietary"):
            rc = cli_main(["calibrate", str(ff), "--method", method, "-o", str(out), *q])
            if rc != 0:
                raise RuntimeError(f"place-safe calibrate --method {method} failed on the simulated sweep ({rc})")
    return out


__all__ = ["capture_level_sweep", "calibrate_sim", "calibration_file", "SWEEP_FRAMES"]
