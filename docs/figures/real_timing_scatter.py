"""How much of a real frame's zone timing no model of the zones can follow: the data against the forward model at the
true plane, zone by zone, frame by frame.

For each frame with ground truth the calibrated forward model renders the true plane. Each zone's timing misfit
(bins) is, by default, the difference of a centroid over the same six bins (two before the model's peak to three
after) of data and model; with ``--shift`` it is the shift of the model's zone histogram (its plane moved along its
normal, amplitude free) that best fits the data (Poisson weights, from 3 bins before the peak to 8 after): what a
model-based fit such as diff reads. Smooth in depth the misfit is what a calibration can follow (a cubic in z0 is
taken out); what is left changes from frame to frame. The script prints, per zone, that remainder and the share of it
one sinusoid in the return's sub-bin position explains (a timing error that repeats every bin), then the part the
zones share (it moves the plane's range only) and the part that differs across the grid (right minus left columns,
top minus bottom rows: it moves the tilt), and the tilt that difference makes at 10, 20 and 40 cm for zone centres
about 11 deg off axis. ``--sigma`` / ``--spline SIGMA`` replace the calibration's soft binning (the sampled Gaussian's
width, or the quadratic B-spline convolved with a Gaussian: ``ForwardParams.soft_bin_spline``), nothing refitted.

    python docs/figures/real_timing_scatter.py CAL FRAMES [--min-distance 0.06] [--shift] [--sigma S | --spline S]
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
#: bins of the shift fit's window about the model's peak (before, after), and the shifts tried (bins, either way)
SHIFT_WINDOW, SHIFT_REACH, SHIFT_STEPS = (-3, 9), 0.25, 51
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


def best_shifts(hists: np.ndarray, models: np.ndarray, floor: float, step: float) -> np.ndarray:
    """Each zone's shift (bins) of the models (S, 9, 128: the plane moved by ``step`` bins between them, the middle one
    at the true plane) that best fits ``hists`` (9, 128), amplitude free, Poisson weights; parabolic between steps."""
    mid = len(models) // 2
    out = []
    for k in range(hists.shape[0]):
        m = models[:, k] - floor
        h = hists[k] - np.median(hists[k][100:])
        j = int(np.argmax(m[mid, 12:])) + 12
        w = slice(j + SHIFT_WINDOW[0], j + SHIFT_WINDOW[1])
        var = np.maximum(hists[k][w], 1.0)
        amp = (m[:, w] * h[w] / var).sum(1) / (m[:, w] ** 2 / var).sum(1)
        chi = ((h[w] - amp[:, None] * m[:, w]) ** 2 / var).sum(1)
        i = min(max(int(np.argmin(chi)), 1), len(chi) - 2)
        c0, c1, c2 = chi[i - 1:i + 2]
        out.append((i - mid + 0.5 * (c0 - c2) / (c0 - 2 * c1 + c2)) * step)
    return np.array(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("calibration")
    ap.add_argument("frames")
    ap.add_argument("--min-distance", type=float, default=0.06, help="m (closer frames overlap the internal return)")
    ap.add_argument("--shift", action="store_true", help="the best-fitting shift of the model, not a centroid")
    ap.add_argument("--sigma", type=float, help="the sampled Gaussian's width instead of the calibration's (bins)")
    ap.add_argument("--spline", type=float, metavar="SIGMA", help="the quadratic B-spline soft binning with this "
                    "Gaussian (bins)")
    a = ap.parse_args()
    cal = Calibration.load(a.calibration)
    params = cal.forward()
    if a.sigma is not None:
        params = params.replace(soft_bin_sigma=a.sigma)
    if a.spline is not None:
        params = params.replace(soft_bin_spline=1.0, soft_bin_integrated=0.0, soft_bin_sigma=a.spline)
    model = ForwardModel(params)
    frames, _ = load_truth_frames([a.frames], a.min_distance, None)
    steps = np.linspace(-SHIFT_REACH, SHIFT_REACH, SHIFT_STEPS) if a.shift else np.zeros(1)
    z0, misfit, phase = [], [], []
    for f in frames:
        n = torch.tensor(f.truth.normal).view(1, 3).expand(len(steps), 3)
        with torch.no_grad():
            m = model.render_plane(n, torch.tensor(f.truth.offset + steps * params.bin_size),
                                   torch.full((len(steps),), params.albedo),
                                   torch.tensor(f.reference).view(1, -1).expand(len(steps), -1)).numpy()
        at_truth = m[len(steps) // 2]
        peaks = [int(np.argmax(mz[12:])) + 12 for mz in at_truth]
        z0.append(f.truth.z0)
        misfit.append(best_shifts(f.hists, m, params.floor, steps[1] - steps[0]) if a.shift
                      else centroids(f.hists, peaks) - centroids(at_truth, peaks))
        phase.append(centroids(at_truth, peaks, (-1, 2)) % 1.0)
    z, d, p = np.array(z0), np.array(misfit), np.array(phase)
    smooth = np.vander(z, 4)
    rest = d - smooth @ np.linalg.lstsq(smooth, d, rcond=None)[0]
    what = "best shift" if a.shift else "centroid"
    print(f"{len(z)} frames, {z.min() * 100:.1f}-{z.max() * 100:.1f} cm; timing misfit ({what}) left after a cubic in "
          f"z0 (bins):")
    for k in range(9):
        design = np.column_stack([np.sin(2 * np.pi * p[:, k]), np.cos(2 * np.pi * p[:, k])])
        left = rest[:, k] - design @ np.linalg.lstsq(design, rest[:, k], rcond=None)[0]
        share = 1.0 - left.var() / rest[:, k].var()
        print(f"  zone {k + 1}: {rest[:, k].std():.4f}, one-bin sinusoid explains {100 * share:.0f} %")
    grid = rest.reshape(-1, 3, 3)
    across = np.hypot((grid[:, :, 2] - grid[:, :, 0]).mean(1).std(), (grid[:, 2, :] - grid[:, 0, :]).mean(1).std()) / 2
    bin_m = params.bin_size
    print(f"shared by the zones: {rest.mean(1).std():.4f} bins; across the grid (per axis, rms of the two): {across:.4f} "
          f"bins = {across * bin_m * 1e3:.3f} mm")
    for zz in (0.1, 0.2, 0.4):
        print(f"  tilt it makes at {zz * 100:.0f} cm: {math.degrees(across * bin_m / (2 * zz * math.tan(ZONE_ANGLE))):.3f} deg")


if __name__ == "__main__":
    main()
