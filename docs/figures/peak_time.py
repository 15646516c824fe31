"""Peak's estimate, CPU time a frame, of this checkout against another commit (issue 24: "peak no slower than now",
now being the code the issue was filed on, ``15981dc``), alternated in fresh processes on the same frames.

    python docs/figures/peak_time.py                          # against 15981dc, 8 rounds (about 3 minutes)
    python docs/figures/peak_time.py --against HEAD~3 --rounds 12

The frames: the real sweep's odd half repeated 20 times (520 frames); each code reads them with a peak calibration of
the even half made by its own ``calibrate``. A measurement is the best of 9 passes of ``Estimator.estimate`` over the
frames, parsed beforehand, in ``time.process_time`` (CPU of this process, not wall: a shared host's neighbours move
wall time more). The other commit is checked out with ``git worktree add --detach`` under ``--work`` (the temporary
folder by default; kept for reruns). Prints each code's measurements, sorted, with their minimum and median: where
neighbours move a measurement by 5-10 %, compare the minima and medians of many rounds, not one pair.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SWEEP = ROOT / "tests" / "data" / "tmf8820_ur5_sweep.json"
FILING = "15981dc"  # issue 24 filed (2026-11-24)
PASSES = 9
REPEAT = 20


def one(checkout: Path, cal: Path, frames: Path) -> float:
    """Best of PASSES passes, CPU seconds a frame, of the peak estimate of ``frames`` with ``cal`` (run in a process
    whose ``sys.path`` starts with ``checkout``)."""
    from place_safe.calibration import Calibration
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    loaded = load_frames(str(frames))
    est = make_estimator("peak", Calibration.load(str(cal)))
    best = float("inf")
    for _ in range(PASSES):
        t = time.process_time()
        for f in loaded:
            est.estimate(f)
        best = min(best, (time.process_time() - t) / len(loaded))
    return best


def run(checkout: Path, work: Path, *args: str) -> subprocess.CompletedProcess:
    """``python ARGS`` with ``checkout``'s place_safe, run in ``work`` (``-m`` puts the current folder first on
    the path)."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_NUM_THREADS": "1"}
    return subprocess.run([sys.executable, *args], env=env, cwd=work, capture_output=True, text=True, check=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], epilog=__doc__.split("\n\n", 1)[1],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--against", default=FILING, help=f"the commit to compare with (default {FILING}, issue 24 filed)")
    ap.add_argument("--rounds", type=int, default=8, help="alternated rounds (default 8)")
    ap.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "place_safe_peak_time",
                    help="frames, calibrations and the other commit's worktree (default: in the temporary folder)")
    ap.add_argument("--one", nargs=2, metavar=("CHECKOUT", "CAL"), help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    work = args.work
    if args.one:
        print(one(Path(args.one[0]), Path(args.one[1]), work / "odd20.json"))
        return 0
    work.mkdir(parents=True, exist_ok=True)
    sweep = json.loads(SWEEP.read_text())
    (work / "even.json").write_text(json.dumps(sweep[0::2]))
    (work / "odd20.json").write_text(json.dumps(sweep[1::2] * REPEAT))
    other = work / f"tree-{args.against}"
    if not (other / "place_safe").is_dir():  # (not there yet, or left by a worktree git has since pruned)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "prune"], check=True, capture_output=True)
        if other.exists():
            shutil.rmtree(other)
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(other), args.against], check=True,
                       capture_output=True)
    codes = {"this checkout": ROOT, args.against: other}
    cals = {}
    for name, checkout in codes.items():
        cals[name] = work / f"cal-{checkout.name}.json"
        cals[name].unlink(missing_ok=True)  # (each code's own calibrate; an older one may not know --force)
        run(checkout, work, "-m", "place_safe", "calibrate", str(work / "even.json"), "--method", "peak", "-o",
            str(cals[name]))
    seen: dict[str, list[float]] = {name: [] for name in codes}
    for r in range(args.rounds):
        for name, checkout in codes.items():
            out = run(checkout, work, str(Path(__file__).resolve()), "--work", str(work), "--one", str(checkout),
                      str(cals[name]))
            seen[name].append(float(out.stdout.strip()) * 1e6)
        print(f"round {r + 1}/{args.rounds}: " + ", ".join(f"{n} {v[-1]:.0f} us" for n, v in seen.items()),
              file=sys.stderr)
    for name, values in seen.items():
        print(f"{name:>16}: min {min(values):.0f} us, median {statistics.median(values):.0f} us a frame "
              f"({' '.join(f'{v:.0f}' for v in sorted(values))})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
