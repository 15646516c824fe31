"""How much of a real frame's zone timing no model of the zones can follow: the data against the forward model at the
true plane, zone by zone, frame by frame.

For each frame with ground truth the calibrated forward model renders the true plane; in each zone a centroid over
the same six bins (two before the model's peak to three after) is taken of the data and of the model, and their
difference is the zone's timing misfit (bins). Smooth in depth it is what a calibration can follow (a cubic in z0 is
taken out); what is left changes from frame to frame. The script prints, per zone, that remainder and the share of it
one sinusoid in the return's sub-bin position explains (a timing error that repeats every bin), then the part the
zones share (it moves the plane's range only) and the part that differs across the grid (right minus left columns,
top minus bottom rows: it moves the tilt), and the tilt that difference makes at 10, 20 and 40 cm for zone centres
about 11 deg off axis.

    python docs/figures/real_timing_scatter.py CAL FRAMES [--min-distance 0.06]
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch

from place_safe.calibration import Calibration
from place_safe.cli.common import load_truth_frames
from place_safe.recovery.forward import ForwardModel

#: bins of the centroid window about the model's peak (before, after)
WINDOW = (-2, 4)
#: rad: the off-axis angle of the outer zones' centres (zone table of the sensor docs, about 11 deg)
ZONE_ANGLE = math.radians(10.7)


def centroids(hists: np.ndarray, peaks, window=WINDOW) -> np.ndarray:
    """Each zone's centroid (bins) over ``window`` about its bin in ``peaks``, the floor (median of bins 100+) removed."""
    out = []
    for h, j in zip(hists, peaks):
        h = h - np.median(h[100:])
        b = np.arange(j + window[0], j + window[1])
        out.append(float((h[b] * b).sum() / h[b].sum()))
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration")
    ap.add_argument("frames")
    ap.add_argument("--min-distance", type=float, default=0.06, help="m (closer frames overlap the internal return)")
    a = ap.parse_args()
    cal = Calibration.load(a.calibration)
    model = ForwardModel(cal.forward())
    frames, _ = load_truth_frames([a.frames], a.min_distance, None)
    z0, misfit, phase = [], [], []
    for f in frames:
        with torch.no_grad():
            m = model.render_plane(torch.tensor(f.truth.normal).view(1, 3), torch.tensor([f.truth.offset]),
                                   torch.tensor([cal.forward().albedo]), torch.tensor(f.reference).view(1, -1))[0].numpy()
        peaks = [int(np.argmax(mz[12:])) + 12 for mz in m]
        z0.append(f.truth.z0)
        misfit.append(centroids(f.hists, peaks) - centroids(m, peaks))
        phase.append(centroids(m, peaks, (-1, 2)) % 1.0)
    z, d, p = np.array(z0), np.array(misfit), np.array(phase)
    smooth = np.vander(z, 4)
    rest = d - smooth @ np.linalg.lstsq(smooth, d, rcond=None)[0]
    print(f"{len(z)} frames, {z.min() * 100:.1f}-{z.max() * 100:.1f} cm; timing misfit left after a cubic in z0 (bins):")
    for k in range(9):
        design = np.column_stack([np.sin(2 * np.pi * p[:, k]), np.cos(2 * np.pi * p[:, k])])
        left = rest[:, k] - design @ np.linalg.lstsq(design, rest[:, k], rcond=None)[0]
        share = 1.0 - left.var() / rest[:, k].var()
        print(f"  zone {k + 1}: {rest[:, k].std():.4f}, one-bin sinusoid explains {100 * share:.0f} %")
    grid = rest.reshape(-1, 3, 3)
    across = np.hypot((grid[:, :, 2] - grid[:, :, 0]).mean(1).std(), (grid[:, 2, :] - grid[:, 0, :]).mean(1).std()) / 2
    bin_m = cal.forward().bin_size
    print(f"shared by the zones: {rest.mean(1).std():.4f} bins; across the grid (per axis, rms of the two): {across:.4f} "
          f"bins = {across * bin_m * 1e3:.3f} mm")
    for zz in (0.1, 0.2, 0.4):
        print(f"  tilt it makes at {zz * 100:.0f} cm: {math.degrees(across * bin_m / (2 * zz * math.tan(ZONE_ANGLE))):.3f} deg")


if __name__ == "__main__":
    main()
