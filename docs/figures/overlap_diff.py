"""Diff through the overlap (issue 26, item 1): can the unit model read a plane closer than 2 cm?

Two measurements, both on the real sweep, neither through ``recover`` (whose too-close test gives such frames no plane
and whose fallbacks answer closer than 5 cm with peak's plane):

1. **Held out.** Each frame of FRAMES closer than ``--max-distance`` is solved by diff's own per-frame solver
   (``DifferentiableEstimator._solve_fast``, no fallback, no too-close test) with CAL's forward model, from a grid of
   starting planes (7 depths 3-45 mm x 9 tilts, since peak has no plane there to start from); the solution with the
   lowest residual is what a solver that tried them all would return. Its tilt against the truth, its residual (about 1
   where the model explains the counts) and its offset.
2. **In sample.** CAL's forward model fitted again (``fit_forward``, min distance 0) on CAL_FRAMES's own frames closer
   than ``--near-fit`` with the unit terms free (cover-glass return, crosstalk grid, echo, emitter baseline), from five
   emitter baselines: the RMS scaled residual per frame it reaches. A model that cannot fit the near frames it is
   fitted on cannot read new ones.

    python docs/figures/overlap_diff.py cal_odd.json even.json                 # held out (CAL from the other half)
    python docs/figures/overlap_diff.py cal_even.json odd.json --fit even.json   # and the in-sample refit (~1 min)

CAL: ``place-safe calibrate HALF.json --method diff -o CAL`` on one half of ``tests/data/tmf8820_ur5_sweep.json``
(``d[0::2]`` / ``d[1::2]``), FRAMES the other half.
"""
from __future__ import annotations

import argparse
import itertools
import math

import numpy as np

from place_safe.calibration import Calibration
from place_safe.calibration import forward_fit as ff
from place_safe.evaluation.metrics import angular_error
from place_safe.geometry import Plane
from place_safe.io.frame_file import load_frames
from place_safe.recovery import make_estimator
from place_safe.recovery.forward_params import ForwardParams

START_DEPTHS = (0.003, 0.006, 0.010, 0.015, 0.020, 0.030, 0.045)  # m
START_SLOPES = (-0.15, 0.0, 0.15)                                  # (8.5 deg either way, each axis)
BASELINES = ((0.0, 0.0), (-0.004, 0.0), (0.004, 0.0), (0.0, -0.004), (0.0, 0.004))  # m


def held_out(cal: Calibration, frames_path: str, max_distance: float) -> None:
    est = make_estimator("diff", cal)
    starts = [Plane.from_slopes(a, b, z) for z in START_DEPTHS for a, b in itertools.product(START_SLOPES, repeat=2)]
    print(f"held out: diff's own solve from {len(starts)} starts, the lowest residual kept")
    print("| depth (mm) | peak | diff: tilt error (deg) | residual | offset (mm, true) | starts within 1 % of it |")
    print("|---|---|---|---|---|---|")
    for f in (f for f in load_frames(frames_path) if f.truth is not None and f.truth.z0 < max_distance):
        pk = est.init.estimate(f)
        peak = f"{math.degrees(angular_error(pk.plane, f.truth)):.2f} deg" if pk.ok else "too close"
        sols = sorted((e for e in est._solve_fast([f] * len(starts), starts) if e.ok), key=lambda e: e.residual)
        if not sols:
            print(f"| {f.truth.z0 * 1e3:.1f} | {peak} | no solution | | | |")
            continue
        b = sols[0]
        near = sum(e.residual <= 1.01 * b.residual for e in sols)
        print(f"| {f.truth.z0 * 1e3:.1f} | {peak} | {math.degrees(angular_error(b.plane, f.truth)):.1f} | "
              f"{b.residual:.1f} | {b.plane.offset * 1e3:.1f} ({f.truth.offset * 1e3:.1f}) | {near} |")


def in_sample(cal: Calibration, frames_path: str, near_fit: float) -> None:
    frames = load_frames(frames_path)
    n = sum(f.truth is not None and f.truth.z0 <= near_fit for f in frames)
    print(f"\nin sample: the forward model fitted again on the {n} frames of {frames_path} to {near_fit * 1e3:.0f} mm, "
          "unit terms free")
    print("| baseline start (mm) | RMS scaled residual | per frame median / max | converged | baseline (mm) | "
          "beam power | edge / corner fov |")
    print("|---|---|---|---|---|---|---|")
    for bx, by in BASELINES:
        init = ForwardParams(**{**cal.sections["forward"], "baseline": [bx, by], "beam_power": 5.0,
                                **ff.NONZERO_START})
        p, rep = ff.fit_forward(frames, init=init, min_distance=0.0, max_distance=near_fit, progress=False,
                                fitted={**ff.FITTED, **ff.UNIT_TERMS}, coarse_rays=0, iterations=150)
        per = rep["rms_scaled_residual_per_frame"]
        print(f"| {bx * 1e3:+.0f}, {by * 1e3:+.0f} | {rep['rms_scaled_residual_after']:.2f} | {per['median']:.1f} / "
              f"{per['max']:.1f} | {rep['converged']} | {np.round(np.array(p.baseline) * 1e3, 1).tolist()} | "
              f"{p.beam_power:.1f} | {p.edge_fov_scale:.2f} / {p.corner_fov_scale:.2f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration", help="a diff calibration (place-safe calibrate HALF.json --method diff)")
    ap.add_argument("frames", help="frames with truth to read (the other half)")
    ap.add_argument("--max-distance", type=float, default=0.045, help="read frames closer than this (m)")
    ap.add_argument("--fit", metavar="CAL_FRAMES", help="also refit the model on these frames' near ones (in sample)")
    ap.add_argument("--near-fit", type=float, default=0.09, help="the in-sample refit's deepest frame (m)")
    a = ap.parse_args()
    cal = Calibration.load(a.calibration)
    held_out(cal, a.frames, a.max_distance)
    if a.fit:
        in_sample(cal, a.fit, a.near_fit)


if __name__ == "__main__":
    main()
