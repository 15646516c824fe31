"""Task commands that run the same on the UR5 and in MuJoCo: ``place``, ``capture``, ``calibrate-mount``.

Each chooses a robot and a sensor -- ``--robot ROBOT.toml --sensor URI`` for the arm (ur_rtde, the sensor
opened by URI), ``--sim SCENARIO`` for MuJoCo (SimRobot + simulated TMF8820) -- and then runs one library
function: :class:`~place_safe.placement.loop.PlacementLoop`, :func:`~place_safe.calibration.capture.capture_sweep`
or :func:`~place_safe.calibration.mount.fit_mount`. Parsing and printing only; heavy imports inside the
command functions. Units on the command line: mm and degrees where the option says so, else SI.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

from place_safe.cli import options
from place_safe.cli.options import opt
from place_safe.cli.common import (CALIBRATE_METHODS, ORACLE_NOT_A_CALIBRATION, PROG, ROBOT_FILE_HELP, count_note,
                                   flags_said, log, uncalibrated_note)
from place_safe.cli.options import REACH, float_range, int_range
from place_safe.exceptions import CalibrationError, ConfigError, UsageError
from place_safe.calibration import Calibration, mark, placement_reason, uncalibrated_reason
from place_safe.calibration.capture import (MIN_CLEARANCE, TOUCH_HEIGHT_STD, refusal_line, repeated_value,
                                            touch_plane)
from place_safe.recovery import make_estimator
from place_safe.config import read_json
from place_safe.geometry import transform_problem
from place_safe.sensor.frame import SENSOR_RANGE, without_repeats


def _items(text: str, what: str) -> list[str]:
    """The items of a comma-separated option ``text`` (spaces dropped); one ``expected ...`` line for an empty item
    between commas or at either end (``--incidences 0,,12`` read as ``0,12``, silently: session 83). An empty
    ``text`` gives ``[]`` (the caller says it is empty)."""
    items = text.replace(" ", "").split(",")
    if len(items) > 1 and "" in items:
        raise argparse.ArgumentTypeError(f"expected comma-separated {what} with no empty item (two commas together, "
                                         f"or one at an end), got {text[:80]!r}")
    return [v for v in items if v != ""]


def _floats(text: str, n: int | None = None, what: str = "numbers", lo: float = -math.inf,
            hi: float = math.inf) -> list[float]:
    """Comma-separated finite numbers (``n`` of them when given, at most :data:`MAX_LIST`), each in [lo, hi]; an
    empty item is refused (:func:`_items`)."""
    items = _items(text, what)
    try:
        vals = [float(v) for v in items]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated {what}, got {text[:80]!r}") from None
    return _checked(vals, text, n, what, lo, hi)


def _checked(vals: list[float], text: str, n: int | None, what: str, lo: float, hi: float) -> list[float]:
    """``vals`` read from option ``text`` if finite, ``n`` of them (1 to :data:`MAX_LIST` without ``n``) and each in
    [lo, hi]; else one ``expected ...`` line naming ``text``."""
    if (not vals or not all(math.isfinite(v) for v in vals) or (n is not None and len(vals) != n)
            or len(vals) > MAX_LIST):
        raise argparse.ArgumentTypeError(f"expected {n or f'1 to {MAX_LIST}'} comma-separated finite {what}, "
                                         f"got {text[:80]!r}")
    if not all(lo <= v <= hi for v in vals):
        raise argparse.ArgumentTypeError(f"expected {what} from {lo:g} to {hi:g}, got {text[:80]!r}")
    return vals


def _distinct(vals: list[float], text: str, unit: str, period: float | None = None) -> list[float]:
    """``vals`` of a sweep plan's axis (``capture --distances``, ``--incidences``, ``--azimuths``) read from ``text``
    if no value repeats an earlier one (within 1e-6 of the unit; modulo ``period``); else one line naming the value.
    The rule is :class:`~place_safe.calibration.capture.SweepPlan`'s (:func:`repeated_value`), said here in the option's
    units before anything runs: ``--distances 80,80`` captured the 80 mm poses twice (round 14)."""
    if (ij := repeated_value(vals, period, 1e-6)) is not None:
        i, j = ij
        same = "" if vals[i] == vals[j] else f" (as {vals[j]:g} {unit}: a turn apart is one direction)"
        overlap = " (ranges that overlap?)" if ":" in text else ""
        raise argparse.ArgumentTypeError(f"{vals[i]:g} {unit} is given twice in {text[:80]!r}{same}{overlap}: each "
                                         "value is a row of poses, captured once (more frames of a pose: "
                                         "--frames-per-pose)")
    return vals


#: The guarded descent of ``capture --touch`` (:func:`~place_safe.calibration.capture.touch_plane`'s defaults: m/s, N,
#: m), for its help.
_TOUCH = touch_plane.__kwdefaults__

#: The most values one comma-separated option takes (a sweep grid is their product).
MAX_LIST = 100


def _distances(text: str) -> list[float]:
    """``capture --distances``: comma-separated millimetres from 10 to the sensor's range (5000), each a number or a
    range ``START:STOP:STEP`` (STOP included when the steps reach it), e.g. ``10:90:2,100:400:10``; at most
    :data:`MAX_LIST` values in all."""
    values: list[float] = []
    for item in _items(text, "mm (numbers or START:STOP:STEP)"):
        if ":" not in item:
            try:
                values += [float(item)]
            except ValueError:
                raise argparse.ArgumentTypeError(f"expected comma-separated mm (numbers or START:STOP:STEP), got "
                                                 f"{text[:80]!r}") from None
            continue
        try:
            start, stop, step = (float(v) for v in item.split(":"))
        except ValueError:
            start = stop = step = math.nan
        if not (math.isfinite(start + stop + step) and step > 0.0 and stop >= start
                and (stop - start) / step + 1 <= MAX_LIST):
            raise argparse.ArgumentTypeError(f"expected a range START:STOP:STEP (mm) with STOP >= START, STEP > 0 "
                                             f"and at most {MAX_LIST} values, got {item[:80]!r}")
        n = int(math.floor((stop - start) / step + 1e-9))
        values += [round(start + i * step, 9) for i in range(n + 1)]  # no drift from adding steps up
    return _distinct(_checked(values, text, None, "mm", 10.0, SENSOR_RANGE * 1000.0), text, "mm")


#: m: base-frame coordinates an option may name (the UR5 reaches 0.85 m from its base).


def _mount_error(text: str) -> list[float]:
    """``dx,dy,dz,rx,ry,rz`` in mm and degrees -> m and rad."""
    v = _floats(text, 6, "numbers (mm, mm, mm, deg, deg, deg)", -1000.0, 1000.0)
    if max(abs(x) for x in v[3:]) > 180.0:
        raise argparse.ArgumentTypeError(f"expected rotations from -180 to 180 degrees, got {text[:80]!r}")
    return [x / 1000.0 for x in v[:3]] + [math.radians(x) for x in v[3:]]


def _xy_points(text: str) -> list[float]:
    return _floats(text, 2, "x,y metres", -REACH, REACH)


def open_sensor(uri: str, **source_options: Any) -> Any:
    """The frame source a sensor URI names (:func:`place_safe.sources.open_source`: ``i2c:``, ``serial:``,
    ``file:``, ``emu:``), with the sensor options given (:func:`place_safe.cli.options.sensor_options`)."""
    from place_safe.sources import open_source

    return open_source(uri, **source_options)


def _robot_config(path: str | None):
    from place_safe.drivers.ur5 import URConfig

    return URConfig.load(path if path else _packaged_path("sim"))


def _packaged_path(name: str) -> Path:
    from place_safe.drivers.ur5 import packaged_config

    return packaged_config(name)


#: What the result file's "calibration" says of a run without a calibration file.
BUILT_IN = "built-in defaults"


def _estimator(method: str, calibration: str | None):
    """(estimator, note saying where its calibration came from: the file, or :data:`BUILT_IN`, the calibration or
    None). Whether it calibrates ``method`` is :func:`~place_safe.calibration.uncalibrated_reason`'s: a file without
    the method's sections (diff's ``peak``) calibrates it no more than no file."""

    if calibration:  # every section valid (a NaN anywhere is refused), not only the method's
        cal = Calibration.load(calibration).check()
        return make_estimator(method, cal), calibration, cal
    return make_estimator(method, None), BUILT_IN, None


def _mount_truth(path: str) -> Any:
    """The true ``flange_T_sensor`` (4x4 rigid transform, metres) of a truth JSON file; one-line ConfigError."""
    import numpy as np

    d = read_json(path, "mount truth", ConfigError)
    if not isinstance(d, dict) or "flange_T_sensor" not in d:
        got = "an object without it" if isinstance(d, dict) else f"a JSON {type(d).__name__}"
        raise ConfigError(f"mount truth {path}: expected an object with \"flange_T_sensor\" (a 4x4 matrix), got {got}")

    v = d["flange_T_sensor"]
    ok = isinstance(v, list) and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                     for r in v if isinstance(r, list) for x in r)
    why = transform_problem(v) if ok else "is not a 4x4 matrix of numbers"
    if why is None and np.abs(np.asarray(v, dtype=float)[:3, 3]).max() > 2.0:
        why = "translation is more than 2 m from the flange"
    if why is not None:
        raise ConfigError(f"mount truth {path}: flange_T_sensor {why}")
    T = np.asarray(v, dtype=float)
    return T


def _write_json(path: str, value: Any) -> None:
    Path(path).write_text(json.dumps(value, indent=1) + "\n", encoding="utf-8")


# ------------------------------------------------------------------------------------------------
# place
# ------------------------------------------------------------------------------------------------
def cmd_place(args: argparse.Namespace) -> int:
    """One placement: on the UR5 (``--robot``) or in MuJoCo (``--sim``, :func:`~place_safe.sim.placement_run.run_placement`).

    Writes the result (``--json``) and the transition log (``--log``) either way; exit 0 released, 1 refused or
    timed out."""
    from place_safe.placement.machine import PlacementConfig

    if not args.sim:
        for flag, given in (("--oracle", args.oracle), ("--render", args.render)):
            if given:
                raise UsageError(f"place: {flag} is for the simulation (--sim SCENARIO)")
    elif args.uncalibrated:
        raise UsageError("place: --uncalibrated is for the arm (--robot); in simulation give --calibration none")
    elif args.oracle and args.calibration is not None:
        raise UsageError(f"place: {ORACLE_NOT_A_CALIBRATION}")
    elif args.render:
        from place_safe.sim.render import image_problem

        if (why := image_problem(args.render)) is not None:  # (before the run: it failed after, and no result written)
            raise UsageError(f"place: --render {args.render} {why}")
    cfg = PlacementConfig.load(args.config) if args.config else None
    if args.sim:
        out, res, lines = _place_sim(args, cfg)
    else:
        out, res, lines = _place_arm(args, cfg if cfg is not None else PlacementConfig())
    if not args.frame_log:
        out.pop("frame_log", None)
    with open(args.log, "w", encoding="utf-8") as fh:
        for tr in _transition_rows(res):
            fh.write(json.dumps(tr) + "\n")
    _write_json(args.json, out)
    print("\n".join(lines))
    log(f"wrote {args.json} and {args.log}" + (f" and {args.render}" if args.render else ""))
    return 0 if res.outcome == "released" else 1


def _transition_rows(res: Any) -> list[dict]:
    """The placement's transitions as the log's JSON objects (``time``, ``from``, ``to``, ``reason``): the loop's
    result holds the machine's :class:`~place_safe.placement.machine.Transition` objects, the simulation's result
    their dicts."""
    return [tr.to_dict() if hasattr(tr, "to_dict") else dict(tr) for tr in res.transitions]


def _place_sim(args: argparse.Namespace, cfg) -> tuple[dict, Any, list[str]]:
    """The placement in MuJoCo: the scenario's calibration unless --calibration/--oracle, refused without one."""
    from place_safe.sim.placement_run import run_placement

    robot_cfg = _robot_config(args.robot) if args.robot else None  # its mount, limits and motion, as on the arm
    if robot_cfg is not None:
        print(f"place --sim: {args.robot}: the tool frames, speed, acceleration and force limits and [motion] "
              "apply; the workspace box, min_descent_z and surface_keepout are checked on the arm only",
              file=sys.stderr)
    res = run_placement(args.sim, method=args.method, calibration=args.calibration, seconds=args.timeout,
                        render=args.render, seed=args.seed, config=cfg, oracle=args.oracle,
                        log_frames=args.frame_log, mount_error=args.sim_mount_error, robot_config=robot_cfg)
    out = {"where": f"simulation {res.scenario}", "robot_config": args.robot or "packaged sim.toml",
           "mount_error": [float(v) for v in (args.sim_mount_error or [0.0] * 6)], **res.to_dict()}
    return out, res, [res.summary()]


def _place_arm(args: argparse.Namespace, cfg) -> tuple[dict, Any, list[str]]:
    """The placement on the UR5 (or its dry run) with the sensor of --sensor."""
    from place_safe.placement.loop import PlacementLoop

    from place_safe.drivers.ur5 import URRobot
    from place_safe.drivers.ur5.config import placement_config

    if not args.sensor:
        raise UsageError("place: --sensor URI is required with --robot (e.g. --sensor i2c:/dev/i2c-1)")
    source_options = options.sensor_options(args, args.sensor, "place")
    method = args.method or "diff"
    estimator, cal_note, cal = _estimator(method, args.calibration)
    why = placement_reason(method, cal)  # (a calibration without the method's uncertainty entries too)
    calibrated = why is None
    robot_cfg = _robot_config(args.robot)
    if not calibrated and not (args.dry_run or args.uncalibrated):
        # a file without the method's section (diff's peak): which; no file: how to make one
        what = (f"{args.calibration}: {why}" if args.calibration else
                "on the arm the sensor needs its calibration (--calibration CAL.json, made by 'place-safe calibrate' "
                "from this unit's level sweep): built-in constants read a level table degrees off")
        raise UsageError(f"place: {what} (--uncalibrated runs on built-in constants anyway; a dry run moves nothing "
                         "and may)")
    if not calibrated:  # said before anything moves, not after the cup is down
        print(uncalibrated_note(method, cal, args.calibration) or f"UNCALIBRATED: {args.calibration}: {why}",
              flush=True)
    robot = URRobot(robot_cfg, dry_run=args.dry_run)
    cfg = placement_config(robot_cfg, cfg)  # near-surface speed and stop decelerations of the robot file
    source = open_sensor(args.sensor, **source_options)
    where = f"UR5 at {robot_cfg.connection.host}" + (" (dry run)" if args.dry_run else "")
    try:  # the sensor is closed however the robot ends (an arm that does not connect left it measuring)
        with robot:
            res = PlacementLoop(robot, source, estimator, tool=robot.tool, config=cfg).run(timeout=args.timeout)
    finally:
        source.close()
    out = {"where": where, "method": method, "calibration": cal_note, "calibrated": calibrated,
           "robot_config": args.robot, **res.to_dict()}
    lines = [mark(f"{where}: {res.outcome.upper()} ({res.reason})", calibrated)]
    lines += [f"  t={tr['time']:7.3f} s  {tr['from']:>8} -> {tr['to']:<8} {tr['reason']}" for tr in _transition_rows(res)]
    return out, res, lines


# ------------------------------------------------------------------------------------------------
# capture
# ------------------------------------------------------------------------------------------------
#: m, rad: how far ``capture --sim --table-height Z`` may be from the scenario's table top (its height, and its tilt
#: from the level that --table-height states) before capture refuses: the simulated table is exact, and a height
#: off by more went into every frame as wrong ground truth (and placed the sensor off its planned distances). With
#: ``--table-tilt-std S`` the table may be tilted up to 3 S (the levelness the frames then state).
SIM_TABLE_HEIGHT_TOL, SIM_TABLE_TILT_TOL = 0.001, math.radians(0.1)


def _check_sim_table(args: argparse.Namespace, plane: tuple[Any, float]) -> None:
    """A usage error when ``--table-height`` disagrees with the simulated table ``plane`` (base frame: unit normal,
    offset) beyond :data:`SIM_TABLE_HEIGHT_TOL` or :data:`SIM_TABLE_TILT_TOL`."""
    n, d = plane
    nz = abs(float(n[2]))
    tilt, z = math.acos(min(1.0, nz)), d / nz  # z: the table top's height above (or below) the base's origin
    tilt_ok = max(SIM_TABLE_TILT_TOL, 3 * math.radians(args.table_tilt_std or 0.0))
    if not (abs(z - args.table_height) <= SIM_TABLE_HEIGHT_TOL and tilt <= tilt_ok):
        raise UsageError(f"capture: --table-height {args.table_height:g} disagrees with the scenario's table (z = "
                         f"{z:.4f} m in the base frame, tilted {math.degrees(tilt):.2f} deg; allowed "
                         f"{SIM_TABLE_HEIGHT_TOL * 1000:g} mm, {math.degrees(tilt_ok):g} deg): leave it out to use "
                         "the scenario's table")


def cmd_capture(args: argparse.Namespace) -> int:
    from place_safe.calibration.capture import (SweepPlan, capture_sweep, level_plane, read_capture, resume_problem,
                                                touch_plane, touched_reference)
    from place_safe.recovery.estimator import Reference

    # an output that is not a capture to resume: refused before the arm is connected, touched or moved; read once, and
    # what was read passed on (the resume check, the sweep)
    existing = read_capture(Path(args.output))
    existed = Path(args.output).exists()

    grid = len(args.distances) * len(args.incidences) * len(args.azimuths)
    if min(grid, args.poses or grid) * args.frames_per_pose > 100_000:
        raise UsageError(f"capture: {grid} poses x {args.frames_per_pose} frames is too long a sweep; "
                         "give --poses N (at most 100000 frames in all)")
    if args.table_tilt_std is not None and args.touch:
        raise UsageError("capture: --table-tilt-std goes with --table-height, not --touch (a touched plane states its "
                         "own error)")
    if args.table_tilt_std is not None and args.table_height is None:
        raise UsageError("capture: --table-tilt-std goes with --table-height (how far that table may be from level)")
    if not args.touch and (given := [flag for flag, v in (("--touch-height", args.touch_height),
                                                          ("--touch-force", args.touch_force)) if v is not None]):
        raise UsageError(f"capture: {flags_said(given, 'goes', 'go')} with --touch (the points "
                         "where the TCP touches the table); without it the plane is not touched")
    if args.touch and not 3 <= len(args.touch) <= 20:
        raise UsageError(f"capture: --touch needs 3 to 20 points, got {len(args.touch)}")
    plan = SweepPlan(distances=[d / 1000.0 for d in args.distances],
                     incidences=[math.radians(a) for a in args.incidences],
                     azimuths=[math.radians(a) for a in args.azimuths], frames_per_pose=args.frames_per_pose,
                     max_poses=args.poses, speed=args.speed, settle_s=args.settle,
                     min_clearance=args.min_clearance / 1000.0)
    if (why := resume_problem(existing, plan)) is not None:  # before the arm is connected, touched or moved
        raise UsageError(f"capture: {args.output} was captured with other options ({why}): resume it with the "
                         "--distances, --incidences, --azimuths and --poses it was made with, or give another output")
    robot_cfg = _robot_config(args.robot)
    if args.sim:
        from place_safe.sim.world import sim_world

        world = sim_world(args.sim, seed=args.seed, mount_error=args.sim_mount_error, hold_cup=False)
        if args.table_height is not None:
            _check_sim_table(args, world.table_plane_base())
        robot, source = world.robot, world.tof
        robot.tool = robot_cfg.tool.frames()
    else:
        if not args.sensor:
            raise UsageError("capture: --sensor URI is required with --robot")
        source_options = options.sensor_options(args, args.sensor, "capture")
        if args.table_height is None and not args.touch:
            raise UsageError("capture: give the plane: --table-height Z or --touch X,Y --touch X,Y --touch X,Y")
        if args.dry_run and args.touch:
            raise UsageError("capture: --touch moves the arm; with --dry-run give --table-height instead")
        from place_safe.drivers.ur5 import URRobot

        robot = URRobot(robot_cfg, dry_run=args.dry_run)
        source = open_sensor(args.sensor, **source_options)
    tool = robot_cfg.tool.frames()
    reference = None  # how far the plane may be off: stated for touches, and for a table height with its tilt std
    held: list[dict] = []  # the refused poses, listed once: with the result, or on stderr if there is none
    notes: list[str] = []  # said with the result (a capture that captured nothing is one error line, without them)
    try:  # the sensor is closed however the capture ends
        with robot:
            if args.touch:
                if len(args.touch) < 3:
                    raise UsageError("capture: --touch needs at least 3 points")
                z0 = args.touch_height if args.touch_height is not None else robot.tcp_pose()[2, 3]
                n, d, pts = touch_plane(robot, args.touch, z0,
                                        force_threshold=_TOUCH["force_threshold"] if args.touch_force is None
                                        else args.touch_force)
                reference = touched_reference(pts)
                log(f"touched the plane at {len(pts)} points: normal {n.round(4).tolist()}, offset {d * 1000:.1f} "
                    f"mm, within {math.degrees(reference.tilt_std):.2f} deg / {reference.offset_std * 1000:.2f} mm "
                    f"(1 sigma, {reference.height_std * 1000:.2f} mm per contact)")
                plane = (n, d)
            elif args.table_height is not None:
                plane = level_plane(args.table_height)
                if args.table_tilt_std is not None:
                    reference = Reference(tilt_std=math.radians(args.table_tilt_std))
                else:
                    notes.append("note: the table is taken as exactly level in the base frame; --table-tilt-std DEG "
                                 "states how far it may be off (or --touch the table), so that placements count it")
            else:
                plane = world.table_plane_base()
                notes.append(f"table from the scenario: z = {plane[1] * 1000:.1f} mm in the base frame")
            res = capture_sweep(robot, source, plan, args.output, plane=plane, tool=tool, progress=not args.quiet,
                                reference=reference, on_refused=held.append, existing=existing)
    except BaseException:  # no result to list them with (a fault, Ctrl-C): the poses refused so far, on stderr
        for entry in held:
            log(refusal_line(entry))
        raise
    finally:
        source.close()
    if res.refused and not res.frames and not res.skipped_done:  # nothing captured at all: an error, not a capture
        if not existed and Path(args.output).is_file() and Path(args.output).stat().st_size == 0:
            Path(args.output).unlink()  # (exit 0 with an empty file, which calibrate then called "empty"; session 82)
        first = res.refused[0]
        raise UsageError(f"capture: every pose was refused ({len(res.refused)} of {len(res.refused)}; the first, pose "
                         f"{first['pose_index']}: {first['reason']}): nothing captured, {args.output} "
                         f"{'left as it was' if existed else 'not written'}")
    for note in notes:
        log(note)
    print(res.summary())  # each refused pose listed once, here with the result (each was listed twice)
    for r in res.refused:
        print(f"  refused pose {r['pose_index']}: {r['reason']}")
    return 0


# ------------------------------------------------------------------------------------------------
# calibrate-mount
# ------------------------------------------------------------------------------------------------
def _posed_frames(path: str, use_kinematics: bool) -> tuple[list, Any, Any]:
    """The frames of a capture that can be read and have a usable flange pose, their base_T_flange (n, 4, 4), and the
    others counted by why (a bad frame is skipped and counted, as calibrate and evaluate do, not the end of the fit)."""
    from collections import Counter

    import numpy as np

    from place_safe.calibration.mount import FlangePoseError, flange_poses
    from place_safe.exceptions import FrameError
    from place_safe.io.frame_file import iter_frames
    from place_safe.robot.kinematics import Kinematics

    kin = Kinematics() if use_kinematics else None
    frames, poses, skipped = [], [], Counter()
    for f in iter_frames(path):
        if isinstance(f, FrameError):
            skipped["unreadable"] += 1
            continue
        try:
            poses.append(flange_poses([f], use_kinematics=use_kinematics, kinematics=kin)[0])
        except FlangePoseError as exc:
            skipped[exc.kind] += 1
            continue
        frames.append(f)
    return frames, np.array(poses), skipped


def _mount_hints(args: argparse.Namespace) -> str:
    """What a straight-down sweep needs of ``calibrate-mount``'s options not given (``--level`` for the mount's tilt,
    and with it ``--table-height`` for its height: the plane's tilt and height trade against them), as "; a ...";
    '' when both were given."""
    if not args.level:
        return "; a straight-down sweep needs --level for the tilt and, with it, --table-height for the height"
    return "" if args.table_height is not None else "; a straight-down sweep needs --table-height for the height"


def cmd_calibrate_mount(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from place_safe.calibration.mount import MIN_SIGMA_ANGLE, MIN_SIGMA_DISTANCE, fit_mount
    from place_safe.drivers.ur5.config import FrameConfig

    if args.force and not args.write:
        raise UsageError("calibrate-mount: --force goes with --write")
    for flag, value, floor, unit in (("--sigma-angle", args.sigma_angle, math.degrees(MIN_SIGMA_ANGLE), "deg"),
                                     ("--sigma-mm", args.sigma_mm, MIN_SIGMA_DISTANCE * 1000, "mm")):
        if value < floor:  # (the parser bounds them above and at 0: the fit's own floor is known here)
            raise UsageError(f"calibrate-mount: {flag} {value:g} is below the smallest per-frame noise the fit takes "
                             f"({floor:.2g} {unit}): it weighs each frame's residuals")
    robot_cfg = _robot_config(args.robot)
    truth = _mount_truth(args.truth) if args.truth else None  # every input checked before the fit runs
    frames, F, skipped = _posed_frames(args.capture, args.poses == "joints")
    if not frames:
        raise UsageError(f"calibrate-mount: {args.capture} has no frames with a usable flange pose"
                         + (f" ({count_note(skipped)})" if skipped else ""))
    # counted twice, a repeat halved every direction's stated variance: each measurement once
    frames, repeats, keep = without_repeats(frames, "counting the frames with a usable flange pose from 0")
    F = F[keep]
    if repeats is not None and not args.quiet:
        log(f"calibrate-mount: {args.capture}: {repeats}")
    if skipped and not args.quiet:
        log(f"calibrate-mount: {len(frames)} frames ({count_note(skipped)})")
    estimator, cal_note, cal = _estimator(args.method, args.calibration)
    calibrated = uncalibrated_reason(args.method, cal) is None
    planes = [estimator.estimate(f).plane for f in tqdm(frames, desc="planes", unit="frame", file=sys.stderr,
                                                        disable=None if not args.quiet else True)]
    start = robot_cfg.tool.sensor.matrix()
    fit = fit_mount(F, planes, start, sigma_angle=math.radians(args.sigma_angle), sigma_distance=args.sigma_mm / 1000,
                    level=args.level, plane_offset=args.table_height)
    if fit.determines_nothing:  # the "fit" is the starting mount: an error before any output, no file written
        raise CalibrationError(f"calibrate-mount: {args.capture} determines none of the mount's six parameters: poses "
                               "tilted at several azimuths would (capture's default --incidences 0,12,24 --azimuths "
                               "every 60)" + _mount_hints(args)
                               + ("; the robot file is not written" if args.write else ""))
    if not calibrated:  # the first line of the output (printed once the fit succeeded: an error prints nothing)
        print(uncalibrated_note(args.method, cal, args.calibration))
    # frames without joint angles are posed by their recorded pose (mount.flange_poses): said, not "from joints"
    recorded = sum(f.extra.get("joint_angles") is None for f in frames) if args.poses == "joints" else 0
    posed = (f"joints ({recorded} of {len(frames)} frames without joint angles: from their recorded pose)" if recorded
             else args.poses)
    print(mark(f"{args.capture}: {sum(p is not None for p in planes)}/{len(frames)} frames with a plane "
               f"({args.method}, calibration: {cal_note}); flange poses from {posed}", calibrated))
    print(fit.summary())
    result = {"capture": args.capture, "method": args.method, "calibration": cal_note, "calibrated": calibrated,
              "poses": args.poses,
              **fit.to_dict()}
    if truth is not None:
        et, er = fit.error_to(truth)
        result["error_to_truth"] = {"translation": et, "rotation": er}
        print(f"  error to the true mount: {et * 1000:.2f} mm, {math.degrees(er):.3f} deg")
    if args.json:
        _write_json(args.json, result)
    if args.write:
        if (poor := fit.quality_problem()) is not None:  # the report above is printed either way
            if not args.force:
                kept = "left untouched" if Path(args.write).exists() else "not written"
                log(f"{PROG}: error: calibrate-mount: not writing a fit with {poor}: {args.write} {kept} (check the "
                    "capture and the sensor's calibration; --force writes it anyway)")
                return 1
            log(f"calibrate-mount: writing a fit with {poor} (--force)")
        robot_cfg.tool.sensor = FrameConfig.from_matrix(fit.flange_T_sensor)
        robot_cfg.tool.mount_fit = {"capture": str(args.capture), "method": args.method,
                                    "frames": fit.frames, "rms_angle_deg": math.degrees(fit.rms_angle),
                                    "rms_distance_mm": fit.rms_distance * 1000,
                                    "sigma_xyz_mm": [float(v) * 1000 if v == v else -1.0 for v in fit.sigma_xyz],
                                    "sigma_rot_deg": [math.degrees(v) if v == v else -1.0 for v in fit.sigma_rot],
                                    "unobserved": list(fit.unobserved)}  # sigma -1: held (unobserved)
        start = args.robot or _packaged_path("sim")  # the file the mount was read from: its comments and layout stay
        Path(args.write).write_text(robot_cfg.to_toml(like=start), encoding="utf-8")
        log(f"wrote the fitted mount into {args.write}" + ("" if args.robot else
            " (started from the simulated arm's robots/ur5/sim.toml, host 127.0.0.1: for the real arm give --robot "
            "with its robot file)"))
    return 0


# ------------------------------------------------------------------------------------------------
# registration
# ------------------------------------------------------------------------------------------------
def _robot_or_sim(sub, name: str, func, help: str, description: str, examples: list[str], robot_help: str,
                  *more, **changes) -> argparse.ArgumentParser:
    """A command that runs on the arm (--robot) or in MuJoCo (--sim): the choice, the sensor and the
    simulation's options, then ``more`` (:func:`place_safe.cli.options.add`)."""
    p = options.command(sub, name, lambda a: func(_resolve(a)), help, description, examples)
    options.add(p.add_mutually_exclusive_group(required=True),
                opt("--sim", metavar="SCENARIO", help="run in MuJoCo on a scenario (file or packaged name)"),
                opt("--robot", metavar="ROBOT.toml", help=robot_help))
    options.add(p, opt("--sensor", metavar="URI", help="sensor URI on the arm (i2c:/dev/i2c-1@0x41, "
                                                     "serial:/dev/ttyACM0, file:frames.json, emu:synthetic); the "
                                                     "sensor options below apply to i2c: and emu:"),
                opt("--dry-run", action="store_true", help="on the arm: receive-only, print the planned motion, "
                                                         "command nothing"),
                opt("--sim-mount-error", type=_mount_error, metavar="DX,DY,DZ,RX,RY,RZ",
                    help="simulation: the true sensor mount differs from the robot file's by this (mm and deg)"),
                "seed", *more, seed={"default": None, "help": "simulated sensor noise seed (default 0)"}, **changes)
    options.add_sensor_options(p)
    return p


def register(subparsers: argparse._SubParsersAction) -> None:
    _robot_or_sim(
        subparsers, "place", cmd_place, "put the held cup down (or refuse) on the UR5 or in MuJoCo",
        "Run one placement with the PlacementLoop: approach, descend, check the surface with the TMF8820, release or "
        "refuse. The same loop drives the UR5 (--robot, over ur_rtde) and the simulated arm (--sim SCENARIO: the "
        "scenario's table, sensor and calibration; the result also says what happened to the cup and the liquid). "
        "Writes the transition log and a result JSON either way; exit status 0 released, 1 refused or timed out, 2 "
        "bad input.",
        ["place-safe place --sim place_level   # the simulated unit's own calibration (one from another unit misreads it)",
         "place-safe place --sim place_level --robot-file robots/ur5/sim.toml --method peak",
         "place-safe place --robot robots/ur5/real.toml --sensor i2c:/dev/i2c-1 --calibration cal.json --dry-run",
         "place-safe place --robot robots/ur5/real.toml --sensor i2c:/dev/i2c-1 --calibration cal.json",
         "place-safe place --robot mine.toml --sensor i2c:/dev/i2c-1@0x41 --calibration-dir sensorcal \\\n"
         "      --int-line /dev/gpiochip0:17 --calibration cal.json   # factory calibration, the INT line"],
        f"robot file of the real UR5: {ROBOT_FILE_HELP}",
        "robot_file", "calibration",
        opt("--oracle", action="store_true", help="with --sim, DEBUGGING: give the estimator the simulator's true "
                                                "parameters (named ORACLE in the result)"),
        "method",
        opt("--config", metavar="PLACEMENT.json", help="placement thresholds (SI units; default with --sim: the "
                                                     "scenario's)"),
        opt("--timeout", type=float_range(0.0, 3600.0, lo_open=True), default=30.0,
            help="s of robot (or simulated) time (default 30, at most 3600)"),
        opt("--render", metavar="PNG", help="with --sim: write a PNG of the final scene"),
        opt("--json", default="place-result.json", help="result file (default place-result.json)"),
        opt("--log", default="place-transitions.jsonl", help="transition log (default place-transitions.jsonl)"),
        opt("--frame-log", action="store_true", help="include the per-frame log in the result file"),
        opt("--uncalibrated", action="store_true",
            help="on the arm: run without --calibration, on built-in constants (another unit's: they read a level "
                 "table degrees off, so expect refusals); without it the arm needs a calibration"),
        calibration={"metavar": "CAL.json",
                     "help": "sensor calibration; with --sim also 'sim' or 'none' (default: the scenario's, normally "
                             "the packaged simulated user calibration). Without one the placement refuses in "
                             "simulation; on the arm it is required (a dry run, or --uncalibrated, runs on built-in "
                             "constants, and the output says UNCALIBRATED before anything moves)"},
        method={"default": None, "choices": CALIBRATE_METHODS,
                "help": "plane recovery (default diff; with --sim the scenario's)"})

    capture = _robot_or_sim(
        subparsers, "capture", cmd_capture, "robot-driven sweep of sensor poses above a plane (for calibration)",
        "Drive the arm through distances x incidence x azimuth above a plane and write every frame with its "
        "ground-truth plane, flange pose and joint angles (JSON Lines, the shared frame format). The plane: --touch "
        "(the TCP touches it at 3+ points, slow guarded descent: speedL + force threshold, CB3-compatible), "
        "--table-height, or in simulation the scenario's table. Resumable: rerun with the same output to continue. "
        "Poses the robot's limits refuse, and poses that would bring the TCP, the flange or the sensor within "
        "--min-clearance of the plane (checked before moving: the gripper's tips reach past the sensor), are skipped "
        "and listed once, with the result on standard output (--dry-run lists them without moving the arm).",
        ["place-safe capture --sim level_table --poses 60 -o sim_capture.jsonl",
         "place-safe capture --sim level_table --sim-mount-error 5,0,0,0,2,0 -o perturbed.jsonl",
         "place-safe capture --robot robots/ur5/real.toml --sensor i2c:/dev/i2c-1 \\\n"
         "      --touch -0.45,-0.05 --touch -0.55,-0.05 --touch -0.5,-0.15 --touch-height 0.05 -o lab.jsonl",
         "place-safe capture --robot robots/ur5/real.toml --sensor i2c:/dev/i2c-1 --table-height 0.02 \\\n"
         "      --table-tilt-std 0.1 --incidences 0 --azimuths 0 --distances 10:90:2,100:400:10 \\\n"
         "      -o level_sweep.jsonl   # for calibrate: the table levelled to about 0.1 deg"],
        f"robot file of the real UR5: {ROBOT_FILE_HELP}",
        "output", "robot_file",
        opt("--distances", type=_distances, default=[80, 120, 170, 220, 270],
            help="sensor-to-plane distances in mm, numbers or START:STOP:STEP ranges (default 80,120,170,220,270; "
                 "a level sweep for calibration: 10:90:2,100:400:10 with --incidences 0 --azimuths 0, the 2 mm "
                 "steps below 9 cm so that calibrate sizes the near-range covariance at a new frame's gap; the "
                 "distances the gripper cannot reach are refused and listed)"),
        opt("--incidences", type=lambda s: _distinct(_floats(s, None, "degrees", 0.0, 80.0), s, "deg"),
            default=[0, 12, 24],
            help="optical-axis tilts from the normal in degrees (default 0,12,24)"),
        opt("--azimuths", type=lambda s: _distinct(_floats(s, None, "degrees", -360.0, 360.0), s, "deg", 360.0),
            default=[0, 60, 120, 180, 240, 300],
            help="tilt directions in degrees (default every 60)"),
        opt("--poses", type=int_range(1, 10_000), help="subsample the grid evenly to this many poses (1..10000)"),
        opt("--frames-per-pose", type=int_range(1, 100), default=1, help="frames per pose (default 1, at most 100)"),
        opt("--speed", field="place_safe.calibration.capture:SweepPlan.speed", default=0.1,
            what="moveL speed between poses, default 0.1"),
        opt("--settle", type=float_range(0.0, 60.0, lo_open=True), default=0.25,
            help="s at rest before frames count (default 0.25, at most 60)"),
        opt("--min-clearance", type=float_range(0.0, 100.0), default=MIN_CLEARANCE * 1000, metavar="MM",
            help="mm the TCP (the gripper's tips), the flange and the sensor must stay above the plane: closer "
                 f"poses are refused (never moved to) and listed with the result (default {MIN_CLEARANCE * 1000:g}; the near end "
                 "of a level sweep is set by how far the tips reach past the sensor)"),
        "table_height",
        opt("--table-tilt-std", type=float_range(0.0, 5.0), metavar="DEG",
            help="with --table-height: how far the table may be from level in the robot's base frame, one standard "
                 "deviation in degrees (e.g. 0.1 for a table and a robot base each levelled by a spirit level). It goes "
                 "with the capture into the calibration (its 'reference') and a placement adds it to the fused tilt's "
                 "uncertainty once: no number of frames averages it away. Default: the table is taken as exactly level. "
                 "--touch states its own (0.1 mm per contact)"),
        "quiet",
        output={"required": True, "metavar": None, "help": "capture file (JSON Lines; appended to when resuming)"},
        robot_file={"help": "with --sim: the robot file whose tool frames the loop believes and whose speed, "
                            "acceleration and force limits and [motion] the simulated arm takes (default sim.toml)"},
        table_height={"metavar": None, "help": "known table top z in the base frame (m); with --sim it must be the "
                                               f"scenario's (within {SIM_TABLE_HEIGHT_TOL * 1000:g} mm), which is "
                                               "the default"},
        quiet={"help": "no progress bar"})
    options.add(capture.add_argument_group(
        "the plane by touching it (the touched table as reference; instead of --table-height)"),
        opt("--touch", type=_xy_points, action="append", metavar="X,Y",
            help="a point (x,y in m, the robot's base frame) where the TCP touches the table; give it 3 to 20 times, "
                 f"spread wide. At each point the arm moves to --touch-height, descends at "
                 f"{_TOUCH['speed'] * 1000:g} mm/s until the contact force exceeds --touch-force (no contact within "
                 f"{_TOUCH['max_depth'] * 1000:g} mm stops the capture) and retracts {_TOUCH['retract'] * 1000:g} mm. "
                 "The plane through the contacts is every frame's ground truth; how far it may be off (each contact "
                 f"{TOUCH_HEIGHT_STD * 1000:g} mm, 1 sigma: three touches 8 cm apart fix its tilt to 0.12 deg, "
                 "wider apart less) goes with the capture into the calibration's 'reference', which a placement adds "
                 "once to the fused tilt's uncertainty. Not with --dry-run (it moves the arm)"),
        opt("--touch-height", type=float_range(-REACH, REACH), metavar="Z",
            help="m: base-frame z of the TCP where each touch's descent starts, a few cm above the table (default: "
                 "the TCP's height when the capture starts)"),
        opt("--touch-force", type=float_range(0.0, 200.0, lo_open=True), default=None,
            metavar="N", help=f"N: the contact force that ends a touch's descent (default {_TOUCH['force_threshold']:g}, "
                              "at most 200): well above the controller's force noise at rest (CB3 about 3.6 N per "
                              "cycle; place-safe bench robot measures it), well below its protective stop"))

    options.command(
        subparsers, "calibrate-mount", cmd_calibrate_mount, "fit the sensor mount (flange_T_sensor) from a capture",
        "Estimate every frame's plane, then fit flange_T_sensor (6 DoF) and the plane in the base frame to all frames "
        "at once by nonlinear least squares on forward kinematics. Prints the fit, its residuals and 1-sigma "
        "uncertainty, flags directions the sweep does not observe, and with --write saves a robot file with the "
        "fitted mount. A capture that determines none of the six (a straight-down sweep without --level) is an error "
        "that says which poses and options would.",
        ["place-safe calibrate-mount sim_capture.jsonl --robot robots/ur5/sim.toml --calibration "
         "sim/sensors/calibration_nominal.json --write robot_fitted.toml",
         "place-safe calibrate-mount tests/data/tmf8820_ur5_sweep.json --method peak --calibration cal.json --level"],
        opt("capture", help="capture or sweep file (frames with joint_angles or pose)"),
        opt("--robot", metavar="ROBOT.toml", help="robot file with the starting mount (default sim.toml); "
                                                 f"{ROBOT_FILE_HELP}"),
        "method", "calibration",
        opt("--poses", choices=("joints", "recorded"), default="joints",
            help="flange poses from forward kinematics of the joint angles (default) or the recorded pose"),
        opt("--sigma-angle", type=float_range(0.0, 90.0, lo_open=True), default=1.0,
            help="per-frame normal noise, deg (weighting; at most 90)"),
        opt("--sigma-mm", type=float_range(0.0, 1000.0, lo_open=True), default=2.0,
            help="per-frame distance noise, mm (weighting; at most 1000)"),
        opt("--level", action="store_true", help="the plane is level (normal = base z): needed to see the mount's tilt "
                                               "from a straight-down sweep"),
        "table_height",
        opt("--truth", help="JSON with the true flange_T_sensor (simulation): report the error to it"),
        "json",
        opt("--write", metavar="ROBOT.toml", help="write the robot file with the fitted mount here; a fit whose "
                                                  "residual RMS exceeds the limits of a good fit (the refusal names "
                                                  "them) is not written: exit 1, the file left untouched"),
        "force", "quiet",
        method={"choices": CALIBRATE_METHODS, "help": "per-frame planes"},
        calibration={"metavar": "CAL.json", "help": "sensor calibration for the method"},
        table_height={"help": "the plane's known base-frame z (m): needed to see the mount's height from a "
                              "straight-down sweep"},
        json={"metavar": None, "help": "write the fit (with per-frame residuals) here"},
        force={"help": "with --write: write the fitted mount even when its residuals exceed the limits"},
        quiet={"help": "no progress bar"})


def _resolve(args: argparse.Namespace) -> argparse.Namespace:
    """--robot is the arm's file; in simulation --robot-file names the file whose tool frames are used. An option of
    the arm given with --sim (--sensor, --dry-run, a sensor option) is a usage error: the simulated placement ran and
    released without a word about it; so is one of the simulation's given with --robot (--robot-file,
    --sim-mount-error, --seed)."""
    if args.sim:
        given_options = [(f"--{name.replace('_', '-')}", getattr(args, name, None)) for name in options.SENSOR_OPTIONS]
        for flag, given in (("--sensor", getattr(args, "sensor", None)), ("--dry-run", getattr(args, "dry_run", False)),
                            *given_options):
            if given is not None and given is not False:
                raise UsageError(f"{args.command}: {flag} is for the arm (--robot ROBOT.toml), not --sim: the simulation "
                                 "has its own sensor and moves nothing real")
        args.robot = getattr(args, "robot_file", None)
    else:  # the simulation's options on the arm: never read (the run went on to connect as if they were not given)
        for flag, given in (("--robot-file", args.robot_file), ("--sim-mount-error", args.sim_mount_error),
                            ("--seed", args.seed)):
            if given is not None:
                raise UsageError(f"{args.command}: {flag} is for the simulation (--sim SCENARIO)")
    if args.seed is None:
        args.seed = 0
    return args


__all__ = ["register", "open_sensor", "cmd_place", "cmd_capture", "cmd_calibrate_mount"]
