"""What a calibration's own forward model says about peak on tilted planes, against what peak does on the unit's
tilted frames (docs/results.md, "Peak's slope error on tilted planes, predicted by the forward model").

For each calibration (with a ``forward`` and a ``peak`` section) the script renders tilted planes with the
calibration's fitted forward model (``place_safe.evaluation.synthetic.make_frames``: 0-30 deg, 5-30 cm, Poisson
noise, no specular lobe, the unit's own reference histogram when a frame file is given) and reads them with the
calibrated peak method. Where a file of the unit's own tilted frames with ground truth is given, it reads those too.
Two numbers per set:

- **slope scale**: the least-squares ``k`` in ``e_t = k t`` (``t`` the true ``(n_x, n_y)``, ``e_t`` peak's error in
  them): peak reads slopes ``(1 + k)`` times as steep;
- **offset bias**: the least-squares ``c`` in ``e_d = c z0 tan(tilt)`` (``e_d`` the error in ``d``, m).

The model's figures are a prediction from the level sweep alone; they hold only as far as the fitted geometry does
(a level sweep cannot tell the zones' fields of view from each zone's own time scale, docs/results.md).

    python docs/figures/peak_tilt_bias.py sc/A_cal.json --frames sc/A_tilt.json
    python docs/figures/peak_tilt_bias.py c_even.json --reference-from even.json     # the real unit: model only
"""
from __future__ import annotations

import argparse

import numpy as np


def _errors(frames, estimates):
    """Rows (true n_x, true n_y, e_nx, e_ny, e_d, z0 tan(tilt)) of the frames peak read."""
    from place_safe.recovery.estimator import tilt_offset

    rows = []
    for f, r in zip(frames, estimates):
        if not r.ok or f.truth is None:
            continue
        nz = f.truth.normal[2]
        t = tilt_offset(f.truth)
        e = tilt_offset(r.plane) - t
        rows.append((t[0], t[1], e[0], e[1], e[2], f.truth.z0 * np.sqrt(max(1 - nz * nz, 0.0)) / nz))
    return np.array(rows)


def summary(frames, estimates) -> dict:
    """Slope scale, offset bias (m per m of z0 tan(tilt)), peak's mean angle error and what is left of it (deg)."""
    from place_safe.calibration.uncertainty import slope_scale_offset_bias

    a = _errors(frames, estimates)
    t, e = a[:, :2], a[:, 2:4]
    k, c = slope_scale_offset_bias(t, e, a[:, 4], a[:, 5])
    return {"n": len(a), "slope_scale": k, "offset_bias": c,
            "angle_deg": float(np.degrees(np.mean(np.hypot(e[:, 0], e[:, 1])))),
            "angle_left_deg": float(np.degrees(np.mean(np.hypot(*(e - k * t).T))))}


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("calibration", nargs="+", help="calibration files (forward and peak sections)")
    p.add_argument("--frames", help="the unit's own tilted frames with ground truth (one calibration only)")
    p.add_argument("--reference-from", help="a frame file whose first 20 reference histograms are averaged for the "
                                            "model's frames (default: --frames, else the packaged reference)")
    p.add_argument("--n", type=int, default=150, help="model frames (default 150)")
    p.add_argument("--seed", type=int, default=3)
    args = p.parse_args(argv)
    if args.frames and len(args.calibration) > 1:
        p.error("--frames goes with one calibration")

    from place_safe.calibration import Calibration
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    own = load_frames(args.frames) if args.frames else None
    ref_src = load_frames(args.reference_from) if args.reference_from else own
    ref = None if ref_src is None else np.mean([f.reference for f in ref_src[:20]], axis=0)
    spec = SyntheticSpec(z_range=(0.05, 0.30), theta_range=(0.0, np.radians(30.0)), specular_weight_range=(0.0, 0.0))
    for path in args.calibration:
        cal = Calibration.load(path)
        peak = make_estimator("peak", cal)
        model = make_frames(args.n, params=cal.forward(), spec=spec, seed=args.seed, reference=ref)
        rows = [("model", summary(model, peak.estimate_many(model)))]
        if own is not None:
            rows.append(("unit", summary(own, peak.estimate_many(own))))
        for name, s in rows:
            print(f"{path} {name:5s} n {s['n']:3d}  slope scale {s['slope_scale']:+.4f}  offset bias "
                  f"{s['offset_bias']:+.4f} z0 tan(tilt)  angle {s['angle_deg']:.3f} deg "
                  f"({s['angle_left_deg']:.3f} without the slope scale)")


if __name__ == "__main__":
    main()
