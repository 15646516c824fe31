"""Would a per-zone timing that follows a smooth curve in distance help the diff method's own plane? An emulation.

    python docs/figures/zone_timing_curves.py CAL_A.json A.json B.json DEGREE [--gains] [--scale S]

1. Each zone's timing at the TRUE plane, per frame of A (its calibration half) at 5-40 cm: ``fit_forward`` on
   that frame alone (three copies: the fit wants three frames) from CAL_A's forward model with only ``bin_offset``
   and ``zone_offsets`` free (the centre zone's offset is the gauge), and with ``--gains`` each zone's brightness
   (``zone_gains``) as well, as diff's per-zone albedos free it.
2. Per zone a Chebyshev series of DEGREE in 1 / z0 through those offsets (times ``--scale``; 0 is the control:
   diff as calibrated).
3. Diff with each frame's zone offsets moved by the curves at the distance its peak initialisation reads (for a
   level plane a zone's rays lie within a few per cent of one range, so this is a range-dependent timing term
   per zone evaluated at the zone's range); the plane correction refitted on A's frames that way
   (``fit_range_correction``), then diff's own plane (no fallback limits) on B's frames at 5-40 cm.
Prints the zone timings' rms, what the curves leave of them, the correction's terms and diff's own angular (mean,
p95) and linear (mean) error on B.
"""

import argparse

import numpy as np

from place_safe.calibration import Calibration, forward_fit, plane_correction
from place_safe.cli.common import load_truth_frames
from place_safe.evaluation.metrics import angular_errors, linear_errors
from place_safe.recovery.differentiable import DifferentiableEstimator, RangeCorrection
from place_safe.recovery.peak import PeakEstimator


def zone_timings(cal: Calibration, frames, gains: bool) -> tuple[np.ndarray, np.ndarray]:
    """(z0 (F,), zone offsets less the calibration's (F, 9), bins) at each frame's true plane."""
    base = cal.forward()
    fitted = {"bin_offset": "lin", "zone_offsets": "lin", **({"zone_gains": "log"} if gains else {})}
    z, off = [], []
    for f in frames:
        fit, _ = forward_fit.fit_forward([f, f, f], init=base, progress=False, fitted=fitted, coarse_rays=0,
                                         priors={})
        z.append(f.truth.z0)
        off.append(np.asarray(fit.zone_offsets) - np.asarray(base.zone_offsets))
    return np.array(z), np.array(off)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration")
    ap.add_argument("a")
    ap.add_argument("b")
    ap.add_argument("degree", type=int)
    ap.add_argument("--gains", action="store_true")
    ap.add_argument("--scale", type=float, default=1.0)
    args = ap.parse_args()
    cal = Calibration.load(args.calibration)
    base, peak_params = cal.forward(), cal.peak()
    frames_a = load_truth_frames([args.a], 0.05, None)[0]
    z, off = zone_timings(cal, frames_a, args.gains)
    lo, hi = float((1 / z).min()), float((1 / z).max())

    def design(inv_z: np.ndarray) -> np.ndarray:
        return np.polynomial.chebyshev.chebvander(2 * (np.clip(inv_z, lo, hi) - lo) / (hi - lo) - 1, args.degree)

    coef = np.linalg.lstsq(design(1 / z), off, rcond=None)[0] * args.scale  # (degree + 1, 9)
    print(f"zone timing at the true plane on {args.a}: {np.sqrt(np.mean(off ** 2)):.4f} bins rms; about the curves "
          f"(degree {args.degree}, scale {args.scale:g}) {np.sqrt(np.mean((off - design(1 / z) @ coef) ** 2)):.4f}")
    peak = PeakEstimator(peak_params, cal.uncertainty("peak"))

    class Curved(DifferentiableEstimator):
        """Diff with each frame's zone offsets moved by the curves at its peak distance."""

        def estimate_many(self, frames):
            out = []
            for f in frames:
                p = peak.estimate(f)
                move = (design(np.array([1 / (p.plane.offset if p.ok else 0.2)])) @ coef)[0]
                one = DifferentiableEstimator(self.params.replace(
                    zone_offsets=list(np.asarray(base.zone_offsets) + move)), peak_params, options=self.opt,
                    correction=self.correction)
                out.extend(DifferentiableEstimator.estimate_many(one, [f]))
            return out

    options = cal.diff_options()
    plain = plane_correction.DifferentiableEstimator
    plane_correction.DifferentiableEstimator = Curved  # the plane correction fitted with the curves
    try:
        section, report = plane_correction.fit_range_correction(load_truth_frames([args.a], None, None)[0], base,
                                                           peak_params, progress=False, options=options)
    finally:
        plane_correction.DifferentiableEstimator = plain
    print(f"plane correction on {args.a}: {report['kept']} (in 1/z0: {report['inverse']})")
    frames_b = load_truth_frames([args.b], 0.05, None)[0]
    est = Curved(base, peak_params, options=options, correction=RangeCorrection(**section["range_correction"]))
    ests = est.estimate_many(frames_b)
    tn = np.array([f.truth.normal for f in frames_b])
    td = np.array([f.truth.offset for f in frames_b])
    n = np.array([e.plane.normal for e in ests])
    d = np.array([e.plane.offset for e in ests])
    ang = np.degrees(angular_errors(n, tn))
    lin = linear_errors(n, d, tn, td) * 1e3
    print(f"diff's own plane on {args.b} (5-40 cm, {len(frames_b)} frames): {ang.mean():.3f} deg mean "
          f"(p95 {np.percentile(ang, 95):.3f}), {lin.mean():.3f} mm mean")


if __name__ == "__main__":
    main()
