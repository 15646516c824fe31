"""Three untried answers to what keeps diff's own tilt on the real halves at 0.10-0.11 deg per axis frame to frame
(peak 0.05-0.07), tried; and where the extra scatter sits in the zones' timing (docs/results.md, the unit model,
step 12).

    python docs/figures/diff_timing_variants.py pulse FRAMES                  # forward fit: a pulse at each ray's delay
    python docs/figures/diff_timing_variants.py nuisance CAL A B [--orders 2] [--sd 0.005]
    python docs/figures/diff_timing_variants.py shift CAL A B [--window LO HI]
    python docs/figures/diff_timing_variants.py modes CAL A B

``pulse``: the forward fit (``forward_fit.fit_forward``, defaults) of FRAMES with the model as it is and with the
laser pulse read at each ray's continuous delay (the reference, read at ``x / ref_time_scale``, blurred by a Gaussian
of ``soft_bin_sigma`` and integrated over one bin, looked up at ``n - u`` for every ray; ``--no-box``: not integrated)
in place of the pulse at whole-bin lags convolved with the ray's soft-binned Gaussian: a time-to-digital converter
counting a continuous pulse in its bins. Prints both fits' RMS scaled residual.

``nuisance``: diff's own plane (``diff_tilt_scatter.py``'s report, fallback limits null, no plane correction) with
each zone's histogram given per-frame shape terms under a Gaussian prior of ``--sd``: ``h_z + e_z D^k h_z`` for the
centred difference ``D^k`` of each order in ``--orders`` (1 a time shift, 2 a width, 3 a skew), solved with the plane
by Levenberg-Marquardt. ``--sd 1e-6`` holds them (the control: reproduces diff).

``shift``: diff's plane from the zones' time shifts alone: at the current plane each zone's residual and each plane
derivative are projected on that zone's (amplitude, time shift) pair, and the plane step fits the shifts weighted by
their Fisher information (the shape beyond the shift does not inform the plane); ``--window`` keeps only the bins LO..HI
about each zone's highest.

``modes``: at the true plane of every frame of A and B, each zone's timing misfit by peak (its calibrated range less
the true range), by diff's model (the data's centroid less the model's, +-3 bins about each, fractional edges) and
by a shift fit of the model (the ``shift`` projection), about a smooth curve in 1 / z0 per zone; split into the grid's
modes: common (moves the range), x and y gradients (move the tilt) and the rest; and whether the model's misfit
follows each zone's sub-bin position (harmonics fitted on one file, tested on the other).
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import diff_tilt_scatter as dts  # noqa: E402  (the scatter report)

from place_safe.calibration import Calibration  # noqa: E402
from place_safe.calibration import forward_fit as ff  # noqa: E402
from place_safe.calibration.point_errors import true_ranges  # noqa: E402
from place_safe.cli.common import load_truth_frames  # noqa: E402
from place_safe.geometry import Plane  # noqa: E402
from place_safe.io.frame_file import load_frames  # noqa: E402
from place_safe.recovery import differentiable as dm, forward as fw, make_estimator  # noqa: E402
from place_safe.recovery.differentiable import _LOWER, _UPPER, convolution_matrices, residual_weights  # noqa: E402
from place_safe.recovery.forward import ZoneRays, mount_rotation  # noqa: E402
from place_safe.recovery.plane_renderer import PlaneRenderer  # noqa: E402
from place_safe.sensor.frame import N_BINS, N_ZONES  # noqa: E402

# ---------------------------------------------------------------------------------------------------------- pulse
FINE = 8  # samples per bin of the continuous pulse
PAD = 4  # bins before lag 0 the blurred pulse may reach
BOX = True


def fine_pulse(reference, time_scale, ref_floor, sigma):
    """The pulse Q(x) at x = -PAD + j / FINE bins (B, L): the reference (floor off, tail smoothed, peak 1) read at
    ``x / time_scale``, blurred by a Gaussian of ``sigma`` bins and (``BOX``) integrated over one bin."""
    ref = torch.clamp(reference - ref_floor, min=0.0)
    ref = fw._smooth_tail(ref)
    ref = ref / torch.clamp(ref.amax(dim=-1, keepdim=True), min=1e-12)
    k_len = int(math.floor((N_BINS - 1) * float(torch.as_tensor(time_scale).detach()))) + 1
    n = (k_len + 2 * PAD) * FINE
    pos = (torch.arange(n, dtype=ref.dtype) / FINE - PAD) / time_scale
    inside = (pos >= 0) & (pos <= N_BINS - 1)
    lo = torch.clamp(torch.floor(pos), 0, N_BINS - 2)
    frac = torch.clamp(pos - lo, 0.0, 1.0)
    p = (ref[..., lo.long()] * (1 - frac) + ref[..., lo.long() + 1] * frac) * inside
    half = int(math.ceil(4.5 * FINE))
    y = torch.arange(-half, half + 1, dtype=ref.dtype) / FINE
    s = torch.clamp(sigma, min=1e-3) * math.sqrt(2.0)
    taps = (0.5 * (torch.erf((y + 0.5) / s) - torch.erf((y - 0.5) / s)) if BOX
            else torch.exp(-(y / s) ** 2) / (s * math.sqrt(math.pi))) / FINE
    q = torch.nn.functional.conv1d(torch.nn.functional.pad(p.reshape(-1, 1, n), (half, half)),
                                   taps.flip(0).view(1, 1, -1))
    return q.reshape(p.shape)


def lookup(q, u, n_bins):
    """Q(n - u) (B, 9, R, n_bins) by linear interpolation in the tables ``q`` (B, L) at ray positions ``u`` (B, 9, R)."""
    pos = (torch.arange(n_bins, dtype=u.dtype).view(1, 1, 1, -1) - u.unsqueeze(-1) + PAD) * FINE
    i0 = torch.floor(pos).detach()
    frac = pos - i0
    i0 = i0.long()
    ok = (i0 >= 0) & (i0 < q.shape[-1] - 1)
    idx = torch.clamp(i0, 0, q.shape[-1] - 2)
    b, z, r, n = idx.shape
    a = torch.gather(q, 1, idx.reshape(b, -1)).reshape(b, z, r, n)
    c = torch.gather(q, 1, idx.reshape(b, -1) + 1).reshape(b, z, r, n)
    return (a * (1 - frac) + c * frac) * ok


class DelayedPulseModel(fw.ForwardModel):
    """The forward model with the pulse read at each ray's continuous delay: its soft binning and pulse convolution
    (:meth:`~place_safe.recovery.forward.ForwardModel.bin_arrivals`) replaced, the rays' counts and positions and
    everything after the pulse as the model's."""

    def bin_arrivals(self, amp, u, reference, kernel=None, n_bins=N_BINS):
        t = self.t
        q = fine_pulse(torch.as_tensor(reference, dtype=self.dtype).expand(amp.shape[0], N_BINS), t["ref_time_scale"],
                       t["ref_floor"], t["soft_bin_sigma"])
        amp, u = torch.broadcast_tensors(amp, u)
        return torch.einsum("bzr,bzrn->bzn", amp, lookup(q, u, n_bins))


def pulse(args) -> None:
    global BOX
    BOX = not args.no_box
    frames = load_frames(args.frames)
    plain = ff.ForwardModel
    for name, model in (("as it is", plain), ("pulse at each ray's delay", DelayedPulseModel)):
        ff.ForwardModel = model
        params, rep = ff.fit_forward(frames, progress=False)
        print(f"{name:26s} RMS scaled residual {rep['rms_scaled_residual_before']:.3f} -> "
              f"{rep['rms_scaled_residual_after']:.3f} ({rep['why']}); soft_bin_sigma {params.soft_bin_sigma:.3f}")
    ff.ForwardModel = plain


# ------------------------------------------------------------------------------------------- nuisance, shift
def centred_difference(h: np.ndarray, order: int) -> np.ndarray:
    """The centred difference of ``order`` (1-3) along the last axis, zero beyond the ends."""
    p = np.pad(h, [(0, 0)] * (h.ndim - 1) + [(2, 2)])
    if order == 1:
        return 0.5 * (p[..., 3:-1] - p[..., 1:-3])
    if order == 2:
        return p[..., 3:-1] - 2 * p[..., 2:-2] + p[..., 1:-3]
    return 0.5 * (p[..., 4:] - 2 * p[..., 3:-1] + 2 * p[..., 1:-3] - p[..., :-4])


def _setup(est, frames):
    """What diff's fast solver prepares: observed counts, weights (zeroed past each frame's window), renderer inputs,
    the start (peak's plane, albedos by least squares)."""
    hists = np.array([f.hists for f in frames], dtype=float)
    obs_full, amb = est._observed(hists)
    own = np.minimum(N_BINS, obs_full.argmax(axis=-1).max(axis=-1) + est.opt.window_after_peak)
    width = int(own.max())
    obs = obs_full[..., :width]
    w = residual_weights(hists[..., :width], est.params.model_error) * (np.arange(width) < own[:, None])[:, None, :]
    kernels = est._kernels(frames)
    rd = est._renderer
    conv = rd.responses(convolution_matrices(kernels, width))
    return obs, amb, own, width, w, kernels, conv


def _start(est, inits, obs, conv, amb):
    rd = est._renderer
    nu = rd.n_unknowns
    n_alb = nu - 5
    x = np.zeros((len(inits), nu))
    for i, p in enumerate(inits):
        x[i, :3] = p.slopes
    x[:, 3:3 + n_alb] = math.log(est.params.albedo)
    x[:, nu - 2] = est.params.specular_weight
    x[:, nu - 1] = math.log(est.params.specular_exponent)
    for _ in range(2):
        h = rd.render(x, conv, ambient=amb)
        scale = (h * obs).sum(axis=2) / np.maximum((h * h).sum(axis=2), 1e-12)
        x[:, 3:3 + n_alb] += np.log(np.clip(scale, 1e-3, 1e3)).reshape(len(inits), -1)
    return x


def nuisance_solver(orders, sd):
    def solve(self, frames, inits):
        obs, amb, own, width, w, _, conv = _setup(self, frames)
        rd = self._renderer
        nb, nu = len(frames), rd.n_unknowns
        n_alb, ne = nu - 5, N_ZONES * len(orders)
        x = np.concatenate([_start(self, inits, obs, conv, amb), np.zeros((nb, ne))], 1)
        lower = np.concatenate([_LOWER[:3], np.full(n_alb, _LOWER[3]), _LOWER[4:], np.full(ne, -2.0)])
        upper = np.concatenate([_UPPER[:3], np.full(n_alb, _UPPER[3]), _UPPER[4:], np.full(ne, 2.0)])
        prior_mu = np.array([self.params.specular_weight, math.log(self.params.specular_exponent)])
        prior_w = 1.0 / np.array([self.opt.prior_specular_weight, self.opt.prior_log_exponent])
        centre = (np.eye(n_alb) - 1.0 / n_alb) / self.opt.zone_albedo_spread
        n_hist, n_pr = N_ZONES * width, 2 + n_alb + ne
        Jp = np.zeros((n_pr, nu + ne))
        Jp[0, nu - 2], Jp[1, nu - 1] = prior_w
        Jp[2:2 + n_alb, 3:3 + n_alb] = centre
        Jp[2 + n_alb:, nu:] = np.eye(ne) / sd

        def residual(xs, jac=False):
            out = rd.render(xs[:, :nu], conv, jacobian=jac, ambient=amb)
            h, dh = out if jac else (out, None)
            e = xs[:, nu:].reshape(nb, len(orders), N_ZONES)
            dif = [centred_difference(h, o) for o in orders]
            hh = h + sum(e[:, k, :, None] * dif[k] for k in range(len(orders)))
            res = np.concatenate([((hh - obs) * w).reshape(nb, -1), (xs[:, nu - 2:nu] - prior_mu) * prior_w,
                                  xs[:, 3:3 + n_alb] @ centre.T, xs[:, nu:] / sd], 1)
            if not jac:
                return res
            J = np.zeros((nb, n_hist + n_pr, nu + ne))
            dhh = dh + sum(e[:, k, :, None, None] * centred_difference(np.moveaxis(dh, -1, -2), o).swapaxes(-1, -2)
                           for k, o in enumerate(orders))
            J[:, :n_hist, :nu] = (dhh * w[..., None]).reshape(nb, n_hist, nu)
            for k in range(len(orders)):
                for z in range(N_ZONES):
                    col = np.zeros((nb, N_ZONES, width))
                    col[:, z] = dif[k][:, z] * w[:, z]
                    J[:, :n_hist, nu + k * N_ZONES + z] = col.reshape(nb, -1)
            J[:, n_hist:] = Jp
            return res, J

        lam = np.full(nb, 1e-3)
        r, J = residual(x, True)
        cost = (r * r).sum(1)
        for _ in range(40):
            JtJ = J.transpose(0, 2, 1) @ J
            g = (J.transpose(0, 2, 1) @ r[..., None])[..., 0]
            diag = np.einsum("bii->bi", JtJ) + 1e-12
            moved = False
            for _ in range(10):
                A = JtJ + lam[:, None, None] * np.einsum("bi,ij->bij", diag, np.eye(nu + ne))
                xn = np.clip(x - np.linalg.solve(A, g[..., None])[..., 0], lower, upper)
                cn = (residual(xn) ** 2).sum(1)
                better = cn < cost
                x[better], cost[better] = xn[better], cn[better]
                lam[better] *= 0.3
                lam[~better] *= 10
                if better.any():
                    moved = True
                    break
            r, J = residual(x, True)
            cost = (r * r).sum(1)
            if not moved or np.all(lam > 1e7):
                break
        chi2 = (r[:, :n_hist] ** 2).sum(1) / np.maximum(N_ZONES * own - nu - ne, 1)
        cov = np.linalg.pinv(J.transpose(0, 2, 1) @ J)[:, :3, :3] * chi2[:, None, None]
        xr = np.concatenate([x[:, :3], x[:, 3:3 + n_alb].mean(axis=1, keepdims=True)], axis=1)
        return [self._finish(xr[i], float(cost[i]), int(N_ZONES * own[i]), cov[i]) for i in range(nb)]
    return solve


SHIFT_STEP = 0.01  # bins: the time shift of the renderer copy whose difference is each zone's shift derivative


def _shifted_renderer(est) -> PlaneRenderer:
    return PlaneRenderer(est.params.model_copy(update={"bin_offset": est.params.bin_offset + SHIFT_STEP}),
                         ZoneRays.stratified(est.opt.rays), zone_albedo=est.opt.zone_albedo)


def zone_shifts(h, hs, dh, obs, w2):
    """Per zone the least-squares (amplitude share, time shift) of the residual ``obs - h`` on (h, dh/dshift), the
    shift per unit of each plane unknown (a, b, z0) by the same projection of ``dh``, and the shift's Fisher
    information with the amplitude free: (s (B, 9), g (B, 9, 3), info (B, 9), amplitude share (B, 9))."""
    basis = np.stack([h, (hs - h) / SHIFT_STEP], -1)
    btb = np.einsum("bzwi,bzw,bzwj->bzij", basis, w2, basis)
    coef = np.linalg.solve(btb, np.einsum("bzwi,bzw,bzw->bzi", basis, w2, obs - h)[..., None])[..., 0]
    g = np.linalg.solve(btb, np.einsum("bzwi,bzw,bzwk->bzik", basis, w2, dh[..., :3]))[..., 1, :]
    return coef[..., 1], g, 1.0 / np.linalg.inv(btb)[..., 1, 1], coef[..., 0]


def shift_solver(window):
    def solve(self, frames, inits):
        obs, amb, own, width, w, kernels, conv = _setup(self, frames)
        if window is not None:
            rel = np.arange(width) - obs.argmax(-1)[..., None]
            w = w * ((rel >= window[0]) & (rel <= window[1]))
        rd, rs = self._renderer, _shifted_renderer(self)
        conv_s = rs.responses(convolution_matrices(kernels, width))
        nu = rd.n_unknowns
        n_alb = nu - 5
        x = _start(self, inits, obs, conv, amb)
        for _ in range(8):
            h, dh = rd.render(x, conv, jacobian=True, ambient=amb)
            s, g, info, share = zone_shifts(h, rs.render(x, conv_s, ambient=amb), dh, obs, w * w)
            a = np.einsum("bzk,bz,bzl->bkl", g, info, g)
            x[:, :3] += np.linalg.solve(a, np.einsum("bzk,bz,bz->bk", g, info, s)[..., None])[..., 0]
            share = np.log(np.clip(1 + share, 0.2, 5))
            x[:, 3:3 + n_alb] += share if n_alb > 1 else share.mean(1, keepdims=True)
        chi = ((obs - rd.render(x, conv, ambient=amb)) * w) ** 2
        chi2 = chi.sum((1, 2)) / np.maximum(N_ZONES * own - nu, 1)
        cov = np.linalg.inv(a) * np.maximum(chi2, 1)[:, None, None]
        xr = np.concatenate([x[:, :3], x[:, 3:3 + n_alb].mean(axis=1, keepdims=True)], axis=1)
        return [self._finish(xr[i], float(chi[i].sum()), int(N_ZONES * own[i]), cov[i])
                for i in range(len(frames))]
    return solve


def scatter(args, solver) -> None:
    dm.DifferentiableEstimator._solve_fast = solver
    cal = Calibration.load(args.calibration)
    dts.report(dts.slope_errors(cal, [args.a, args.b]), cal, [args.a, args.b])


# ---------------------------------------------------------------------------------------------------------- modes
def modes(args) -> None:
    cal = Calibration.load(args.calibration)
    est = make_estimator("diff", dts.own_calibration(cal, None))
    first = load_truth_frames([args.a], 0.05, None)[0]
    frames = sorted(first + load_truth_frames([args.b], 0.05, None)[0], key=lambda f: f.truth.z0)
    in_a = np.array([any(f is g for g in first) for f in frames])
    z = np.array([f.truth.z0 for f in frames])
    to_optical = mount_rotation(cal.forward().mount_tilt).numpy().T
    obs, amb, _, width, w, kernels, conv = _setup(est, frames)
    rd, rs = est._renderer, _shifted_renderer(est)
    x = _start(est, [Plane(to_optical @ f.truth.normal, f.truth.offset) for f in frames], obs, conv, amb)
    h, dh = rd.render(x, conv, jacobian=True, ambient=amb)
    rel = np.arange(width) - obs.argmax(-1)[..., None]
    s, g, info, _ = zone_shifts(h, rs.render(x, rs.responses(convolution_matrices(kernels, width)), ambient=amb), dh,
                                obs, (w * (rel >= -3)) ** 2)
    n = np.arange(width)

    def centroid(a, half=3.0):
        c = a.argmax(-1).astype(float)
        for _ in range(4):
            wgt = np.clip(half + 0.5 - np.abs(n - c[..., None]), 0, 1)
            c = (a * wgt * n).sum(-1) / (a * wgt).sum(-1)
        return c

    smooth = np.vander(1 / z, dts.SMOOTH_DEGREE + 1)
    about = lambda e: e - smooth @ np.linalg.lstsq(smooth, e, rcond=None)[0]  # noqa: E731  (F, 9) columns
    pp = cal.peak()
    pos, _, _ = pp.peaks(np.array([f.hists for f in frames], dtype=float))
    peak_err = (pp.ranges(pos) - true_ranges(np.array([f.truth.normal for f in frames]),
                                             np.array([f.truth.offset for f in frames]), pp.directions())
                ) / est.params.bin_size
    grid = np.array([[1.0, (k % 3) - 1, (k // 3) - 1] for k in range(N_ZONES)])
    model_c = centroid(h)
    misfits = {"peak (range less truth)": about(peak_err), "diff's model (centroid, data less model)":
               about(centroid(obs) - model_c), "diff's model (shift fit)": about(s)}
    print(f"{len(z)} frames, 5-40 cm; per zone about a smooth curve in 1/z0; bins rms")
    print("misfit | per zone | common | x gradient | y gradient | rest | tilt through diff's zone derivatives a / b (deg)")
    co = {}
    for name, e in misfits.items():
        co[name] = np.linalg.lstsq(grid, e.T, rcond=None)[0].T
        rest = e - co[name] @ grid.T
        step = np.linalg.solve(np.einsum("bzk,bzl->bkl", g, g), np.einsum("bzk,bz->bk", g, e)[..., None])[..., 0]
        tilt = np.degrees(np.sqrt(np.mean(np.stack([about(step[:, 0]), about(step[:, 1])], 1) ** 2, 0)))
        print(f"{name} | {np.sqrt(np.mean(e ** 2)):.4f} | " + " | ".join(
            f"{np.sqrt(np.mean(co[name][:, i] ** 2)):.4f}" for i in range(3)) +
            f" | {np.sqrt(np.mean(rest ** 2)):.4f} | {tilt[0]:.3f} / {tilt[1]:.3f}")
    p, d = co["peak (range less truth)"], co["diff's model (centroid, data less model)"]
    print("correlation of peak's and the model's modes: common %.2f, x %.2f, y %.2f" % tuple(
        abs(np.corrcoef(p[:, i], d[:, i])[0, 1]) for i in range(3)))
    e = misfits["diff's model (centroid, data less model)"]
    phase = 2 * np.pi * (model_c % 1.0)
    for harmonics in (1, 2, 3):
        left = e.copy()
        for k in range(N_ZONES):
            design = np.concatenate([np.stack([np.sin(m * phase[:, k]), np.cos(m * phase[:, k])], 1)
                                     for m in range(1, harmonics + 1)], 1)
            for fit in (in_a, ~in_a):
                left[~fit, k] = e[~fit, k] - design[~fit] @ np.linalg.lstsq(design[fit], e[fit, k], rcond=None)[0]
        print(f"the model's misfit less a function of each zone's sub-bin position (harmonics 1..{harmonics}, fitted "
              f"on one file, read on the other): {np.sqrt(np.mean(e ** 2)):.4f} -> {np.sqrt(np.mean(left ** 2)):.4f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    p = sub.add_parser("pulse")
    p.add_argument("frames")
    p.add_argument("--no-box", action="store_true")
    for name in ("nuisance", "shift", "modes"):
        q = sub.add_parser(name)
        q.add_argument("calibration")
        q.add_argument("a")
        q.add_argument("b")
        if name == "nuisance":
            q.add_argument("--orders", type=int, nargs="+", default=[2], choices=(1, 2, 3))
            q.add_argument("--sd", type=float, default=0.005)
        if name == "shift":
            q.add_argument("--window", type=int, nargs=2, default=None)
    args = ap.parse_args()
    torch.set_num_threads(1)
    if args.what == "pulse":
        pulse(args)
    elif args.what == "nuisance":
        scatter(args, nuisance_solver(args.orders, args.sd))
    elif args.what == "shift":
        scatter(args, shift_solver(args.window))
    else:
        modes(args)


if __name__ == "__main__":
    main()
