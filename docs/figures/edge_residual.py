"""What the rising edge's residual is: a sub-bin phase effect, a timing shift, a width, by zone and distance.

    python docs/figures/edge_residual.py FWD_A.json FRAMES_B.json [FWD_B.json FRAMES_A.json ...] OUT.png

Each FORWARD.json (``ForwardParams.save`` or a calibration file's ``forward`` section) is measured on the FRAMES
after it (frames it was not fitted to; 5-40 cm), with each frame's ambient (mean of bins 0-7) through the pile-up
as ``fit_forward(..., ambient=True)`` fits it, and each frame's least-squares albedo. Per frame and zone the scaled
residual of bins peak-3..peak+3 is regressed on the model's derivatives in a timing shift (``bin_offset``), in the
soft binning's width (``soft_bin_sigma``) and in amplitude; printed: the share of the squared residual in bins
peak-2..-1 (the rising edge) and what the shift alone and all three leave of it; the shift split into a part common
to a frame's zones (a function of distance), each zone's straight line in distance, and the rest; and the common
shift's dependence on the return's sub-bin phase (the fraction of its bin position) against its dependence on
distance, and a nested test by distance band: what a pulse shape at 1/8 bin, fixed relative to the return, removes
beyond a mean per frame, against the same with the positions shuffled. The figure: the common shift against distance, coloured by phase; each zone's shift less the common one;
the rising edge's residual (% of the peak) against the sub-bin position of the bin relative to the return.
"""

import json
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from place_safe.io.frame_file import load_frames  # noqa: E402
from place_safe.recovery.forward import (MODEL_ERROR, ForwardModel, ForwardParams, ZoneRays,  # noqa: E402
                                         mount_rotation, residual_weights, warp_positions)
from place_safe.sensor.histogram import arriving_ambient  # noqa: E402

STEP = 0.02  # the derivatives' finite step (bins for the shift, relative for the width)


def _params(path: str) -> ForwardParams:
    d = json.load(open(path))
    return ForwardParams.from_dict(d.get("forward", d))


def _render(p: ForwardParams, s: dict, log_albedo=None):
    """Histograms above the ambient (B, 9, 128), the log albedos, each zone's mean bin position (B, 9)."""
    m = ForwardModel(p, ZoneRays.stratified(4))
    with torch.no_grad():
        n_opt = s["normals"] @ mount_rotation(m.t["mount_tilt"])
        amb = torch.as_tensor(s["amb"])

        def draw(la):
            return m.render_plane(n_opt, s["offsets"], torch.exp(la), s["refs"], ambient=amb).numpy() - p.floor

        if log_albedo is None:
            log_albedo = torch.full((len(s["z0"]),), float(np.log(p.albedo)), dtype=torch.float64)
            w = s["width"]
            for _ in range(5):
                h = draw(log_albedo)[..., :w]
                log_albedo = log_albedo + torch.log(torch.as_tensor(
                    (h * s["obs"][..., :w]).sum((1, 2)) / (h * h).sum((1, 2))))
        h = draw(log_albedo)
        ranges = m.plane_returns(n_opt, s["offsets"])[0]
        u = ranges / m.t["bin_size"] + m.t["bin_offset"] + m.t["zone_offsets"].view(1, 9, 1)
        u = warp_positions(u, m.t["time_warp"])[0]
        wt = m.ray_geometry()[1] / ranges ** 2
        u = ((u * wt).sum(-1) / wt.sum(-1)).numpy()
    return h, log_albedo, u


def analyse(fwd: str, frames: str) -> dict:
    p = _params(fwd)
    fr = sorted((f for f in load_frames(frames) if f.truth is not None and 0.05 - 1e-9 <= f.truth.z0 <= 0.40 + 1e-9),
                key=lambda f: f.truth.z0)
    hists = np.array([f.hists for f in fr], float)
    amb = arriving_ambient(hists)
    s = {"z0": np.array([f.truth.z0 for f in fr]), "amb": amb, "obs": hists - amb[..., None],
         "normals": torch.as_tensor(np.array([f.truth.normal for f in fr])),
         "offsets": torch.as_tensor(np.array([f.truth.offset for f in fr])),
         "refs": torch.as_tensor(np.array([f.reference for f in fr]), dtype=torch.float64)}
    s["width"] = int(s["obs"].argmax(-1).max() + 24)
    h, la, u = _render(p, s)
    d_shift = (_render(p.model_copy(update={"bin_offset": p.bin_offset + STEP}), s, la)[0] - h) / STEP
    d_width = (_render(p.model_copy(update={"soft_bin_sigma": p.soft_bin_sigma * (1 + STEP)}), s, la)[0] - h) / STEP
    wts = residual_weights(hists, MODEL_ERROR)
    res = (h - s["obs"]) * wts
    peak = s["obs"].argmax(-1)
    nf = len(fr)
    out = {k: np.zeros((nf, 9)) for k in ("shift", "width", "edge", "edge_shift", "edge_all", "peak_counts", "zone_sq")}
    out["edge_r"] = np.zeros((nf, 9, 2))  # the edge's scaled residuals and their derivative in the shift
    out["edge_d"] = np.zeros((nf, 9, 2))
    out["edge_rel"] = np.zeros((nf, 9, 2))
    out["edge_x"] = np.zeros((nf, 9, 2))
    out["edge_w"] = np.zeros((nf, 9, 2))  # the scaled residual per unit relative residual (peak counts x weight)
    for i in range(nf):
        for z in range(9):
            win = slice(peak[i, z] - 3, peak[i, z] + 4)
            a = np.stack([d_shift[i, z, win], d_width[i, z, win], h[i, z, win]], 1) * wts[i, z, win, None]
            r = res[i, z, win]
            c1 = np.linalg.lstsq(a[:, :1], -r, rcond=None)[0]
            c3 = np.linalg.lstsq(a, -r, rcond=None)[0]
            out["shift"][i, z], out["width"][i, z] = c1[0], c3[1]  # the shift alone; the width beside shift and amplitude
            out["edge"][i, z] = (r[1:3] ** 2).sum()
            out["edge_shift"][i, z] = ((r + a[:, :1] @ c1)[1:3] ** 2).sum()
            out["edge_all"][i, z] = ((r + a @ c3)[1:3] ** 2).sum()
            out["edge_r"][i, z], out["edge_d"][i, z] = r[1:3], a[1:3, 0]
            out["zone_sq"][i, z] = (res[i, z, :s["width"]] ** 2).sum()
            out["peak_counts"][i, z] = s["obs"][i, z, peak[i, z]]
            edge = np.arange(peak[i, z] - 2, peak[i, z])
            out["edge_rel"][i, z] = (h[i, z, edge] - s["obs"][i, z, edge]) / s["obs"][i, z, peak[i, z]]
            out["edge_x"][i, z] = edge - u[i, z]
            out["edge_w"][i, z] = s["obs"][i, z, peak[i, z]] * wts[i, z, edge]
    w = s["width"]
    out.update(z0=s["z0"], u=u, total=(res[..., :w] ** 2).sum(), n=res[..., :w].size,
               albedo=np.exp(la.numpy()))
    return out


def _design(z0: np.ndarray, phase: np.ndarray | None, degree: int = 4) -> np.ndarray:
    x = (z0 - 0.225) / 0.175
    cols = [x ** k for k in range(degree + 1)]
    if phase is not None:
        for k in (1, 2):
            cols += [np.cos(2 * np.pi * k * phase), np.sin(2 * np.pi * k * phase)]
    return np.stack(cols, 1)


def _weighted_lsq_left(cols: list[np.ndarray], y: np.ndarray, w: np.ndarray) -> float:
    a = np.stack(cols, 1) * w[:, None]
    coef = np.linalg.lstsq(a, y * w, rcond=None)[0]
    return float(((y * w - a @ coef) ** 2).sum())


def _subbin_test(cat: dict, shuffles: int = 20) -> None:
    """By distance band: how much of the edge's squared residual (relative to the peak, Neyman-weighted) a mean per
    frame and edge bin removes (anything common to a frame's zones: distance, brightness, the reference), and how much
    a shape at 1/8 bin fixed relative to the return (its cells of sub-bin position, per edge bin) removes beyond that,
    against the same shape with the positions shuffled among the band's edge bins (what any 15 extra columns fit)."""
    rng = np.random.default_rng(1)
    for lo, hi in ((0.05, 0.12), (0.12, 0.25), (0.25, 0.41), (0.05, 0.41)):
        m = (cat["z0"] >= lo) & (cat["z0"] < hi)
        x, y, w = cat["edge_x"][m], cat["edge_rel"][m].ravel(), cat["edge_w"][m].ravel()
        n = int(m.sum())
        frame = np.broadcast_to(np.arange(n)[:, None, None], x.shape)
        kbin = np.broadcast_to(np.arange(2)[None, None, :], x.shape).ravel()
        base = [((frame.ravel() * 2 + kbin) == v).astype(float) for v in range(2 * n)]

        def cells(xv):
            c = np.floor((xv - np.floor(xv)) * 8).astype(int).ravel()
            return [((c == j) & (kbin == k)).astype(float) for j in range(8) for k in range(2)][1:]

        total = float((y * w) @ (y * w))
        left = _weighted_lsq_left(base, y, w)
        shaped = _weighted_lsq_left(base + cells(x), y, w)
        ctrl = []
        for _ in range(shuffles):
            xs = x.ravel().copy()
            rng.shuffle(xs)
            ctrl.append(_weighted_lsq_left(base + cells(xs.reshape(x.shape)), y, w))
        print(f"  sub-bin test {lo * 100:.0f}-{hi * 100:.0f} cm ({n} frames): a mean per frame and edge bin removes "
              f"{(1 - left / total) * 100:.1f} % of the edge; a shape at 1/8 bin a further {(left - shaped) / total * 100:.1f} % "
              f"(positions shuffled: {(left - np.mean(ctrl)) / total * 100:.1f} +- {np.std(ctrl) / total * 100:.1f} %)")


def report(runs: list[dict], out_png: str) -> None:
    cat = {k: np.concatenate([r[k] for r in runs]) for k in runs[0] if isinstance(runs[0][k], np.ndarray)}
    total = sum(r["total"] for r in runs)
    n = sum(r["n"] for r in runs)
    edge = cat["edge"].sum()
    print(f"held-out RMS {np.sqrt(total / n):.3f}; per run " + ", ".join(f"{np.sqrt(r['total'] / r['n']):.3f}" for r in runs))
    print(f"rising edge (peak-2..-1): {edge / total * 100:.1f} % of the squared residual; "
          f"after a timing shift per frame and zone {cat['edge_shift'].sum() / edge * 100:.1f} % of it is left, "
          f"after shift + width + amplitude {cat['edge_all'].sum() / edge * 100:.1f} %")
    print(f"  were the edge left at the noise, the RMS would be {np.sqrt((total - edge + 2 * cat['edge'].size) / n):.2f}; "
          f"with only the shift removed {np.sqrt((total - edge + cat['edge_shift'].sum()) / n):.2f}")
    print("  edge share of the squared residual by zone: " + " ".join(
        f"{z + 1}: {cat['edge'][:, z].sum() / total * 100:.1f} %" for z in range(9)))
    print("  edge rms (sigma) by distance: " + ", ".join(
        f"{lo * 100:.0f}-{hi * 100:.0f} cm {np.sqrt(cat['edge'][(cat['z0'] >= lo) & (cat['z0'] < hi)].mean() / 2):.1f}"
        for lo, hi in ((0.05, 0.10), (0.10, 0.20), (0.20, 0.30), (0.30, 0.41))))
    shift, z0 = cat["shift"], cat["z0"]
    phase = cat["u"] - np.floor(cat["u"])
    common = shift.mean(1)
    per_zone = shift - common[:, None]
    lines = np.zeros_like(per_zone)
    for z in range(9):
        coef = np.polyfit(z0, per_zone[:, z], 1)
        lines[:, z] = np.polyval(coef, z0)
        print(f"  zone {z + 1}: shift less the common one {coef[0] * 0.1:+.3f} bins per 10 cm, "
              f"{np.polyval(coef, 0.05):+.3f} at 5 cm, {np.polyval(coef, 0.40):+.3f} at 40 cm")
    rest = per_zone - lines
    # the edge with each (frame, zone) moved by a structured part of its shift only (linearised): what a timing term
    # of the model that is a function of distance (common), or of distance per zone, could remove
    for name, part in (("the common shift (a function of distance)", np.repeat(common[:, None], 9, 1)),
                       ("the common shift and each zone's line in distance", common[:, None] + lines)):
        left = ((cat["edge_r"] + cat["edge_d"] * part[..., None]) ** 2).sum()
        print(f"  the edge moved by {name}: {left / edge * 100:.1f} % of its squared residual left; RMS "
              f"{np.sqrt((total - edge + left) / n):.2f}")
    zsq = cat["zone_sq"].sum(0)
    print("  held-out RMS by zone: " + " ".join(f"{z + 1}: {np.sqrt(zsq[z] / (n / 9)):.2f}" for z in range(9))
          + f"; without zones 6 and 7: {np.sqrt((zsq.sum() - zsq[5] - zsq[6]) / (n * 7 / 9)):.2f}")
    print(f"shift (bins): rms {shift.std():.4f}; common to the frame's zones {common.std():.4f}; each zone's line in "
          f"distance {lines.std():.4f}; the rest {rest.std():.4f}")
    # the common shift: a smooth function of distance, or of the sub-bin phase?
    ph5 = phase[:, 4]
    for name, a in (("distance (quartic)", _design(z0, None)), ("distance + phase harmonics 1, 2", _design(z0, ph5)),
                    ("phase harmonics 1, 2 alone", _design(z0, ph5)[:, [0, 5, 6, 7, 8]])):
        coef = np.linalg.lstsq(a, common, rcond=None)[0]
        left = common - a @ coef
        extra = (f"; phase amplitudes {np.hypot(coef[5], coef[6]):.4f}, {np.hypot(coef[7], coef[8]):.4f} bins"
                 if a.shape[1] == 9 else "")
        print(f"  common shift explained by {name}: rms left {left.std():.4f} of {common.std():.4f}{extra}")
    # per zone: does the shift about its distance trend depend on that zone's phase?
    a_all = []
    for z in range(9):
        a = _design(z0, phase[:, z])
        coef = np.linalg.lstsq(a, shift[:, z], rcond=None)[0]
        a_all.append(np.hypot(coef[5], coef[6]))
    print("  per zone, first phase harmonic of the shift (about a quartic in distance), bins:",
          " ".join(f"{v:.3f}" for v in a_all))
    bright = cat["peak_counts"]
    print(f"width (relative sigma): rms {cat['width'].std():.3f}; mean by distance "
          + ", ".join(f"{lo * 100:.0f}-{hi * 100:.0f} cm {cat['width'][(z0 >= lo) & (z0 < hi)].mean():+.3f}"
                      for lo, hi in ((0.05, 0.10), (0.10, 0.20), (0.20, 0.30), (0.30, 0.41))))
    # brightness at a given distance: the zones' shifts about their own lines against their peak counts
    lb = np.log(bright) - np.log(bright).mean(1, keepdims=True)
    print(f"  rest of the shift against the zone's brightness within the frame: corr {np.corrcoef(lb.ravel(), rest.ravel())[0, 1]:+.2f}")
    wz = cat["width"] - cat["width"].mean(1, keepdims=True)
    slope = np.polyfit(lb.ravel(), wz.ravel(), 1)[0]
    print(f"  width about the frame's mean against the zone's brightness within the frame: corr "
          f"{np.corrcoef(lb.ravel(), wz.ravel())[0, 1]:+.2f} ({slope:+.3f} per e-fold of peak counts)")
    print("  mean width by zone: " + " ".join(f"{z + 1}: {cat['width'][:, z].mean():+.3f}" for z in range(9))
          + "; mean brightness / zone 5: " + " ".join(f"{v:.2f}" for v in (bright / bright[:, 4:5]).mean(0)))
    _subbin_test(cat)
    # the most a shape fixed relative to the return at sub-bin resolution could remove: the mean relative residual in
    # 1/8-bin cells of the edge bins' position relative to the return, shared by all frames or one per zone
    x, rel, w = cat["edge_x"], cat["edge_rel"], cat["edge_w"]
    cell = np.floor(x * 8).astype(int)
    for name, key in (("shared by the zones", np.zeros_like(cell)), ("one per zone", np.broadcast_to(
            np.arange(9)[None, :, None], cell.shape))):
        k = cell * 16 + key
        fix = np.zeros_like(rel)
        for v in np.unique(k):  # the weighted least-squares correction of each cell
            m = k == v
            fix[m] = (rel[m] * w[m] ** 2).sum() / (w[m] ** 2).sum()
        left = (((rel - fix) * w) ** 2).sum() / ((rel * w) ** 2).sum()
        print(f"  a pulse shape at 1/8 bin, {name}, could remove at most {(1 - left) * 100:.1f} % of the edge's squared residual")

    fig, ax = plt.subplots(1, 3, figsize=(16, 4.6))
    sc = ax[0].scatter(z0 * 100, common, c=ph5, cmap="twilight", vmin=0, vmax=1, s=18)
    fig.colorbar(sc, ax=ax[0], label="sub-bin phase of zone 5's return")
    ax[0].set_xlabel("distance (cm)"); ax[0].set_ylabel("timing shift, data - model (bins)")
    ax[0].set_title("common to a frame's zones")
    for z in range(9):
        o = np.argsort(z0)
        ax[1].plot(z0[o] * 100, per_zone[o, z], ".-", ms=3, label=f"zone {z + 1}")
    ax[1].set_xlabel("distance (cm)"); ax[1].set_ylabel("bins"); ax[1].set_title("each zone less the common shift")
    ax[1].legend(fontsize=7, ncol=3)
    x = cat["edge_x"].ravel() - np.floor(cat["edge_x"].ravel())
    sc = ax[2].scatter(x, cat["edge_rel"].ravel() * 100, c=np.repeat(z0 * 100, 18), s=5, cmap="viridis")
    fig.colorbar(sc, ax=ax[2], label="distance (cm)")
    ax[2].set_xlabel("sub-bin position of the edge bin relative to the return (frac)")
    ax[2].set_ylabel("(model - data) / peak (%)"); ax[2].set_title("rising edge, bins peak-2..-1")
    fig.tight_layout()
    fig.savefig(out_png, dpi=70)


def main(args: list[str]) -> None:
    *pairs, out_png = args
    runs = [analyse(pairs[i], pairs[i + 1]) for i in range(0, len(pairs), 2)]
    report(runs, out_png)


if __name__ == "__main__":
    main(sys.argv[1:])
