"""The simulated sensor's near frames against the real ones at 5, 12.5 and 20 mm, zone by zone.

    MUJOCO_GL=egl python docs/figures/near_histograms.py [FRAMES.json] [OUT.png]

FRAMES.json defaults to tests/data/tmf8820_ur5_sweep.json; OUT.png to docs/figures/near_histograms_sim_vs_real.png.
Each real frame closer than 2.1 cm is simulated as ``place-safe sim validate`` does (a rig over a level table at
the frame's ground-truth plane, no noise, the real frame's reference histogram and floor), with the simulator's
true parameters (``sim/sensors/tmf8820_real.json``, internal return included) and again without the internal
return. Prints per zone the real and simulated peak bin (sub-bin), peak height above the floor, and the
counts the internal return adds at the real peak's bin. The plot: bins 6-26 of each zone, log counts.
"""

import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from place_safe.io.frame_file import load_frames  # noqa: E402
from place_safe.sim.tof import true_params  # noqa: E402
from place_safe.sim.validate import subbin_peak, validate  # noqa: E402
from place_safe.sensor.frame import N_ZONES  # noqa: E402
from place_safe.sensor.histogram import FLOOR_BINS  # noqa: E402

NEAR = 0.021  # m
BINS = slice(6, 27)


def main(frames: str = "tests/data/tmf8820_ur5_sweep.json",
         out: str = "docs/figures/near_histograms_sim_vs_real.png") -> None:
    near = sorted((f for f in load_frames(frames) if f.truth is not None and f.truth.z0 < NEAR),
                  key=lambda f: f.truth.z0)
    p = true_params()
    sim = validate(near, params=p, min_distance=0.0).sim_hists
    bare = validate(near, params=p.model_copy(update={"glass_gains": [0.0] * N_ZONES}), min_distance=0.0).sim_hists
    fig, axes = plt.subplots(len(near), N_ZONES, figsize=(2.0 * N_ZONES, 2.2 * len(near)), sharex=True)
    x = np.arange(BINS.start, BINS.stop)
    print("z0_mm zone  peak_bin real sim   height real sim (counts)   internal return at real peak (counts)")
    for i, f in enumerate(near):
        real = f.hists
        hr = real - np.median(real[:, FLOOR_BINS], axis=1, keepdims=True)
        hs = sim[i] - np.median(sim[i][:, FLOOR_BINS], axis=1, keepdims=True)
        pr, ps = subbin_peak(real), subbin_peak(sim[i])
        glass = sim[i] - bare[i]
        for z in range(N_ZONES):
            k = int(np.argmax(hr[z]))
            print(f"{f.truth.z0 * 1000:5.1f} {z + 1:4d}  {pr[z]:8.2f} {ps[z]:6.2f}   {hr[z].max():11.0f} "
                  f"{hs[z].max():9.0f}   {glass[z, k]:8.1f}")
            ax = axes[i, z]
            ax.semilogy(x, np.clip(real[z, BINS], 0.5, None), "k.-", lw=1, ms=3, label="real")
            ax.semilogy(x, np.clip(sim[i][z, BINS], 0.5, None), "r-", lw=1, label="sim")
            ax.semilogy(x, np.clip(glass[z, BINS], 0.5, None), "b:", lw=1, label="sim: internal return")
            ax.set_ylim(0.5, 3e6)
            if i == 0:
                ax.set_title(f"zone {z + 1}", fontsize=8)
            if z == 0:
                ax.set_ylabel(f"{f.truth.z0 * 1000:.1f} mm\ncounts", fontsize=8)
            ax.tick_params(labelsize=6)
    axes[0, 0].legend(fontsize=6)
    for ax in axes[-1]:
        ax.set_xlabel("bin", fontsize=7)
    fig.suptitle("Near frames: real TMF8820 (black) and the simulated sensor (red; blue: its internal return alone)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    print("wrote", out)


if __name__ == "__main__":
    main(*sys.argv[1:3])
