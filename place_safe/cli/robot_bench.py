"""``place-safe bench robot``: measure the arm's force noise at rest; ``bench contact``: the contact detector
against it.

* ``bench robot --robot ROBOT.toml [--write]``: connect (receive, control; nothing moves), sample the TCP
  force at rest for ``--seconds``, print its offset and spread per axis, the detector setting that follows
  (:mod:`place_safe.robot.contact_detector`) and that setting's false-alarm rate and detection delays on
  noise of the measured spread; ``--write`` stores ``[contact] noise_std`` (and what was measured) in the
  robot file. ``--fake`` runs the same on the fake ur_rtde controller (CB3 noise by default).
* ``bench contact``: placements from 40 cm through URRobot on the fake CB3 (false contacts, outcomes,
  watchdog stops, script errors) and guarded touches of the table (delay, force at detection).

Parsing and printing only; the work is in :mod:`place_safe.evaluation.contact`.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from place_safe.cli.common import ROBOT_FILE_HELP, flags_said, log
from place_safe.cli import options
from place_safe.cli.options import float_range, int_range, opt
from place_safe.evaluation.contact import DESCENT_HEIGHT, DESCENT_JOBS, DESCENT_SEED, TOUCH_STIFFNESS
from place_safe.geometry import MAX_REACH
from place_safe.exceptions import UsageError
from place_safe.io.json_values import jsonable


#: Descents or touches per speed ``bench contact`` may ask for (200 descents take minutes).
MAX_TRIALS = 100_000
#: s at rest ``bench robot`` may sample (the UR's RTDE gives 125-500 samples a second).
MAX_SAMPLE_SECONDS = 3600.0
#: N/m the simulated table contact may be (steel on steel is about 1e8).
MAX_STIFFNESS = 1e8
#: The default of ``bench robot --controller`` (the fake's), an option only one part of the bench reads (None on the
#: command line: not given, which the part's absence requires). ``bench contact``'s descents' ``--height``, ``--seed``
#: and ``--jobs`` and its touches' ``--stiffness`` are filled in the same way with their functions' own defaults
#: (:mod:`place_safe.evaluation.contact`).
FAKE_CONTROLLER = "cb3"


def unread_contact_options(args: argparse.Namespace) -> str | None:
    """The usage error of a ``bench contact`` option of a part not run, or None: ``--descents 0`` runs no descent
    (``--height``, ``--seed``, ``--jobs`` unread), ``--touch-trials 0`` no touch (``--stiffness`` unread). Both printed
    the detector's report and exited 0 without a word."""
    for part, runs, given in (
            ("--descents", args.descents, [flag for flag, v in (("--height", args.height), ("--seed", args.seed),
                                                                  ("--jobs", args.jobs)) if v is not None]),
            ("--touch-trials", args.touch_trials, ["--stiffness"] if args.stiffness is not None else [])):
        if not runs and given:
            return f"bench contact: {flags_said(given, 'goes', 'go')} with {part}, and {part} 0 runs none"
    return None


def cmd_bench(args: argparse.Namespace) -> int:
    import numpy as np

    from place_safe.drivers.ur5 import URConfig, URRobot
    from place_safe.evaluation.contact import format_settings_report, make_stand_in, rest_noise, settings_report

    target = Path(args.write) if args.write else None
    if target is not None and not args.robot and not target.is_file():  # checked before the measurement
        raise UsageError("bench robot --write: give --robot ROBOT.toml to start the written file from")
    if args.controller is not None and not args.fake:  # (the arm's is its robot file's: it was never read)
        raise UsageError("bench robot: --controller is the fake controller's (with --fake); the arm's is its robot "
                         "file's [connection] controller")
    if args.fake:
        path = Path(args.robot) if args.robot else None
        if path is not None:  # read and checked before the measurement, as without --fake (it went unread: any
            URConfig.load(path)  # file, even a missing one, passed; an adversarial round, session 74)
        robot, _ = make_stand_in(args.controller or FAKE_CONTROLLER, host="127.0.0.1")
        cfg = robot.config
    else:
        if not args.robot:
            raise UsageError("bench robot: --robot ROBOT.toml is required (or --fake for the stand-in)")
        path = Path(args.robot)
        cfg = URConfig.load(path)
        robot = URRobot(cfg)
    controller = cfg.connection.controller
    with robot:
        offset, spread = rest_noise(robot, args.seconds)
    sigma = float(np.max(spread))
    print(f"{'fake ' if args.fake else ''}{controller} at {cfg.connection.host}: TCP force at rest over "
          f"{args.seconds:g} s: offset {np.round(offset, 2).tolist()} N, spread {np.round(spread, 2).tolist()} N "
          "per axis per cycle")
    settings = cfg.contact.settings(controller).__class__.for_controller(
        controller, **{**{k: getattr(cfg.contact, k) for k in ("window", "sigmas", "persistence", "min_threshold",
                                                                 "lateral_sigmas")}, "noise_std": round(sigma, 2)})
    rep = settings_report(settings, sigma, cycles=args.cycles)
    print(format_settings_report(rep))
    if target is not None:
        source = path if path is not None else target  # the robot file given, else the one written to
        base = URConfig.load(source)
        base.contact.noise_std = round(sigma, 2)
        base.contact.measured = {"seconds": float(args.seconds), "offset_n": [round(float(v), 3) for v in offset],
                                 "std_n": [round(float(v), 3) for v in spread], "controller": controller,
                                 "threshold_n": round(rep["threshold"], 2)}
        target.write_text(base.to_toml(like=source), encoding="utf-8")  # its comments and layout kept
        log(f"wrote [contact] noise_std = {sigma:.2f} N to {target}")
    if args.json:
        Path(args.json).write_text(json.dumps({"offset": offset.tolist(), "spread": spread.tolist(), **rep},
                                              indent=1) + "\n", encoding="utf-8")
    return 0


def cmd_contact_bench(args: argparse.Namespace) -> int:
    from place_safe.evaluation.contact import descents, format_settings_report, settings_report, touches
    from place_safe.robot.contact_detector import DetectorSettings
    from place_safe.drivers.ur5.fake_rtde import FORCE_NOISE

    if (unread := unread_contact_options(args)) is not None:
        raise UsageError(unread)
    for name, default in (("height", DESCENT_HEIGHT), ("seed", DESCENT_SEED), ("jobs", DESCENT_JOBS),
                          ("stiffness", TOUCH_STIFFNESS)):
        if getattr(args, name) is None:
            setattr(args, name, default)
    noise = args.noise if args.noise is not None else FORCE_NOISE[args.controller]
    settings = DetectorSettings.for_controller(args.controller)
    out: dict = {"controller": args.controller, "noise_std": noise}
    rep = settings_report(settings, noise, cycles=args.cycles)
    print("detector on synthetic noise:")
    print(format_settings_report(rep))
    out["settings"] = rep
    if args.touch_trials:
        rows = touches(controller=args.controller, trials=args.touch_trials, force_noise=noise,
                       stiffness=args.stiffness)
        print(f"guarded touches of the table through URRobot on the fake {args.controller} (table stiffness "
              f"{args.stiffness:.0f} N/m), {args.touch_trials} each:")
        for r in rows:
            print(f"  {r['speed'] * 1e3:4.0f} mm/s ({r['rate']:.0f} N/s): contact after {r['delay_median'] * 1e3:.0f} ms "
                  f"median / {r['delay_max'] * 1e3:.0f} ms worst, true force {r['force_median']:.1f} N median / "
                  f"{r['force_max']:.1f} N worst; missed {r['missed']}")
        out["touches"] = rows
    if args.descents:
        progress = None if args.quiet or args.jobs > 1 else (
            lambda i, r: log(f"  {i}/{args.descents}: false contacts {r.false_contacts}, {r.outcomes}"))
        d = descents(args.descents, height=args.height, controller=args.controller, seed=args.seed,
                     force_noise=noise, jobs=args.jobs, progress=progress)
        print(d.summary())
        for why in d.reasons[:10]:
            print(f"  not released: {why}")
        out["descents"] = d.__dict__
    if args.json:
        Path(args.json).write_text(json.dumps(jsonable(out), indent=1) + "\n", encoding="utf-8")  # NaN, inf: null
    return 0


def add_robot_benches(sub: argparse._SubParsersAction) -> None:
    """``place-safe bench robot`` and ``bench contact`` on the ``bench`` sub-parsers."""
    options.command(
        sub, "robot", cmd_bench, "measure the TCP force noise at rest on a connected arm and derive the detector setting",
        "Connect to the arm (nothing moves), sample the TCP force at rest, print its spread, the contact detector's "
        "threshold and its false-alarm rate and detection delay for that noise; --write stores [contact] noise_std in "
        "a robot file.",
        ["place-safe bench robot --robot robots/ur5/real.toml",
         "place-safe bench robot --robot robots/ur5/real.toml --write my_ur5.toml",
         "place-safe bench robot --fake                # the fake ur_rtde CB3 stand-in"],
        opt("--robot", metavar="ROBOT.toml", help=f"robot file of the arm: {ROBOT_FILE_HELP}"),
        opt("--fake", action="store_true", help="measure the fake ur_rtde controller instead of an arm"),
        "controller", "seconds", "cycles",
        opt("--write", metavar="ROBOT.toml", help="write the robot file with the measured noise here"),
        "json",
        controller={"default": None, "help": f"with --fake (default {FAKE_CONTROLLER}; the arm's is its robot "
                                             "file's)"},
        seconds={"type": float_range(0.0, MAX_SAMPLE_SECONDS, lo_open=True), "default": 2.0, "metavar": None,
                 "help": f"s at rest to sample (default 2, at most {MAX_SAMPLE_SECONDS:g})"},
        json={"metavar": "OUT.json", "help": "write the measurement and the report as JSON"})
    options.command(
        sub, "contact", cmd_contact_bench,
        "false contacts over simulated 40 cm descents and touch detection on the fake CB3",
        "The contact detector against the fake controller's force noise: placements from --height through URRobot on "
        "the fake ur_rtde (false contacts, outcomes, watchdog stops, script errors), guarded touches of the table "
        "(delay and true force at detection) and the detector on synthetic noise.",
        ["place-safe bench contact --descents 200 --jobs 2", "place-safe bench contact --descents 0 --touch-trials 50",
         "place-safe bench contact --controller e-series --descents 20"],
        "controller", "noise",
        opt("--descents", type=int_range(0, MAX_TRIALS), default=200,
            help=f"placements from --height (default 200, at most {MAX_TRIALS})"),
        opt("--height", type=float_range(0.0, MAX_REACH, lo_open=True), default=None,
            help=f"m of cup above the table (default {DESCENT_HEIGHT:g}, at most the arm's {MAX_REACH:g} m)"),
        opt("--touch-trials", type=int_range(0, MAX_TRIALS), default=20,
            help=f"touches per speed (default 20, at most {MAX_TRIALS})"),
        opt("--stiffness", type=float_range(0.0, MAX_STIFFNESS, lo_open=True), default=None,
            help=f"N/m of the table contact in the touches (default {TOUCH_STIFFNESS:g}, at most {MAX_STIFFNESS:g})"),
        "cycles", "seed", "jobs", "json", "quiet",
        controller={"help": "fake controller (default cb3)"},
        noise={"what": "force noise at rest, default the controller's (3.6 / 1.0)"},
        seed={"default": None, "help": f"first seed of the descents (default {DESCENT_SEED})"},
        jobs={"default": None, "metavar": None, "help": f"worker processes for the descents (default {DESCENT_JOBS})"},
        json={"metavar": "OUT.json", "help": "write everything as JSON"}, quiet={"help": "no progress lines"})


__all__ = ["add_robot_benches", "cmd_bench", "cmd_contact_bench"]
