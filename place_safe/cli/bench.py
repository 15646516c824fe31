"""``place-safe bench``: every benchmark of the project, one sub-command each.

* ``recovery``: speed and accuracy of the plane-recovery methods on the same frames (:mod:`place_safe.cli.sensing`);
* ``latency``: per-frame wall time of ``recover`` measured from outside (:mod:`place_safe.cli.latency`);
* ``sensor``: the TMF8820 driver over the emulated bus (:mod:`place_safe.cli.sensor`);
* ``sim``: real-time factor of MuJoCo physics and the simulated sensor in lockstep (here; needs the [sim] extra);
* ``robot`` and ``contact``: the arm's force noise at rest and the contact detector against it
  (:mod:`place_safe.cli.robot_bench`).

Benchmarks print figures anyone can rerun; tests assert behaviour, never timings.
"""

from __future__ import annotations

import argparse
import importlib.util

from place_safe.cli import options
from place_safe.cli.common import FMT, UsageError, flags_said

SUB_COMMANDS = ("recovery", "latency", "sensor", "sim", "robot", "contact")


def cmd_sim_bench(args: argparse.Namespace) -> int:
    """``bench sim``: steps the scene for ``--seconds`` of sim time and prints the real-time factor."""
    if importlib.util.find_spec("mujoco") is None:
        raise UsageError("bench sim: the simulation needs MuJoCo, which is not installed: install the [sim] extra, "
                         "e.g. pip install -e \".[sim]\"")
    from place_safe.sim.bench import bench, benchmark

    if args.bare:
        # (never read: a --scene that does not exist measured the bare robot, exit 0; --rate 1 --rays 1 the same)
        if given := [flag for flag, v in (("--scene", args.scene), ("--rig", args.rig), ("--rate", args.rate),
                                          ("--rays", args.rays)) if v is not None and v is not False]:
            raise UsageError(f"bench sim: --bare measures the bare robot, without a scene or sensor: "
                             f"{flags_said(given, 'does', 'do')} not go with it")
        for key, value in benchmark(args.seconds).items():
            print(f"{key}: {value:.1f}")
        return 0
    args.rate = SIM_RATE if args.rate is None else args.rate
    res = bench(args.scene, args.rig, args.seconds, args.rate, SIM_RAYS if args.rays is None else args.rays)
    print(f"{res['sim_seconds']:.2f} s sim in {res['wall_seconds']:.2f} s wall: real-time factor "
          f"{res['real_time_factor']:.1f}x ({res['frames']} sensor frames at {args.rate:g} Hz, "
          f"{res['physics_steps']} physics steps, {'UR5' if res['with_robot'] else 'rig'})")
    return 0


#: ``bench sim``'s sensor frame rate (Hz) and rays per axis and zone where not given (the simulated sensor's defaults;
#: None on the command line: not given, which ``--bare`` requires)
SIM_RATE = options.shared_default("rate_hz")
SIM_RAYS = options.shared_default("rays")

#: ``bench sim --help``: what it measures
SIM_BENCH_ABOUT = ("Steps the scene for --seconds of sim time with the sensor measuring at --rate Hz in lockstep and "
                   "reports the real-time factor (sim time / wall time). Target >= 5. With --bare: the bare robot's "
                   "physics alone (physics steps/s and real-time factor, holding and during a 0.1 m/s linear move). "
                   "Needs the [sim] extra.")


def add_sim_bench(sub) -> None:
    examples = ["place-safe bench sim --seconds 5 --rate 30", "place-safe bench sim --bare --seconds 2"]
    options.command(
        sub, "sim", cmd_sim_bench, "real-time factor of physics + simulated sensor in lockstep", SIM_BENCH_ABOUT,
        examples,
        options.opt("--scene", help="scene JSON (default: level table)"),
        options.opt("--rig", action="store_true", help="sensor rig only (no robot); default: the UR5 holding the cup"),
        options.opt("--bare", action="store_true", help="the bare robot without scene or sensor: physics steps/s, "
                                                        "holding and moving"),
        "seconds", "rate_hz", "rays",
        seconds={"default": 5.0, "metavar": None, "help": "sim seconds to run (default 5)"},
        rate_hz={"default": None, "what": f"sensor frame rate, default {SIM_RATE:g} (not with --bare)"},
        rays={"default": None, "what": f"stratified rays per axis and zone, default {SIM_RAYS} (not with --bare)"})


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``place-safe bench {recovery,latency,sensor,sim,robot,contact}``, and ``place-safe latency`` (the same as
    ``bench latency``)."""
    from place_safe.cli.latency import add_latency_bench
    from place_safe.cli.robot_bench import add_robot_benches
    from place_safe.cli.sensing import add_recovery_bench
    from place_safe.cli.sensor import add_sensor_bench

    p = subparsers.add_parser("bench", formatter_class=FMT, help="benchmarks: " + ", ".join(SUB_COMMANDS),
                              description="Every benchmark, one sub-command each: recovery (speed and accuracy of "
                                          "the recovery methods), latency (recover timed from outside), sensor (the "
                                          "TMF8820 driver over the emulated bus), sim (MuJoCo real-time factor), "
                                          "robot (the arm's force noise at rest) and contact (the contact detector "
                                          "on the fake CB3). Figures anyone can rerun; tests never assert timings.",
                              epilog="examples:\n  place-safe bench recovery --frames 20 --paper-frames 3\n"
                                     "  place-safe bench sensor --frames 200\n  place-safe bench sim --rig\n"
                                     "  place-safe bench contact --descents 20")
    sub = p.add_subparsers(dest="bench_command", metavar="{" + ",".join(SUB_COMMANDS) + "}", required=True)
    add_recovery_bench(sub)
    add_latency_bench(sub)
    add_sensor_bench(sub)
    add_sim_bench(sub)
    add_robot_benches(sub)
    add_latency_bench(subparsers, top_level=True)  # ``place-safe latency``: the name the speed targets use


__all__ = ["register", "cmd_sim_bench", "SUB_COMMANDS"]
