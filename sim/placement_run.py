"""A whole placement in simulation: UR5 holding the cup, simulated TMF8820, estimator, fusion, state machine.

Concept: :func:`run_placement` wires the pieces the real application uses (an estimator from
:func:`place_safe.recovery.make_estimator`, :class:`place_safe.fusion.plane_filter.PlaneFilter`,
:class:`place_safe.placement.machine.PlacementMachine`) to the MuJoCo scene of a scenario file: a
:class:`~place_safe.sim.robot.SimRobot` starting at home holding the cup and a
:class:`~place_safe.sim.tof.SimToF` stepping in lockstep with it. It returns a
:class:`PlacementResult` (outcome, reason, what happened to the cup and the liquid, per-frame log).

Conventions
-----------
* The control loop runs every :data:`CONTROL_PERIOD` s of sim time (the UR CB3's 125 Hz): step the
  robot, read the newest sensor frame if one has arrived, estimate, fuse, tick the state machine,
  apply its command (speedL / stopL / open gripper).
* The placement itself is :class:`place_safe.placement.loop.PlacementLoop`, the same class a real-arm
  task script runs: the simulation only provides the robot (``SimRobot``), the frame source (``SimToF``,
  stamped on the simulation clock), and measures the outcome. Sensor and cup poses come from the TCP
  pose and the configured tool frames (``robots/ur5/config.json``), not from the simulator's bodies.
* ``method="diff"`` without a calibration uses a :class:`place_safe.calibration.Calibration` whose
  ``forward`` section is the simulated sensor's true parameters (``sim/sensors/tmf8820_real.json``):
  the estimator is calibrated to the sensor it looks through, as it would be after
  ``place-safe calibrate`` on the real one (``PlacementResult.calibration`` says which was used).
  Other methods use their built-in defaults unless a calibration is given.
* After the machine finishes, the simulation runs :data:`SETTLE_SECONDS` more so the released cup and
  liquid come to rest before the cup tilt and the spill are measured.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time as _time
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np

from place_safe.exceptions import PlaceSafeError, RobotFault
from place_safe.placement.loop import CONTROL_PERIOD, PlacementLoop
from place_safe.placement.machine import PlacementConfig

#: s of simulation after the machine finished, for the cup and liquid to settle.
SETTLE_SECONDS = 0.8


@dataclass
class PlacementResult:
    """What happened in one simulated placement (SI units; angles in rad)."""

    outcome: str  # "released", "refused" or "timeout"
    reason: str  # why it was released or refused (the deciding transition), or why it timed out
    scenario: str
    method: str
    calibration: str  # where the estimator's calibration came from
    final_phase: str
    cup_tilt: float  # rad, angle of the cup axis from vertical at the end
    cup_height: float  # m, cup bottom above the table top at its xy (world z difference, level-table sense)
    cup_held: bool  # the gripper still holds the cup at the end
    liquid_spilled: int  # liquid spheres outside the cup at the end
    liquid_total: int
    contact_force_peak: float  # N, largest contact force on gripper + held cup during the run
    sim_seconds: float
    wall_seconds: float
    frames: int  # frames read
    planes: int  # frames that gave a plane accepted by the filter
    transitions: list[dict] = field(default_factory=list)
    frame_log: list[dict] = field(default_factory=list)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def summary(self) -> str:
        """A few lines for the console."""
        lines = [f"placement {self.scenario} with {self.method}: {self.outcome.upper()} ({self.reason})",
                 f"  cup: {'held' if self.cup_held else 'released'}, tilt {math.degrees(self.cup_tilt):.1f} deg, "
                 f"bottom {self.cup_height * 1e3:.1f} mm above the table; liquid spilled "
                 f"{self.liquid_spilled}/{self.liquid_total}; peak contact force {self.contact_force_peak:.1f} N",
                 f"  {self.sim_seconds:.2f} s sim in {self.wall_seconds:.2f} s wall; {self.frames} frames, "
                 f"{self.planes} planes accepted; calibration: {self.calibration}"]
        for tr in self.transitions:
            lines.append(f"  t={tr['time']:6.3f} s  {tr['from']:>8} -> {tr['to']:<8} {tr['reason']}")
        return "\n".join(lines)


def scenario_path(name: str | Path) -> Path:
    """A scenario file: a path, or the name of a packaged one (``level_table`` or ``level_table.json``)."""
    p = Path(name)
    if p.is_file():
        return p
    stem = p.name if p.suffix == ".json" else p.name + ".json"
    packaged = Path(str(resources.files("place_safe.scenarios").joinpath(stem)))
    if packaged.is_file():
        return packaged
    raise FileNotFoundError(f"scenario {name} not found (neither a file nor a packaged scenario in scenarios/)")


def _simulated_sensor_calibration():
    from place_safe.calibration import Calibration

    from place_safe.sim.tof import sensor_file

    return Calibration({"forward": json.loads(sensor_file("tmf8820_real.json").read_text())})


def run_placement(scenario: Any = "place_level", method: str = "diff", calibration: Any = None,
                  seconds: float = 20.0, render: str | Path | None = None, seed: int = 0,
                  config: PlacementConfig | None = None, estimator_options: dict | None = None,
                  log_frames: bool = True) -> PlacementResult:
    """Simulate one placement (see module docstring).

    ``scenario``: a scenario file path or packaged name, or a :class:`~place_safe.sim.scene.SceneConfig`
    (the robot is always added). ``calibration``: a :class:`~place_safe.calibration.Calibration`, a path
    to one, or None (see module docstring). ``seconds``: sim-time limit. ``render``: PNG path of the
    scene at the end. ``seed``: the simulated sensor's noise seed. ``config``: the placement thresholds.
    """
    import mujoco

    from place_safe.calibration import Calibration
    from place_safe.recovery import make_estimator
    from place_safe.robots import ur5_config

    from place_safe.sim.robot import SimRobot
    from place_safe.sim.scene import SceneConfig, build_scene, load_scenario
    from place_safe.sim.tof import SimToF, ToFConfig

    wall0 = _time.perf_counter()
    if isinstance(scenario, SceneConfig):
        scene_cfg, sensor_kw, name = scenario, {}, "scene"
    else:
        path = scenario_path(scenario)
        scene_cfg, sensor_kw, _ = load_scenario(path)
        name = path.stem
    scene_cfg.with_robot = True
    if not (math.isfinite(seconds) and seconds > 0):
        raise ValueError(f"seconds must be a positive number of sim seconds; got {seconds!r}")
    if isinstance(calibration, (str, Path)):
        cal_note = str(calibration)
        calibration = Calibration.load(calibration)
    elif calibration is None and method == "diff":
        calibration, cal_note = _simulated_sensor_calibration(), "simulated sensor's true forward parameters"
    else:
        cal_note = "given" if calibration is not None else "built-in defaults"
    estimator = make_estimator(method, calibration, **(estimator_options or {}))
    cfg = config if config is not None else PlacementConfig()

    scene = build_scene(scene_cfg)
    robot = SimRobot(scene.model, mujoco.MjData(scene.model))
    tof = SimToF(scene, robot.data, ToFConfig(**{**sensor_kw, "seed": seed})).attach(robot)
    loop = PlacementLoop(robot, tof, estimator, tool=robot.tool, config=cfg, period=CONTROL_PERIOD,
                         log_frames=log_frames)
    res = loop.run(timeout=seconds)
    if robot.fault() is None:
        try:
            robot.stop(decel=cfg.accel)
            robot.step(SETTLE_SECONDS)
        except RobotFault:
            pass

    cup = robot.cup_pose()
    wb = robot.world_T_base()
    cup_w = wb @ cup
    tilt = float(np.arccos(np.clip(cup_w[2, 2], -1.0, 1.0)))
    n_w, p_w = scene.table_plane_world(robot.data)
    height = float(n_w @ (cup_w[:3, 3] - p_w))
    if render is not None:
        from place_safe.sim import render as _render

        _render.save_png(_render.render_image(scene, robot.data, tof), render)
    return PlacementResult(
        outcome=res.outcome, reason=res.reason, scenario=name, method=method, calibration=cal_note,
        final_phase=res.final_phase, cup_tilt=tilt, cup_height=height, cup_held=robot.holding(),
        liquid_spilled=robot.liquid_spilled(), liquid_total=int(ur5_config()["cup"]["liquid_count"]),
        contact_force_peak=res.contact_force_peak, sim_seconds=robot.time(), wall_seconds=_time.perf_counter() - wall0,
        frames=res.frames, planes=res.planes, transitions=res.transitions, frame_log=res.frame_log)


# ---------------------------------------------------------------------------------------------
# command line
# ---------------------------------------------------------------------------------------------
def add_placement_command(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``place`` on a sub-parser collection (the ``sim`` command's); sets ``func(args) -> int``
    (0 released, 1 refused or timed out, 2 bad input)."""
    p = subparsers.add_parser("place", help="simulate putting the cup down (release or refuse)",
                              description="UR5 holding the cup over a scenario's table: approach, descend, check "
                                          "levelness and clearance with the TMF8820, then release or refuse.")
    p.add_argument("--scenario", default="place_level",
                   help="scenario file or packaged name (default place_level; place_tilted must be refused)")
    p.add_argument("--method", default="diff", help="plane-recovery method (diff, peak, ...; default diff)")
    p.add_argument("--calibration", help="calibration JSON (default for diff: the simulated sensor's parameters)")
    p.add_argument("--config", help="PlacementConfig JSON (speeds m/s, distances m, angles rad)")
    p.add_argument("--seconds", type=float, default=20.0, help="sim-time limit (default 20)")
    p.add_argument("--seed", type=int, default=0, help="sensor noise seed")
    p.add_argument("--render", help="write a PNG of the final scene")
    p.add_argument("--json", help="write the full result (with the per-frame log) to this JSON file")
    p.set_defaults(func=cmd_place)
    return p


def cmd_place(args: argparse.Namespace) -> int:
    cfg = PlacementConfig.load(args.config) if args.config else None
    res = run_placement(args.scenario, method=args.method, calibration=args.calibration, seconds=args.seconds,
                        render=args.render, seed=args.seed, config=cfg)
    print(res.summary())
    if args.json:
        Path(args.json).write_text(json.dumps(res.to_dict(), indent=1) + "\n")
    if args.render:
        print(f"wrote {args.render}", file=sys.stderr)
    return 0 if res.outcome == "released" else 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="place-safe sim place")
    sub = parser.add_subparsers(dest="command")
    add_placement_command(sub)
    args = parser.parse_args(["place", *(argv if argv is not None else sys.argv[1:])])
    try:
        return int(args.func(args))
    except (PlaceSafeError, OSError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())


__all__ = ["PlacementResult", "run_placement", "scenario_path", "add_placement_command", "cmd_place", "main",
           "CONTROL_PERIOD", "SETTLE_SECONDS"]
