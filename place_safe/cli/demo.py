"""``place-safe demo``: the main job on a fresh machine (a simulated placement, or recovery of synthetic
frames when the simulation is not installed)."""

from __future__ import annotations

import argparse
import importlib.util

from place_safe.cli import options
from place_safe.cli.common import log, uncalibrated_note
from place_safe.evaluation.bench import run_bench

# ------------------------------------------------------------------------------------------------
# demo (the main job)
# ------------------------------------------------------------------------------------------------
#: Demo placements: (scenario, the outcome a safe placement must have).
DEMO_SCENARIOS = (("place_level", "released"), ("place_tilted", "refused"))


def _placement_available() -> str | None:
    """None when the simulated placement can run, else why not."""
    if importlib.util.find_spec("mujoco") is None:
        return "MuJoCo is not installed (install the [sim] extra)"
    try:
        from place_safe.sim import placement_run  # noqa: F401
    except ImportError as exc:
        return f"the simulation is not available ({exc})"
    return None


def cmd_demo(args: argparse.Namespace) -> int:
    """The main job: simulated placements (level table: release; tilted table: refuse). Without the
    simulation (or with --synthetic): recover synthetic frames with every method and score them."""
    why_not = None if args.synthetic else _placement_available()
    if not args.synthetic and why_not is None:
        from place_safe.sim.placement_run import run_placement

        ok = True
        if args.method == "diff":
            log("demo: NOTE: diff uses the simulated USER calibration (a simulated level-table sweep fitted "
                 "with 'place-safe calibrate'), not the simulator's true parameters; see 'place-safe place --help'")
        for scenario, expected in DEMO_SCENARIOS:
            if not args.quiet:
                log(f"demo: simulated UR5 placing a cup, scenario {scenario} (expected: {expected}) ...")
            res = run_placement(scenario, method=args.method, seed=args.seed)
            print(res.summary(), flush=True)
            good = res.outcome == expected
            ok &= good
            print(f"-> {scenario}: {res.outcome} ({'as expected' if good else 'EXPECTED ' + expected})\n", flush=True)
        return 0 if ok else 1
    from place_safe.evaluation.synthetic import make_frames

    if why_not and not args.quiet:
        log(f"demo: no simulated placement: {why_not}; showing plane recovery on synthetic frames instead")
    if not args.quiet:
        log(f"demo: {args.frames} synthetic frames (forward model with shot noise, planes 2-30 cm, "
             "up to 30 deg incidence); recovering them with each method ...")
    frames = make_frames(args.frames, seed=args.seed)
    runs = [("diff-fast", "diff", {"mode": "fast"}), ("peak", "peak", {}), ("peak-naive", "peak-naive", {}),
            ("proprietary", "proprietary", {}), ("proprietary-naive", "proprietary-naive", {})]
    report = run_bench(frames, None, runs=runs, source="synthetic frames", progress=not args.quiet)
    # the synthetic frames are drawn with the built-in constants; the first line still says they ran uncalibrated
    print(uncalibrated_note([r[1] for r in runs], None, advice="The demo shows them so on purpose: its synthetic frames "
                            "come from those constants (place-safe calibrate and recover --calibration fit and use "
                            "a unit's own)"), flush=True)
    print(report.table(), flush=True)
    return 0


def register(sub) -> None:
    """Add demo to the ``place-safe`` sub-parsers."""
    options.command(
        sub, "demo", cmd_demo, "run the main job (no data or hardware needed)",
        "The main job on a fresh machine: a simulated UR5 puts a cup down on a level table (it must release) and over "
        "a tilted one (it must refuse), sensing the table with the simulated TMF8820. Exit status 1 if either outcome "
        "is wrong. Without the [sim] extra, or with --synthetic: recover synthetic frames with every method and print "
        "their errors and speed side by side.",
        ["place-safe demo", "place-safe demo --method peak", "place-safe demo --synthetic --frames 10"],
        "method",
        options.opt("--synthetic", action="store_true", help="show recovery on synthetic frames, no simulation"),
        "frames", "seed", "quiet",
        method={"help": "plane recovery in the placement (default diff)"},
        frames={"default": 20, "help": "synthetic frames (default 20)"},
        seed={"help": "seed of the synthetic frames and the placements"})
