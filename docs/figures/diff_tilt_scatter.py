"""What limits the diff method's own tilt: a smooth function of distance (which a plane correction or a model term
smooth in range could remove) or a scatter from frame to frame (which neither can).

    python docs/figures/diff_tilt_scatter.py CAL.json A.json B.json [--options JSON] [--model-error E]
                                             [--mean-reference all|near] [--weight W LO HI] [--save OUT.npy]

Every frame of A and B (two halves of a level sweep, interleaved in distance; 5-40 cm) is recovered by diff with
CAL's forward model and solver options, without its plane correction and without its fallback limits (its own
plane), and by peak with CAL. Per frame: the slope errors (deg) about x and y in the optical frame. Printed per
method and axis: the raw rms; the rms about ONE smooth curve in 1 / z0 (a degree-6 polynomial fitted to the frames
of both files at once: in-sample, so optimistic); the mean of that residual on B's frames less A's (an offset
between the halves); the frame-to-frame scatter (each frame against the mean of its two neighbours in distance,
which belong to the other half, / sqrt(1.5)); and the mean angle each file's frames would have after that smooth
curve (degrees 4, 6, 8): the best any correction smooth in distance could do, fitted on both halves. Then whether
the sub-bin phase explains the scatter: the tilt a timing error of one shape in every zone (harmonics 1, 2 of each
zone's sub-bin position, at the zone's mean obliquity) would give, fitted beside the smooth curves; and a shape of
its own per zone (harmonic 1, ridge), fitted on one file's frames and tested on the other's.

``--options``: SolverOptions fields to change (JSON); ``--model-error``: the forward model's relative model error
instead of the calibrated one; ``--mean-reference``: every frame's reference histogram replaced by the mean over
the frames (``all``) or over the 5 nearest in distance (``near``); ``--weight``: diff's residual weights of each
zone's bins LO..HI about its highest bin multiplied by W (-3 -1: the rising edge).
"""

import argparse
import dataclasses
import json

import numpy as np
import torch

from place_safe.calibration import Calibration
from place_safe.cli.common import load_truth_frames
from place_safe.geometry import Plane
from place_safe.recovery import differentiable, make_estimator
from place_safe.recovery.forward import ForwardModel, ZoneRays, mount_rotation

SMOOTH_DEGREE = 6


def own_calibration(cal: Calibration, model_error: float | None) -> Calibration:
    """CAL with diff's fallback limits off and no plane correction (and another model error if given), the crosstalk held
    (``diff_timing_variants.py``'s solvers have no crosstalk column; the real unit's calibrations hold it anyway)."""
    d = cal.without_fallback().to_dict()
    d["diff"]["range_correction"] = {}
    d["diff"].pop("crosstalk_std", None)
    if model_error is not None:
        d["forward"]["model_error"] = model_error
    return Calibration.from_dict(d)


def slope_errors(cal: Calibration, paths, options=None, model_error=None, mean_reference=None) -> np.ndarray:
    """Rows (file index, z0, diff da, diff db, peak da, peak db): slope errors in deg, optical frame."""
    own = own_calibration(cal, model_error)
    diff = make_estimator("diff", own, **({"options": dataclasses.replace(own.diff_options(), **options)}
                                          if options else {}))
    peak = make_estimator("peak", cal)
    to_optical = mount_rotation(cal.forward().mount_tilt).numpy().T
    frames = [load_truth_frames([p], 0.05, None)[0] for p in paths]
    if mean_reference:
        every = [f for fs in frames for f in fs]
        z_all = np.array([f.truth.z0 for f in every])
        refs = np.array([np.asarray(f.reference, dtype=float) for f in every])
        pick = ((lambda f: refs.mean(0)) if mean_reference == "all" else
                (lambda f: refs[np.argsort(np.abs(z_all - f.truth.z0))[:5]].mean(0)))
        frames = [[dataclasses.replace(f, reference=pick(f)) for f in fs] for fs in frames]

    def slopes(plane):
        return np.degrees(np.arctan(Plane(to_optical @ plane.normal, plane.offset).slopes[:2]))

    rows = []
    for i, fs in enumerate(frames):
        for f, e, p in zip(fs, diff.estimate_many(fs), peak.estimate_many(fs)):
            t = slopes(f.truth)
            rows.append((i, f.truth.z0, *(slopes(e.plane) - t), *(slopes(p.plane) - t)))
    rows = np.array(rows)
    return rows[np.argsort(rows[:, 1])]


def zone_geometry(cal: Calibration):
    """Each zone's mean tangents (x, y) and mean 1 / cos over its footprint (the forward model's rays)."""
    model = ForwardModel(cal.forward(), ZoneRays.stratified(6))
    with torch.no_grad():
        dirs, w = (v.numpy() for v in model.ray_geometry())
    tan = [(w * dirs[..., k] / dirs[..., 2]).sum(1) for k in (0, 1)]
    return tan, (w / dirs[..., 2]).sum(1)


def tilt_of(delta_bins: np.ndarray, z: np.ndarray, cal: Calibration, geometry) -> np.ndarray:
    """(F, 2) slope errors (deg) of the least-squares plane through the zones' points when each zone's return is
    late by ``delta_bins`` (F, 9) on a level plane at ``z``."""
    tan, sec = geometry
    dz = delta_bins * cal.forward().bin_size / sec[None]
    out = []
    for t in tan:
        x = z[:, None] * t[None]
        xc = x - x.mean(1, keepdims=True)
        out.append(np.degrees((xc * dz).sum(1) / (xc ** 2).sum(1)))
    return np.stack(out, 1)


def report(rows: np.ndarray, cal: Calibration, names) -> None:
    z, second = rows[:, 1], rows[:, 0] > 0.5
    smooth = np.vander(1 / z, SMOOTH_DEGREE + 1)
    about = lambda e, s=smooth: e - s @ np.linalg.lstsq(s, e, rcond=None)[0]  # noqa: E731
    print(f"{len(z)} frames ({names[0]}: {int((~second).sum())}, {names[1]}: {int(second.sum())}), 5-40 cm; deg")
    print("method axis | raw rms | about one smooth curve | its mean B - A | frame-to-frame")
    for name, cols in (("diff", (2, 3)), ("peak", (4, 5))):
        for k, c in zip("ab", cols):
            e = rows[:, c]
            res = about(e)
            jump = (e[1:-1] - 0.5 * (e[:-2] + e[2:])) / np.sqrt(1.5)
            print(f"{name} {k} | {np.sqrt(np.mean(e ** 2)):.3f} | {np.sqrt(np.mean(res ** 2)):.3f} | "
                  f"{res[second].mean() - res[~second].mean():+.3f} | {np.sqrt(np.mean(jump ** 2)):.3f}")
    print(f"mean angle after one smooth curve in 1/z0 fitted to both files ({names[0]} / {names[1]} frames):")
    for deg in (4, 6, 8):
        s = np.vander(1 / z, deg + 1)
        line = []
        for name, cols in (("diff", [2, 3]), ("peak", [4, 5])):
            ang = np.hypot(*about(rows[:, cols], s).T)
            line.append(f"{name} {ang[~second].mean():.3f} / {ang[second].mean():.3f}")
        print(f"  degree {deg}: " + ", ".join(line))
    geometry = zone_geometry(cal)
    p = cal.forward()
    u = (z[:, None] * geometry[1][None] / p.bin_size * np.asarray(p.zone_bin_scales)[None] + p.bin_offset
         + np.asarray(p.zone_offsets)[None])  # each zone's bin position on the level plane
    print("sub-bin phase: rms about the smooth curves (a, b) | + one timing shape in every zone, harmonics 1..H "
          "(in-sample) | + each zone's own (harmonic 1), fitted on A -> tested on B, B -> A")
    for name, cols in (("diff", [2, 3]), ("peak", [4, 5])):
        res = about(rows[:, cols])
        common = [tilt_of(f(2 * np.pi * h * u), z, cal, geometry) for h in (1, 2) for f in (np.sin, np.cos)]
        text = [f"{name}: {np.sqrt(np.mean(res ** 2, 0)).round(3)}"]
        for n_h in (2, 4):
            design = np.stack(common[:n_h], -1).reshape(-1, n_h)  # both axes, one shape
            y = res.reshape(-1)
            left = y - design @ np.linalg.lstsq(design, y, rcond=None)[0]
            text.append(f"H={n_h // 2}: {np.sqrt(np.mean(left.reshape(-1, 2) ** 2, 0)).round(3)}")
        own = []
        for zone in range(9):
            for f in (np.sin, np.cos):
                d = np.zeros_like(u)
                d[:, zone] = f(2 * np.pi * u[:, zone])
                own.append(tilt_of(d, z, cal, geometry))
        own = np.stack(own, -1)
        for fit in (False, True):
            tr, te = second == fit, second != fit
            a, y = own[tr].reshape(-1, own.shape[-1]), res[tr].reshape(-1)
            ridge = 1e-3 * np.trace(a.T @ a) / a.shape[1]
            co = np.linalg.solve(a.T @ a + ridge * np.eye(a.shape[1]), a.T @ y)
            text.append(f"{names[fit]} -> {names[not fit]}: {np.sqrt(np.mean(res[te] ** 2)):.3f} -> "
                        f"{np.sqrt(np.mean((res[te] - own[te] @ co) ** 2)):.3f}")
        print("  " + " | ".join(text))


def weight_bins(w: float, lo: int, hi: int) -> None:
    """Make diff's solver weigh each zone's bins ``lo..hi`` about its highest bin ``w`` times as much."""
    plain = differentiable.residual_weights

    def weights(hists, model_error):
        rel = np.arange(hists.shape[-1]) - hists.argmax(-1)[..., None]
        return plain(hists, model_error) * np.where((rel >= lo) & (rel <= hi), w, 1.0)

    differentiable.residual_weights = weights


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration")
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("--options", type=json.loads, default=None)
    ap.add_argument("--model-error", type=float, default=None)
    ap.add_argument("--mean-reference", choices=("all", "near"), default=None)
    ap.add_argument("--weight", nargs=3, type=float, default=None)
    ap.add_argument("--save", default=None)
    args = ap.parse_args()
    if args.weight is not None:
        weight_bins(args.weight[0], int(args.weight[1]), int(args.weight[2]))
    cal = Calibration.load(args.calibration)
    rows = slope_errors(cal, [args.a, args.b], args.options, args.model_error, args.mean_reference)
    if args.save:
        np.save(args.save, rows)
    report(rows, cal, [args.a, args.b])


if __name__ == "__main__":
    main()
