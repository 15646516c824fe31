"""The ``place-safe sim ...`` commands: validate the simulated sensor, render scenes, benchmark speed.

``add_sim_commands(subparsers)`` registers a ``sim`` command with its own sub-commands on an
argparse sub-parser collection; each sets ``func(args) -> int`` (exit status: 0 success, 1 a
``--strict`` target missed, 2 bad input). They run as ``place-safe sim ...`` (:func:`place_safe.cli.main`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time


from place_safe.cli import options
from place_safe.exceptions import FrameFileError, UsageError
from place_safe.sim.bench import bench


def add_sim_commands(subparsers: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``sim place``, ``sim validate``, ``sim render`` and ``sim bench``; returns the ``sim`` parser."""
    sim = subparsers.add_parser("sim", help="MuJoCo simulation: validate the simulated TMF8820, render, benchmark",
                                description="MuJoCo simulation of the UR5 and the TMF8820 (needs the [sim] extra).")
    sub = sim.add_subparsers(dest="sim_command", metavar="{place,calibrate,validate,render,bench}")
    sim.set_defaults(func=_no_sub_command)

    from place_safe.sim.placement_run import add_placement_command

    add_placement_command(sub)

    c = sub.add_parser("calibrate", help="regenerate the simulated user calibration (touch, capture, calibrate)",
                       description="The chain a user runs on the UR5, in MuJoCo: the simulated arm touches the level "
                                   "table at three points (the plane it measures is the ground truth), captures a "
                                   "sweep of poses above it with the simulated sensor (as 'place-safe capture'), and "
                                   "fits the capture with 'place-safe calibrate' (--method diff, then proprietary). "
                                   "Without -o, rewrites the packaged sim/sensors/calibration_<sensor>.json that "
                                   "placements use by default. Example: place-safe sim calibrate --sensor mismatch")
    c.add_argument("--sensor", choices=("nominal", "mismatch", "all"), default="all",
                   help="which simulated sensor (default all)")
    c.add_argument("-o", "--output", help="calibration file to write (one sensor only; default: the packaged file)")
    c.add_argument("--frames", type=options.int_range(8, 1000), default=48,
                   help="poses (one frame each) in the sweep (default 48, 8..1000)")
    c.add_argument("--seed", type=options.int_range(0, 2 ** 32 - 1), default=0, help="sweep and noise seed (default 0)")
    c.add_argument("--save-frames", help="also keep the capture file (JSON Lines) here (one sensor only)")
    c.set_defaults(func=cmd_calibrate)

    v = sub.add_parser("validate", help="compare simulated histograms with a real sweep, zone by zone",
                       description="For each real frame with ground truth, place the simulated sensor at the same "
                                   "distance and angle over a level table, simulate without noise and report per zone "
                                   "the sub-bin peak difference and the correlation of the histogram shapes. "
                                   "Targets: mean |peak diff| <= 0.5 bin and mean correlation >= 0.95 in every zone.")
    v.add_argument("frames", help="frame file with ground truth (e.g. tests/data/tmf8820_ur5_sweep.json)")
    v.add_argument("--params", help="ForwardParams JSON of the simulated sensor (default sim/sensors/tmf8820_real.json)")
    v.add_argument("--rays", type=options.int_range(1, 64), default=8, help="stratified rays per axis and zone (default 8)")
    v.add_argument("--min-distance", type=options.float_range(0.0, 500.0), default=5.0, help="use frames at z0 >= this many cm (default 5)")
    v.add_argument("--json", action="store_true", help="print the per-zone figures as JSON instead of a table")
    v.add_argument("--strict", action="store_true", help="exit 1 if a target is missed")
    v.set_defaults(func=cmd_validate)

    r = sub.add_parser("render", help="write a PNG (and optionally a GIF) of a scene with the sensor's rays",
                       description="Offscreen rendering with mujoco.Renderer (EGL when there is no display).")
    r.add_argument("--scene", help="scene JSON (SceneConfig, or a scenario file with a 'scene' key); "
                                   "default: level table and a sensor rig")
    r.add_argument("--robot", action="store_true", help="with the UR5 (overrides the scene's with_robot)")
    r.add_argument("-o", "--output", default="scene.png", help="PNG path (default scene.png)")
    r.add_argument("--gif", help="also write a GIF of the rig descending 20 cm (rig scenes)")
    r.add_argument("--no-rays", action="store_true", help="do not draw the sensor's rays")
    r.add_argument("--width", type=options.int_range(16, 4096), default=640, help="image width (pixels, default 640)")
    r.add_argument("--height", type=options.int_range(16, 4096), default=480, help="image height (pixels, default 480)")
    r.add_argument("--azimuth", type=options.float_range(-360.0, 360.0), default=135.0, help="camera azimuth (deg)")
    r.add_argument("--elevation", type=options.float_range(-90.0, 90.0), default=-25.0, help="camera elevation (deg)")
    r.add_argument("--distance", type=options.float_range(0.0, 100.0, lo_open=True), default=None,
                   help="camera distance (m, at most 100)")
    r.add_argument("--view", action="store_true", help="open the interactive viewer instead (needs a display)")
    r.set_defaults(func=cmd_render)

    b = sub.add_parser("bench", help="real-time factor of physics + simulated sensor in lockstep",
                       description="Steps the scene for --seconds of sim time with the sensor measuring at --rate Hz "
                                   "in lockstep and reports the real-time factor (sim time / wall time). Target >= 5.")
    b.add_argument("--scene", help="scene JSON (default: level table)")
    b.add_argument("--rig", action="store_true", help="sensor rig only (no robot); default: the UR5 holding the cup")
    b.add_argument("--seconds", type=options.float_range(0.0, 3600.0, lo_open=True), default=5.0, help="sim seconds to run (default 5)")
    b.add_argument("--rate", type=options.float_range(0.0, 1000.0, lo_open=True), default=30.0, help="sensor frame rate (Hz, default 30)")
    b.add_argument("--rays", type=options.int_range(1, 64), default=8, help="stratified rays per axis and zone (default 8)")
    b.set_defaults(func=cmd_bench)
    return sim


SUB_COMMANDS = ("place", "calibrate", "validate", "render", "bench")


def _no_sub_command(_args: argparse.Namespace) -> int:
    """``place-safe sim`` alone: one line naming the sub-commands and where the help is (exit 2)."""
    raise UsageError(f"sim: a sub-command is required: {', '.join(SUB_COMMANDS)} (see 'place-safe sim --help')")


def cmd_calibrate(args: argparse.Namespace) -> int:
    from place_safe.sim.calibration_capture import calibrate_sim

    sensors = ("nominal", "mismatch") if args.sensor == "all" else (args.sensor,)
    if len(sensors) > 1 and (args.output or args.save_frames):
        print("error: sim calibrate: -o and --save-frames need one --sensor", file=sys.stderr)
        return 2
    if args.frames < 8:
        print("error: sim calibrate: --frames must be at least 8", file=sys.stderr)
        return 2
    for s in sensors:
        out = calibrate_sim(s, args.output, n=args.frames, seed=args.seed, frames_out=args.save_frames)
        print(f"wrote {out} ({s} simulated sensor, {args.frames} sweep frames)", file=sys.stderr)
    return 0


def cmd_validate(args: argparse.Namespace) -> int:
    import numpy as np

    from place_safe.recovery.forward import ForwardParams
    from place_safe.io.frame_file import load_frames

    from place_safe.sim.validate import validate

    frames = load_frames(args.frames)
    params = ForwardParams.load(args.params) if args.params else None
    t = time.perf_counter()
    rep = validate(frames, params, rays=args.rays, min_distance=args.min_distance / 100.0)
    if len(rep.distances) == 0:
        raise FrameFileError(f"no frame of {args.frames} has ground truth at >= {args.min_distance} cm")
    if args.json:
        table = {k: [float(x) for x in np.round(v, 4)] for k, v in rep.zone_table().items()}
        print(json.dumps({"frames": int(len(rep.distances)), "passed": rep.passed, "zones": table}))
    else:
        print(rep.format())
        print(f"({time.perf_counter() - t:.1f} s)", file=sys.stderr)
    return 1 if (args.strict and not rep.passed) else 0


def cmd_render(args: argparse.Namespace) -> int:
    from place_safe.sim import render
    from place_safe.sim.scene import build_scene, scene_config
    from place_safe.sim.tof import SimToF

    scene = build_scene(scene_config(args.scene, True if args.robot else None))
    data = scene.make_data()
    if scene.config.with_robot:
        from place_safe.sim.robot import SimRobot

        data = SimRobot(scene.model, data).data  # arm at home holding the cup
    if args.view:
        render.view(scene, data)
        return 0
    tof = None if args.no_rays else SimToF(scene, data)
    kw = dict(width=args.width, height=args.height, azimuth=args.azimuth, elevation=args.elevation,
              distance=args.distance)
    img = render.render_image(scene, data, tof, **kw)
    out = render.save_png(img, args.output)
    print(f"wrote {out} ({img.shape[1]}x{img.shape[0]})", file=sys.stderr)
    if args.gif:
        if scene.rig_mocap < 0:
            raise UsageError("sim render: --gif animates the sensor rig; use a scene without the robot")
        rig_tof = tof if tof is not None else SimToF(scene, data)
        frames = render.sweep_frames(scene, rig_tof, **kw)
        print(f"wrote {render.save_gif(frames, args.gif)} ({len(frames)} frames)", file=sys.stderr)
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    res = bench(args.scene, args.rig, args.seconds, args.rate, args.rays)
    print(f"{res['sim_seconds']:.2f} s sim in {res['wall_seconds']:.2f} s wall: real-time factor "
          f"{res['real_time_factor']:.1f}x ({res['frames']} sensor frames at {args.rate:g} Hz, "
          f"{res['physics_steps']} physics steps, {'UR5' if res['with_robot'] else 'rig'})")
    return 0


__all__ = ["add_sim_commands"]

