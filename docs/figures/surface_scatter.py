"""Two readings of "the surface is not one plane", measured on placements and on real frames.

    python docs/figures/surface_scatter.py scenes --kind low-boxes --count 150 --seed 1 [--only 139] [--json OUT]
    python docs/figures/surface_scatter.py scenes --set [--json OUT]
    python docs/figures/surface_scatter.py real tests/data/tmf8820_ur5_sweep.json

``scenes`` runs simulated placements (the packaged set, or random scenes of ``--kind`` numbered as
``place-safe scenarios --random N --kind K --seed S`` numbers them, with the same sensor seeds) and, at the placement's
last level check, reads

* the slope scatter: the RMS angle (deg) of the plane filter's remembered per-frame normals about their mean, and their
  tilt range: a table reads one slope from every height, planes through a box and the table beside it read a slope
  that changes as the zones move over the box;
* the close frames' fit: each frame's consensus plane fits its own zones with an RMS (mm, per degree of freedom:
  ``FrameSurfaces.rms``); over the frames within 5 cm of the lowest, its median and 10th percentile.

``real`` calibrates peak on one half of a real sweep (even / odd frames) and reads the other half's consensus RMS per
frame (level table, so the zones' own scatter about one plane).

docs/results.md, "The low-box releases left: what the frames say" (session 73: the scatter of the one released low box
under the footprint, 1.77 deg, is below the clearly safe `step_down_past_the_rim`'s 1.87; its close frames fit at
0.36-1.2 mm against up to 0.22 mm (median) on clean random scenes and 0.05-0.19 mm on real level frames at 5-40 cm).
"""
from __future__ import annotations

import argparse
import json
import math
import multiprocessing as mp
import os
import sys
import tempfile

import numpy as np

_STATS: dict = {}


def _instrument() -> None:
    """Wrap the level rule to read the filter's memory and the surface map's frames at every check."""
    import place_safe.placement.loop as loop_mod
    import place_safe.placement.rules as rules
    import place_safe.sim.placement_run as run_mod

    made = loop_mod.PlacementLoop.__init__

    def init(self, *a, **k):
        made(self, *a, **k)
        _STATS["loop"] = self

    loop_mod.PlacementLoop.__init__ = init
    run_mod.PlacementLoop.__init__ = init
    level = rules.level_problem

    def level_problem(plane, cfg):
        why = level(plane, cfg)
        loop = _STATS["loop"]
        normals = np.array([m[1] for m in loop.filter._memory]) if loop.filter._memory else np.zeros((0, 3))
        row = {"planes": len(normals), "why": why}
        if len(normals):
            mean = normals.mean(axis=0)
            mean /= np.linalg.norm(mean)
            ang = np.degrees(np.arccos(np.clip(normals @ mean, -1.0, 1.0)))
            tilts = np.degrees(np.arccos(np.clip(normals[:, 2], -1.0, 1.0)))
            row.update(scatter_deg=float(np.sqrt(np.mean(ang ** 2))), tilt_lo=float(tilts.min()),
                       tilt_hi=float(tilts.max()))
        frames = np.array([[f.base_T_sensor[2, 3], f.rms * 1e3] for f in loop.surface.frames], dtype=float)
        if len(frames):
            close = frames[frames[:, 0] <= np.nanmin(frames[:, 0]) + 0.05, 1]
            row.update(close_rms_median=float(np.nanmedian(close)), close_rms_p10=float(np.nanpercentile(close, 10)))
        _STATS["last"] = row
        return why

    rules.level_problem = level_problem


def _run(item: dict) -> dict:
    os.environ.setdefault("MUJOCO_GL", "egl")
    if "ready" not in _STATS:
        _instrument()
        _STATS["ready"] = True
    from place_safe.sim.placement_run import run_placement
    from place_safe.sim.scenario import Scenario, load_scenario
    from place_safe.sim.suite import judge

    _STATS.pop("last", None)
    src = item["scenario"]
    sc = Scenario.model_validate(src) if isinstance(src, dict) else load_scenario(src)
    row = judge(sc, run_placement(sc, seed=item["seed"], seconds=30.0, log_frames=False))
    out = {k: row[k] for k in ("name", "decision", "unsafe", "clearly_safe", "false_refusal")}
    out.update(index=item["index"], check=_STATS.get("last"))
    return out


def scenes(args: argparse.Namespace) -> None:
    from place_safe.sim import suite
    from place_safe.sim.scenario import packaged_scenarios

    if args.set:
        items = [{"scenario": str(p), "seed": i, "index": i} for i, p in enumerate(packaged_scenarios())]
    else:
        rng = np.random.default_rng(args.seed)
        drawn = [suite.RANDOM_KINDS[args.kind](rng, i) for i in range(args.count)]
        keep = args.only if args.only else range(args.count)
        items = [{"scenario": drawn[i].model_dump(), "seed": args.seed + i, "index": i} for i in keep]
    with mp.get_context("spawn").Pool(args.jobs) as pool:
        rows = list(pool.imap(_run, items))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(rows, fh, indent=1)
    print("index decision  unsafe clearly_safe  scatter_deg  tilt_range_deg  close_rms_mm(median/p10)  name")
    for r in rows:
        c = r["check"] or {}
        print(f"{r['index']:5d} {r['decision']:9s} {int(r['unsafe']):6d} {int(r['clearly_safe']):12d}  "
              f"{c.get('scatter_deg', math.nan):11.2f}  {c.get('tilt_lo', math.nan):5.2f}-{c.get('tilt_hi', math.nan):5.2f}"
              f"     {c.get('close_rms_median', math.nan):6.3f} / {c.get('close_rms_p10', math.nan):6.3f}   {r['name']}")


def real(args: argparse.Namespace) -> None:
    import subprocess

    from place_safe.calibration import Calibration
    from place_safe.fusion.surface_map import CONSENSUS_RELATIVE, SurfaceMap
    from place_safe.io.frame_file import load_frames
    from place_safe.placement.loop import peak_params_of
    from place_safe.recovery import make_estimator

    with open(args.sweep) as fh:
        sweep = json.load(fh)
    with tempfile.TemporaryDirectory() as tmp:
        halves = {}
        for name, part in (("even", sweep[0::2]), ("odd", sweep[1::2])):
            path = os.path.join(tmp, f"{name}.json")
            with open(path, "w") as fh:
                json.dump(part, fh)
            cal = os.path.join(tmp, f"cal_{name}.json")
            subprocess.run([sys.executable, "-m", "place_safe.cli", "calibrate", path, "--method", "peak", "-o", cal],
                           check=True, capture_output=True)
            halves[name] = (path, cal)
        print("calibration -> frames  z0_cm  consensus_rms_mm  inliers")
        for cal_half, test_half in (("even", "odd"), ("odd", "even")):
            est = make_estimator("peak", Calibration.load(halves[cal_half][1]))
            smap = SurfaceMap(peak_params_of(est), relative=CONSENSUS_RELATIVE)
            for f in load_frames(halves[test_half][0]):
                fs = smap.add(f, np.eye(4), 0.0)
                if fs is not None:
                    print(f"{cal_half} -> {test_half}  {f.truth.z0 * 100:6.2f}  {fs.rms * 1e3:8.3f}  "
                          f"{int(fs.inliers.sum())}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    s = sub.add_parser("scenes", help="simulated placements: slope scatter and close frames' fit at the last check")
    s.add_argument("--set", action="store_true", help="the packaged scenario set (else random scenes of --kind)")
    s.add_argument("--kind", default="low-boxes", help="random scene kind (tables, low-boxes, rim-boxes)")
    s.add_argument("--count", type=int, default=150)
    s.add_argument("--seed", type=int, default=1)
    s.add_argument("--only", type=lambda t: [int(x) for x in t.split(",")], default=None, help="e.g. 139,43")
    s.add_argument("--jobs", type=int, default=2)
    s.add_argument("--json", default=None)
    r = sub.add_parser("real", help="consensus RMS of real level frames, halves held out")
    r.add_argument("sweep")
    args = ap.parse_args()
    scenes(args) if args.what == "scenes" else real(args)


if __name__ == "__main__":
    main()
