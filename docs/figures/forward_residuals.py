"""Residuals of a fitted forward model on frames it was not fitted to, per zone, by distance and bin.

    python docs/figures/forward_residuals.py FORWARD.json FRAMES.json OUT.png

FORWARD.json: forward parameters (``ForwardParams.save``, or the ``forward`` section of a calibration file);
FRAMES.json: frames with ground truth (4 cm and beyond are used). Each frame's albedo is its least-squares value; the
plot shows, for each of the 9 zones, (model - observed) / sigma (Neyman weights with the 2 % model error, as the
forward fit reports them) against the bin relative to the zone's peak (x) and the frame's distance (y).
Prints the RMS scaled residual of the bins the fit uses and per zone.
"""

import json
import sys

import numpy as np
import torch

from place_safe.io.frame_file import load_frames
from place_safe.recovery.forward import (MODEL_ERROR, ForwardModel, ForwardParams, ZoneRays, mount_rotation,
                                         residual_weights)
from place_safe.sensor.histogram import measure_floor


def rendered_at_truth(forward: str, frames: str):
    """The frames with ground truth at 4 cm and beyond in ``frames`` (a file), sorted by depth, rendered at their
    true planes by the forward parameters in ``forward`` (a calibration's ``forward`` section or the parameters),
    each with its least-squares albedo: (frames, histograms (F, 9, 128), the counts above each zone's floor, the
    model's counts above its floor). Shared by ``residual_floor.py``."""
    d = json.load(open(forward))
    p = ForwardParams.from_dict(d.get("forward", d))
    fr = sorted((f for f in load_frames(frames) if f.truth is not None and f.truth.z0 >= 0.04), key=lambda f: f.truth.z0)
    m = ForwardModel(p, ZoneRays.stratified(4))
    hists = np.array([f.hists for f in fr], float)
    obs = np.clip(hists - measure_floor(hists)[..., None], 0, None)
    normals = torch.as_tensor(np.array([f.truth.normal for f in fr]))
    offsets = torch.as_tensor(np.array([f.truth.offset for f in fr]))
    refs = torch.as_tensor(np.array([f.reference for f in fr]), dtype=torch.float64)
    with torch.no_grad():
        n_opt = normals @ mount_rotation(m.t["mount_tilt"])
        la = torch.full((len(fr),), float(np.log(p.albedo)), dtype=torch.float64)
        for _ in range(4):
            h = m.render_plane(n_opt, offsets, torch.exp(la), refs).numpy() - p.floor
            la += torch.log(torch.as_tensor((h * obs).sum((1, 2)) / (h * h).sum((1, 2))))
    return fr, hists, obs, h


def relative_to_peak(res: np.ndarray, peak: np.ndarray, rel: np.ndarray) -> np.ndarray:
    """``res`` (F, 9, N) at the bins ``rel`` from each zone's highest bin ``peak`` (F, 9): (F, 9, len(rel)), NaN
    outside the N bins."""
    img = np.full(res.shape[:2] + (len(rel),), np.nan)
    for i in range(res.shape[0]):
        for k in range(res.shape[1]):
            idx = peak[i, k] + rel
            ok = (idx >= 0) & (idx < res.shape[-1])
            img[i, k, ok] = res[i, k, idx[ok]]
    return img


def main(forward: str, frames: str, out: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fr, hists, obs, h = rendered_at_truth(forward, frames)
    res = (h - obs) * residual_weights(hists, MODEL_ERROR)
    width = int(obs.argmax(-1).max() + 24)
    print(f"RMS scaled residual {np.sqrt((res[..., :width] ** 2).mean()):.3f}; per zone",
          np.round(np.sqrt((res[..., :width] ** 2).mean((0, 2))), 2))
    z = np.array([f.truth.z0 for f in fr]) * 100
    rel = np.arange(-20, 30)
    img = relative_to_peak(res, obs.argmax(-1), rel)
    fig, ax = plt.subplots(3, 3, figsize=(13, 11), sharex=True, sharey=True)
    for k in range(9):
        a = ax[k // 3, k % 3]
        im = a.imshow(img[:, k], aspect="auto", cmap="RdBu_r", vmin=-8, vmax=8,
                      extent=[rel[0], rel[-1], z[-1], z[0]])
        a.set_title(f"zone {k + 1}")
        if k // 3 == 2:
            a.set_xlabel("bin - zone's peak bin")
        if k % 3 == 0:
            a.set_ylabel("distance z0 (cm)")
    fig.colorbar(im, ax=ax, shrink=0.6, label="(model - observed) / sigma")
    fig.savefig(out, dpi=60)


if __name__ == "__main__":
    main(*sys.argv[1:4])
