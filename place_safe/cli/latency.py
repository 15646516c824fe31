"""``place-safe bench latency`` (also ``place-safe latency``): per-frame wall time of ``recover`` measured from outside (a benchmark, not a test).

The figure the speed targets are stated in: a fresh ``place-safe recover --jsonl --batch 1`` process
over a frame file, each output line timestamped as it arrives; milliseconds per frame (median, p95).
"""

from __future__ import annotations

import argparse

from place_safe.exceptions import PlaceSafeError
from place_safe.cli import options
from place_safe.calibration import mark
from place_safe.cli.common import load_calibration, require_frame_file, uncalibrated_note

EPILOG = """examples:
  place-safe synth --frames 100 --seed 7 -o out/speed.json
  place-safe latency out/speed.json --method diff --calibration calib.json
  place-safe bench latency out/speed.json --method diff --calibration calib.json
  place-safe bench latency out/speed.json --method peak --json out/latency_peak.json"""


def add_latency_bench(subparsers, top_level: bool = False) -> None:
    """``place-safe bench latency`` on the ``bench`` sub-parsers, or with ``top_level`` ``place-safe latency`` (the
    same command under the name the speed targets give it)."""

    options.command(
        subparsers, "latency", cmd_latency, "per-frame wall time of `recover` measured from outside (median, p95)"
        + (" (the same as `bench latency`)" if top_level else ""),
        "Run `place-safe recover --jsonl` in a fresh process over FILE and time each output line as it arrives: the "
        "gaps are per-frame wall times as a caller sees them (parsing, recovery, output). The first line (start-up, "
        "imports) is reported apart.", EPILOG,
        options.opt("file", metavar="FILE", help="frame file (2 frames or more)"),
        "method", "calibration", "batch", "json",
        batch={"help": "frames per recovery call (default 1; larger batches make per-frame gaps bursty)"})


def cmd_latency(args: argparse.Namespace) -> int:
    import json
    from pathlib import Path

    from itertools import islice

    from place_safe.evaluation.bench import measure_recover_latency
    from place_safe.io.frame_file import iter_frames
    require_frame_file(args.file)
    # the entries (usable or not: recover writes a line for each), counted before anything is printed, so a file too
    # short to time is one error line
    if (n := sum(1 for _ in islice(iter_frames(args.file, truth=False), 2))) < 2:
        raise PlaceSafeError(f"latency: {args.file} holds {n} frame{'' if n == 1 else 's'}; it needs 2 or more (the "
                             "first line's time is start-up, the per-frame times are the gaps between lines)")
    note = uncalibrated_note(args.method, load_calibration(args.calibration), args.calibration)  # a bad file: one line
    if note is not None:
        print(note, flush=True)
    try:
        res = measure_recover_latency(args.file, args.method, args.calibration, args.batch)
    except RuntimeError as exc:
        raise PlaceSafeError(f"latency: {exc}") from None
    print(mark(f"recover --method {res['method']}: {res['frames']} frames, per frame median {res['median_ms']:.2f} ms, "
               f"p95 {res['p95_ms']:.2f} ms, mean {res['mean_ms']:.2f} ms (first line after {res['first_line_ms']:.0f} ms); "
               "method used: " + ", ".join(f"{k} {v}" for k, v in res["method_used"].items()), note is None))
    if args.json:
        Path(args.json).write_text(json.dumps({**res, "calibrated": note is None}, indent=2) + "\n")
    return 0
