"""What a forward model's residual on frames it was not fitted to is made of, and the floor a frame-to-frame timing
scatter puts under it.

    python docs/figures/residual_floor.py CALIBRATION.json FRAMES.json [--jitter 0.008 0.010]

CALIBRATION.json: a calibration (its ``forward`` section) or forward parameters; FRAMES.json: frames with ground
truth (4 cm and beyond are used). Each frame is rendered at its true plane with its least-squares albedo, as
``forward_residuals.py`` does, and the residual scaled as the forward fit scales it (Poisson noise and the 2 % model
error: ``recovery.forward.residual_weights``) over the bins the fit uses. Prints:

- the RMS scaled residual, by band of depth and by bins relative to each zone's highest bin (share of the squares);
- the share of the squares that a shape fixed per zone and relative bin explains (what a learned response could take);
- the RMS left with a free timing shift per zone and frame (how much of the misfit is timing rather than shape);
- the RMS that a timing scatter of each ``--jitter`` (bins, independent per zone and frame) alone gives at these
  weights, and with shot noise (RMS 1) the floor it puts under any model that is the same in every frame.
"""

import argparse

import numpy as np
import torch

from forward_residuals import relative_to_peak, rendered_at_truth  # (docs/figures: the rendering it plots)
from place_safe.recovery.forward import MODEL_ERROR, residual_weights


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration")
    ap.add_argument("frames")
    ap.add_argument("--jitter", type=float, nargs="+", default=[0.008, 0.010], help="timing scatter, bins")
    a = ap.parse_args()
    torch.set_num_threads(1)
    fr, hists, obs, h = rendered_at_truth(a.calibration, a.frames)
    w = residual_weights(hists, MODEL_ERROR)
    width = int(obs.argmax(-1).max() + 24)
    res = ((h - obs) * w)[..., :width]
    total = float((res ** 2).sum())
    print(f"{len(fr)} frames, bins 0-{width - 1}: RMS scaled residual {np.sqrt((res ** 2).mean()):.3f}")
    z = np.array([f.truth.z0 for f in fr])
    for lo, hi in ((0.04, 0.1), (0.1, 0.2), (0.2, 0.3), (0.3, 0.41)):
        s = (z >= lo) & (z < hi)
        if s.any():
            print(f"  depth {lo * 100:.0f}-{hi * 100:.0f} cm: RMS {np.sqrt((res[s] ** 2).mean()):.2f} ({s.sum()} frames)")
    peak = obs[..., :width].argmax(-1)
    rel = np.arange(width)[None, None, :] - peak[..., None]
    for lo, hi in ((-200, -8), (-8, -3), (-3, -1), (-1, 1), (1, 3), (3, 8), (8, 20), (20, 200)):
        msk = (rel >= lo) & (rel < hi)
        if msk.any():
            print(f"  bins {lo:+d}..{hi:+d} from the highest: {100 * (res[msk] ** 2).sum() / total:4.1f} % of the "
                  f"squares, RMS {np.sqrt((res[msk] ** 2).mean()):.2f}")
    grid = relative_to_peak(res, peak, np.arange(-20, 40))
    left = np.nansum((grid - np.nanmean(grid, 0)[None]) ** 2)
    print(f"a shape fixed per zone and bin from the highest explains {100 * (1 - left / np.nansum(grid ** 2)):.0f} % "
          f"of the squares; RMS without it {np.sqrt((res ** 2).mean() * left / np.nansum(grid ** 2)):.2f}")
    slope = np.gradient(h, axis=-1)[..., :width] * w[..., :width]
    shift = -(res * slope).sum(-1) / (slope * slope).sum(-1)  # (frames, 9): the timing that fits each zone best
    print(f"with a free timing shift per zone and frame (sd {shift.std():.4f} bins): RMS "
          f"{np.sqrt(((res + slope * shift[..., None]) ** 2).mean()):.2f}")
    for j in a.jitter:
        r = float(np.sqrt(((slope * j) ** 2).mean()))
        print(f"a timing scatter of {j:g} bins per zone and frame alone: RMS {r:.2f}; with shot noise a floor of "
              f"{np.sqrt(1 + r * r):.2f}")


if __name__ == "__main__":
    main()
