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
* Calibration is honest: by default the estimator gets the scenario's calibration, normally the
  packaged simulated *user* calibration of the scenario's simulated sensor (a level-table sweep fitted
  with ``place-safe calibrate``, :mod:`place_safe.sim.calibration_capture`), never the simulator's own
  parameters; only ``oracle=True`` (``--oracle``) hands those over, and ``PlacementResult.calibration``
  then starts with ``ORACLE``. A method without its calibration (or its calibrated uncertainty) refuses before
  anything moves and says how to calibrate (:func:`place_safe.calibration.placement_reason`).
* Simulation truth for judging the run (true tilt, release height, time from 40 cm, ...) is recorded
  by :class:`place_safe.sim.scenario.TruthRecorder` from the robot's step callbacks.
* After the machine finishes, the simulation runs :data:`SETTLE_SECONDS` more so the released cup and
  liquid come to rest before the cup tilt and the spill are measured.
"""

from __future__ import annotations

import math
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from place_safe.exceptions import RobotFault
from place_safe.placement.loop import CONTROL_PERIOD, PlacementLoop
from place_safe.placement.config import PlacementConfig
from place_safe.sim.scenario import (ORACLE_NOTE, Scenario, TruthRecorder, load_scenario, oracle_calibration,
                                     scenario_path, surface_truth)  # noqa: F401 - part of this module's API
from place_safe.recovery import make_estimator
from place_safe.calibration import Calibration, placement_reason
from place_safe.robot.description import ur5_config
from place_safe.sim import render as _render
from place_safe.sim.scene import SceneConfig
from place_safe.sim.world import sim_world

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
    # simulation truth (never shown to the estimator or the machine); see place_safe.sim.scenario
    sensor: str = "nominal"  # which simulated sensor ("nominal" renders with the forward model, "mismatch" not)
    true_tilt: float = math.nan  # rad, the table top's true tilt at the start
    surface_height: float = math.nan  # m, world z of the table top's centre at the start
    start_height: float = math.nan  # m, cup bottom above the surface at the start
    release_height: float = math.nan  # m, cup bottom above the surface it would land on (the table, or clutter under
    #                                   its footprint where higher) when the gripper opened (NaN: never)
    support_height: float = math.nan  # m, the same at the end: ~0 for a cup standing on the table or on clutter
    decision_time: float | None = None  # s from the cup bottom passing 40 cm above the surface to the decision
    surface_moved: float = 0.0  # m the table moved during the run
    fault_injected: str | None = None
    robot_fault: str | None = None
    calibrated: bool = True  # False: the method had no calibration, so the placement refused before moving
    budget: dict = field(default_factory=dict)  # s of robot time per part of the placement (PlacementMachine.budget)

    def to_dict(self) -> dict:
        return dict(self.__dict__)

    def summary(self) -> str:
        """A few lines for the console."""
        lines = [f"placement {self.scenario} with {self.method}: {self.outcome.upper()} ({self.reason})",
                 f"  cup: {'held' if self.cup_held else 'released'}, tilt {math.degrees(self.cup_tilt):.1f} deg, "
                 f"bottom {self.cup_height * 1e3:.1f} mm above the table"
                 + (f" ({self.support_height * 1e3:.1f} mm above the clutter under it)"
                    if self.support_height < self.cup_height - 1e-3 else "") + "; liquid spilled "
                 f"{self.liquid_spilled}/{self.liquid_total}; peak contact force {self.contact_force_peak:.1f} N",
                 f"  {self.sim_seconds:.2f} s sim in {self.wall_seconds:.2f} s wall; {self.frames} frames, "
                 f"{self.planes} planes accepted; sensor {self.sensor}; calibration: {self.calibration}"]
        for tr in self.transitions:
            lines.append(f"  t={tr['time']:6.3f} s  {tr['from']:>8} -> {tr['to']:<8} {tr['reason']}")
        return "\n".join(lines)


def _as_scenario(scenario: Any):
    if isinstance(scenario, Scenario):
        return scenario
    if isinstance(scenario, SceneConfig):
        return Scenario(scene=scenario.to_dict(), name="scene")
    return load_scenario(scenario)


def _calibration(sc: Any, calibration: Any, oracle: bool) -> tuple[Any, str]:
    if oracle:
        return oracle_calibration(), ORACLE_NOTE
    if calibration is None:
        return sc.resolve_calibration()
    if isinstance(calibration, Calibration):
        return calibration, "given"
    if str(calibration) in ("sim", "oracle", "none"):
        return sc.model_copy(update={"calibration": str(calibration)}).resolve_calibration()
    return Calibration.load(calibration), str(calibration)


def run_placement(scenario: Any = "place_level", method: str | None = None, calibration: Any = None,
                  seconds: float = 20.0, render: str | Path | None = None, seed: int = 0,
                  config: PlacementConfig | None = None, estimator_options: dict | None = None,
                  log_frames: bool = True, oracle: bool = False, mount_error: Any = None,
                  tool: Any = None, robot_config: Any = None) -> PlacementResult:
    """Simulate one placement (see module docstring).

    ``scenario``: a scenario file path or packaged name, a :class:`~place_safe.sim.scenario.Scenario`
    or a :class:`~place_safe.sim.scene.SceneConfig` (the robot is always added). ``method``: default
    the scenario's. ``calibration``: a :class:`~place_safe.calibration.Calibration`, a path, ``"sim"``,
    ``"none"``, or None for the scenario's (default the packaged simulated user calibration);
    ``oracle=True`` hands the estimator the simulator's true parameters (debugging; named in the result).
    ``seconds``: sim-time limit. ``render``: PNG path of the scene at the end. ``seed``: the simulated
    sensor's noise seed unless the scenario sets its own. ``config``: the placement thresholds
    (default: the scenario's). ``mount_error``: how far the true sensor mount is off the nominal one
    (dx, dy, dz mm, rx, ry, rz deg; :func:`place_safe.sim.world.sim_world`). ``tool``: the tool frames the loop
    believes (:class:`~place_safe.robot.tool.ToolFrames`, e.g. from a robot file with a fitted mount; default the
    robot's nominal ones). ``robot_config``: a robot file's :class:`~place_safe.drivers.ur5.config.URConfig` whose
    tool frames (unless ``tool``), Cartesian speed, acceleration and contact-force limits, emergency stop and
    placement motion (:func:`~place_safe.drivers.ur5.config.placement_config`: near-surface speed, stop
    decelerations, contact latency) the simulated arm and the loop take, as they do on the arm; its workspace box,
    ``min_descent_z`` and ``surface_keepout`` are the arm driver's host checks and are not simulated.
    """
    wall0 = _time.perf_counter()
    sc = _as_scenario(scenario)
    name = sc.name or "scenario"
    method = method or sc.method
    if isinstance(seconds, bool) or not isinstance(seconds, (int, float)) or not (
            math.isfinite(seconds) and 0 < seconds <= 3600):
        raise ValueError(f"seconds must be a number of sim seconds in (0, 3600]; got {str(seconds)[:40]!r}")
    calibration, cal_note = _calibration(sc, calibration, oracle)
    if calibration is not None:
        calibration.check()  # a placement runs only on a calibration whose every section is valid
    cfg = config if config is not None else sc.placement_config()
    world = sim_world(sc, seed=seed, attach=False, mount_error=mount_error)  # the truth recorder goes in first
    scene, robot, tof = world.scene, world.robot, world.tof
    if robot_config is not None:  # the arm's own limits and motion policy, as on the arm (cli place --robot-file)
        from place_safe.drivers.ur5.config import placement_config
        from place_safe.sim.robot import sim_limits

        robot.limits = sim_limits(robot_config)
        robot.emergency_decel = float(robot_config.motion.emergency_decel)
        cfg = placement_config(robot_config, cfg)
        tool = tool if tool is not None else robot_config.tool.frames()
    if tool is not None:
        robot.tool = tool
    tilt_true, surface_z = surface_truth(scene, robot.data)
    liquid_total = int(ur5_config()["cup"]["liquid_count"])
    truth = TruthRecorder(sc, scene, robot)
    truth()
    common = dict(scenario=name, method=method, calibration=cal_note, sensor=sc.sensor.model,
                  true_tilt=tilt_true, surface_height=surface_z, start_height=truth.start_height)
    why = placement_reason(method, calibration)
    if why is not None:  # calibration is required: refuse before anything moves
        return PlacementResult(outcome="refused", reason=why, final_phase="idle", cup_tilt=0.0, calibrated=False,
                               cup_height=truth.start_height, cup_held=robot.holding(), liquid_spilled=0,
                               liquid_total=liquid_total, contact_force_peak=0.0, sim_seconds=robot.time(),
                               wall_seconds=_time.perf_counter() - wall0, frames=0, planes=0, **common)
    estimator = make_estimator(method, calibration, **(estimator_options or {}))
    robot.add_step_callback(truth)
    tof.attach(robot)
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
    height = truth.cup_height()
    support = truth.support_height()
    if render is not None:
        _render.save_png(_render.render_image(scene, robot.data, tof), render)
    decided = next((t for t in res.transitions if t.target.value in ("release", "refuse", "aborted")), None)
    t_dec = decided.time if decided is not None else None
    t_ref = truth.t_reference
    return PlacementResult(
        outcome=res.outcome, reason=res.reason, final_phase=res.final_phase, cup_tilt=tilt, cup_height=height,
        cup_held=robot.holding(), liquid_spilled=robot.liquid_spilled(), liquid_total=liquid_total,
        contact_force_peak=max(res.contact_force_peak, getattr(robot, "true_force_peak", 0.0)), sim_seconds=robot.time(), wall_seconds=_time.perf_counter() - wall0,
        frames=res.frames, planes=res.planes, transitions=[t.to_dict() for t in res.transitions], frame_log=res.frame_log,
        release_height=truth.release_height, support_height=support, decision_time=(t_dec - t_ref) if (t_dec is not None and t_ref is not None)
        else None, surface_moved=truth.surface_moved, fault_injected=truth.stop_injected,
        robot_fault=robot.fault(), budget=dict(getattr(res, "budget", {}) or {}), **common)


__all__ = ["PlacementResult", "run_placement", "oracle_calibration", "scenario_path",
           "CONTROL_PERIOD", "SETTLE_SECONDS"]
