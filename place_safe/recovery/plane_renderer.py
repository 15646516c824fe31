"""Fast rendering of planes with the forward model, with its analytic Jacobian (numpy).

The same model as :class:`place_safe.recovery.forward.ForwardModel` (which stays the reference and the
tool for calibration), specialised to a plane and to the six unknowns the solver estimates per frame

    x = (a, b, z0, log albedo, specular weight, log specular exponent),

(with ``zone_albedo`` each zone's log albedo, and with ``free_crosstalk`` the frame's scalar crosstalk after the albedo:
``(a, b, z0, log albedo(s), crosstalk, specular weight, log specular exponent)``; the crosstalk's column is
``d F / d c = sum over zones of P - (1 - crosstalk_self) P``, P the counts before the zones mix, then the pile-up),

where the plane is ``a x + b y + z = z0`` (normal ``~ (a, b, 1)``, ``z0`` where it meets the optical
axis). Everything that does not depend on ``x`` (ray directions and weights, zone gains, the pulse
as a convolution matrix) is prepared once, and the Jacobian is accumulated alongside the
histogram in the same array passes, so one solver iteration costs a few hundred microseconds
instead of the tens of milliseconds of operator-by-operator autodiff.

Chain of the derivatives, per ray with direction ``v``::

    q = a v_x + b v_y + v_z,   r = z0 / q,   c = q / s,   s = sqrt(1 + a^2 + b^2)
    h = c + k S^alpha,   S = max(2 c^2 - 1, 0)              (shading)
    p = sat (1 - exp(-g^v rho h^w / (sat r^2))) h^(1-w) g^(1-v),   w = saturate_shading, v = saturate_gain
    u = r / bin_size * zone_bin_scale + bin_offset + zone_offset
    T(bin) = sum_rays w p G(bin - u),      G = Gaussian of soft_bin_sigma (blended with its integral over the bin
                                           by soft_bin_integrated, version 7, or convolved with the quadratic
                                           B-spline, soft_bin_spline, version 8: forward.bin_kernel)
    F = crosstalk-mix(zone-tail(response(T * pulse))),   H = pile-up(F)   (mix: h + c (total - (1 - crosstalk_self) h))   (Coates; identity when ``pileup = 0``)

With the emitter at ``E = (bx, by, 0)`` (``baseline``) the light's range ``r_e = |r v - E|`` replaces ``r`` in
the inverse square, ``c = (z0 - a bx - b by) / (s r_e)`` is the light's cosine, the flux is weighted by the
beam ``(r v_z / r_e)^beam_power`` and ``u`` uses the one-way range ``(r + r_e) / 2``.

The unit terms of :class:`~place_safe.recovery.forward.ForwardParams` (version 3) follow
``ForwardModel``: the multipath echo appends each ray again at twice its one-way range with ``echo_gain (0.1 m /
range)^echo_power`` of its amplitude (its derivatives by the chain above), the cover-glass return adds a fixed Gaussian per
zone at ``bin_offset + glass_delay + zone_offset`` (no derivative in x), and the neighbour crosstalk
(``crosstalk_grid``) is a (9, 9) matrix applied with the scalar crosstalk. Version 4: each zone's pulse width and
skew are causal (9, 128, 128) matrices folded in before the response and tails, and the pile-up's shadowing of later bins is
weighted by ``pileup_shadow``. Version 5: the bins' widths (``bin_gains``) multiply the expected counts before the pile-up, and the time warp
(``time_warp``) moves every position ``u`` to ``u + warp(u)`` (its slope multiplies ``d u / d x``). Version 6: each
zone's time scale (``zone_bin_scales``) multiplies ``r / bin_size`` (and the echo's ``2 r / bin_size``) and ``d u / d x``.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import torch
from numpy.lib.stride_tricks import sliding_window_view

from place_safe.recovery.forward import (ECHO_REFERENCE_RANGE, ForwardModel, ForwardParams, ZoneRays, bin_kernel,
                                         bin_widths, grid_crosstalk_matrix, pulse_shape_matrix, response_matrix, warp_positions,
                                         zone_tail_taps)
from place_safe.sensor.frame import N_BINS, N_ZONES

N_UNKNOWNS = 6
#: soft-bin kernel widths (``soft_bin_sigma``) from a ray's position beyond which
#: :meth:`PlaneRenderer.soft_bin_window` takes the kernel as 0 (the Gaussian there is below ``exp(-40)`` of its peak)
SOFT_BIN_REACH = 9.0


def convolution_matrices(kernels: np.ndarray, width: int) -> np.ndarray:
    """Causal convolution as matrices (B, width, width): ``(T @ M^T)[j] = sum_k K[k] T[j-k]``, i.e.
    ``M[j, i] = K[j - i]`` for ``0 <= j - i < K`` (kernels (B, K)), else 0."""
    b, k_len = kernels.shape
    n = min(k_len, width)
    line = np.zeros((b, 2 * width - 1))  # line[width - 1 + lag] = K[lag]: row j of M is line[width - 1 + j - i] over i
    line[:, width - 1:width - 1 + n] = kernels[:, :n]
    return sliding_window_view(line[:, ::-1], width, axis=1)[:, ::-1].copy()  # a copy of windows: no index arrays


class PlaneRenderer:
    """Histograms of planes and their Jacobian in the unknowns (``a, b, z0``, one log albedo or one per zone, with
    ``free_crosstalk`` the frame's crosstalk, the specular weight and log exponent: :attr:`n_unknowns`), batched over
    frames."""

    def __init__(self, params: ForwardParams, rays: ZoneRays, zone_albedo: bool = False,
                 free_crosstalk: bool = False) -> None:
        self.p = params
        dirs, w = ForwardModel(params, rays).ray_geometry()  # field-of-view scales applied
        self.dirs = dirs.detach().cpu().numpy().astype(float)  # (9, R, 3)
        w = w.detach().cpu().numpy().astype(float)
        gain = params.kind_gains()[:, None]  # (9, 1)
        w_g = params.saturate_gain
        self.gain = gain ** w_g  # the part of the zone gain inside the saturation
        self.amp_weight = w * float(params.rays_per_zone) * gain ** (1.0 - w_g)  # (9, R), the rest after it
        self.offsets = np.asarray(params.zone_offsets, dtype=float)[:, None]  # (9, 1)
        self.scales = np.asarray(params.zone_bin_scales, dtype=float)[:, None]  # (9, 1): each zone's time scale
        #: bins on either side of a ray's position within which its soft-bin kernel is evaluated (beyond them the
        #: kernel is below 1e-17 of its peak and taken as 0; :meth:`soft_bin_window`; the spline's reaches 3/2 bin
        #: further)
        self.reach = int(math.ceil(SOFT_BIN_REACH * params.soft_bin_sigma + 1.5 * params.soft_bin_spline)) + 1
        self._span = np.arange(2 * self.reach)
        #: with ``zone_albedo`` the unknowns are (a, b, z0, log albedo of zones 1..9, ks, log alpha):
        #: each zone's brightness is free, so only timing and shape inform the plane
        self.zone_albedo = zone_albedo
        #: with ``free_crosstalk`` the scalar crosstalk of the frame is an unknown too, after the albedo(s) and before
        #: the specular weight: (a, b, z0, log albedo(s), crosstalk, ks, log alpha); its column (None: held at
        #: ``params.crosstalk``)
        self.crosstalk_column = 3 + (N_ZONES if zone_albedo else 1) if free_crosstalk else None
        self.n_unknowns = N_UNKNOWNS + (N_ZONES - 1 if zone_albedo else 0) + (1 if free_crosstalk else 0)
        self.integrated = float(params.soft_bin_integrated)  # > 0: the kernel integrated over each bin (bin_kernel)
        self.spline = float(params.soft_bin_spline)  # 1: the quadratic B-spline convolved with the Gaussian (bin_kernel)
        # the emitter beside the receiver (ForwardModel.plane_light); None: co-located, uniform beam
        bx, by = (float(v) for v in params.baseline)
        self.light = None if (bx == 0.0 and by == 0.0 and params.beam_power == 0.0) else (
            bx, by, self.dirs[..., 0] * bx + self.dirs[..., 1] * by, float(params.beam_power))
        self.light_dnum = np.array([-bx, -by, 1.0])[:, None, None, None]  # d (z0 - a bx - b by) / d (a, b, z0)
        self.dirs_xy = np.moveaxis(self.dirs[..., :2], -1, 0)[:, None]  # (2, 1, 9, R): the rays' x and y
        # each zone's own tail (ForwardModel: add_zone_tails) as (9, 128, 128) causal matrices; a narrower
        # histogram uses their top-left corner (causal: the first W bins depend on the first W only). None: no tails
        # The learned impulse response (ForwardModel.after_pulse: add_response, before the tails) is folded in:
        # both are causal convolutions, so their matrices multiply
        self.tail_mats = None
        if np.any(np.asarray(params.zone_tail_weights) != 0.0):
            taps = zone_tail_taps(params.zone_tail_weights, params.zone_tail_decays).numpy()
            self.tail_mats = convolution_matrices(np.hstack([np.ones((N_ZONES, 1)), taps]), N_BINS)
        if np.any(np.asarray(params.response_kernel) != 0.0):
            resp = response_matrix(params.response_kernel, N_BINS).numpy()
            self.tail_mats = (np.broadcast_to(resp, (N_ZONES, N_BINS, N_BINS)) if self.tail_mats is None
                              else self.tail_mats @ resp)
        # each zone's pulse width and skew (ForwardModel.after_pulse: first, before the response), causal as well
        self.shaped = bool(np.any(np.asarray(params.zone_pulse_widths) != 0.0)
                           or np.any(np.asarray(params.zone_pulse_skews) != 0.0))
        if self.shaped:
            shape = pulse_shape_matrix(params.zone_pulse_widths, params.zone_pulse_skews, N_BINS).numpy()
            self.tail_mats = shape if self.tail_mats is None else self.tail_mats @ shape

        # neighbour crosstalk (ForwardModel.after_pulse) as a (9, 9) matrix M[to, from]; None: none
        self.grid_mix = (grid_crosstalk_matrix(params.crosstalk_grid).numpy()
                         if np.any(np.asarray(params.crosstalk_grid) != 0.0) else None)
        self.echo_gain = float(params.echo_gain)
        self.echo_power = float(params.echo_power)
        self.glass = (np.asarray(params.glass_gains, dtype=float) if np.any(np.asarray(params.glass_gains) != 0.0)
                      else None)
        self.glass_u = params.bin_offset + params.glass_delay + self.offsets[:, 0]  # (9,)
        # the TDC's integral non-linearity (ForwardModel.render_returns: every position, after the echo and glass)
        self.warp = (torch.as_tensor(params.time_warp, dtype=torch.float64)
                     if np.any(np.asarray(params.time_warp) != 0.0) else None)
        if self.warp is not None:
            self.glass_u = warp_positions(torch.as_tensor(self.glass_u), self.warp)[0].numpy()
        # the TDC's bin widths (ForwardModel.after_pulse: after the crosstalk, before the pile-up); None: nominal
        self.bin_gains = (bin_widths(torch.as_tensor(params.bin_gains, dtype=torch.float64)).numpy()
                          if np.any(np.asarray(params.bin_gains) != 1.0) else None)
        # the last render's rays (keyed by its planes and width) and histograms (keyed by its unknowns, width, pulse
        # matrices and ambient): :meth:`render` reuses them at the same values; each entry is one tuple, replaced whole
        self._rays_cache: tuple | None = None
        self._forward_cache: tuple | None = None

    def render(self, x: np.ndarray, conv: np.ndarray, jacobian: bool = False, ambient: np.ndarray | None = None):
        """Histograms (B, 9, W) for unknowns x (B, n_unknowns) and the frames' pulse convolution matrices (B, W, W) or, made
        once per frame for the renders of a solve, their :meth:`responses` (B, 9, W, W) (the same histograms).

        With ``jacobian`` also returns d hist / d x as (B, 9, W, n_unknowns). The model's constant floor is
        not added (the solver subtracts the measured floor from the data instead). ``ambient`` (B, 9), counts per
        bin: each zone's ambient as it arrives, which goes through the pile-up with the return; the histograms are
        then the counts above it (:func:`~place_safe.recovery.forward.ambient_pileup`; None: the return alone).

        A render at the same unknowns, with the same ``conv`` and ``ambient`` objects (not changed since), as the last
        one reuses its histograms: the solver's Jacobian at an accepted trial step adds only the derivatives. One at the
        same plane ``(a, b, z0)`` (and width) reuses the rays' geometry and soft-bin kernels (the albedo's first
        guesses). The numbers are the same as rendered afresh. The histograms returned are kept for that reuse and are
        read-only; ``conv`` and ``ambient`` must not be changed in place between renders (the objects are the key).
        """
        x = np.array(x, dtype=float)  # a copy: the caches keep what they were computed from
        width = conv.shape[-1]
        f = self._forward(x, conv, ambient, width)
        if not jacobian:
            return f.H
        return f.H, self._jacobian(x, f)

    def forget(self) -> None:
        """Drop the last render's kept arrays (:meth:`render`): the solver calls it when a solve ends, so a batch's
        pulse matrices are not held until the next one."""
        self._rays_cache = None
        self._forward_cache = None

    def _rays(self, x: np.ndarray, width: int) -> SimpleNamespace:
        """Everything of a render that depends on the planes ``(a, b, z0)`` of ``x`` alone (and the width): the rays'
        ranges, cosines and beam, their bin positions and soft-bin kernels (:meth:`soft_bin_window`; the derivative
        kernels on first need). The last one is kept."""
        key = (x[:, :3].tobytes(), x.shape[0], width)
        cached = self._rays_cache
        if cached is not None and cached[0] == key:
            return cached[1]
        p = self.p
        a, b, z0 = x[:, 0, None, None], x[:, 1, None, None], x[:, 2, None, None]
        vx, vy, vz = self.dirs[None, ..., 0], self.dirs[None, ..., 1], self.dirs[None, ..., 2]
        s = np.sqrt(1.0 + a * a + b * b)
        q = a * vx + b * vy + vz                       # (B, 9, R)
        hit = q > 1e-6
        qs = np.where(hit, q, 1.0)
        r = np.maximum(z0 / qs, 1e-4)
        c_raw = w_e = None
        if self.light is None:
            c = np.clip(qs / s, 0.0, 1.0)
            r_e, beam = r, 1.0
        else:  # light from the emitter E = (bx, by, 0): range r_e = |r v - E|, cosine (z0 - a bx - b by) / (s r_e)
            bx, by, w_e, bp = self.light
            r_e = np.sqrt(np.maximum(r * r - 2.0 * r * w_e + bx * bx + by * by, 1e-12))
            num = z0 - a * bx - b * by
            c_raw = num / (s * r_e)
            c = np.maximum(c_raw, 0.0)
            beam = np.maximum(r * vz / r_e, 1e-12) ** bp
        S = np.maximum(2.0 * c * c - 1.0, 0.0)
        pos = S > 0
        Ssafe = np.where(pos, S, 1.0)
        path = r if self.light is None else 0.5 * (r + r_e)   # one-way range (m)
        u = path / p.bin_size * self.scales + p.bin_offset + self.offsets
        n_direct = u.shape[-1]
        echo = None
        if self.echo_gain != 0.0:  # ForwardModel.add_echo_and_glass: each ray again at twice its range
            echo = self.echo_gain * (ECHO_REFERENCE_RANGE / np.maximum(path, 1e-4)) ** self.echo_power
            u = np.concatenate([u, 2.0 * path / p.bin_size * self.scales + p.bin_offset + self.offsets], axis=-1)
        slope = None
        if self.warp is not None:  # apparent positions, and d u' / d u for the derivatives
            u, slope = (v.numpy() for v in warp_positions(torch.from_numpy(u), self.warp))
        t, dense, place = self.soft_bin_window(u, width)
        G = dense(self.kernel(t))  # (B, 9, R, band)
        g = SimpleNamespace(a=a, b=b, z0=z0, s=s, hit=hit, qs=qs, r=r, r_e=r_e, c_raw=c_raw, w_e=w_e, c=c, beam=beam,
                            pos=pos, Ssafe=Ssafe, path=path, n_direct=n_direct, echo=echo, slope=slope, t=t,
                            dense=dense, place=place, G=G, G_u=None)
        self._rays_cache = (key, g)
        return g

    def _forward(self, x: np.ndarray, conv: np.ndarray, ambient, width: int) -> SimpleNamespace:
        """The histograms of ``x`` (:meth:`render`) with what their derivatives reuse. The last one is kept, with the
        ``conv`` and ``ambient`` objects it was rendered with."""
        key = (x.tobytes(), x.shape, width)
        cached = self._forward_cache
        if cached is not None and cached[0] == key and cached[2] is conv and cached[3] is ambient:
            return cached[1]
        p = self.p
        g = self._rays(x, width)
        if self.zone_albedo:
            rho = np.exp(x[:, 3:3 + N_ZONES])[:, :, None]
        else:
            rho = np.exp(x[:, 3])[:, None, None]
        ks = x[:, -2, None, None]
        alpha = np.exp(x[:, -1])[:, None, None]
        pos, Ssafe = g.pos, g.Ssafe
        Sa = np.where(pos, Ssafe ** alpha, 0.0)
        sh = np.maximum(g.c + ks * Sa, 1e-12)            # shading
        wsat = p.saturate_shading
        sat = p.saturation
        r2 = g.r_e * g.r_e
        shw = sh if wsat == 1.0 else sh ** wsat
        rest = 1.0 if wsat == 1.0 else sh ** (1.0 - wsat)
        E = self.gain * rho * shw * g.beam / (sat * r2)
        e = np.exp(-E)
        pp = sat * (1.0 - e)                            # saturated part
        amp = self.amp_weight * pp * rest * g.hit          # (B, 9, R)
        if g.echo is not None:  # the echo's rays: amplitude amp * echo(path)
            amp = np.concatenate([amp, amp * g.echo], axis=-1)
        resp = self.responses(conv) if conv.ndim == 3 else conv
        T = g.place(np.matmul(amp[:, :, None, :], g.G)[:, :, 0])  # sum over rays (a matmul: einsum is slower here)
        if self.glass is not None:  # the cover glass: the same return in every frame (no derivative in x)
            tg = np.arange(width)[None, :] - self.glass_u[:, None]
            kg = self.kernel(tg)
            T = T + (self.glass[:, None] * kg)[None]
        xt = self.p.crosstalk if self.crosstalk_column is None else x[:, self.crosstalk_column, None, None]
        P = np.matmul(resp, T[..., None])[..., 0]  # expected photon counts before the zones mix
        F = self._mix(P, crosstalk=xt)
        F_ok = None
        if self.shaped:  # ForwardModel.after_pulse: no negative counts beside a sharpened pulse
            F_ok = F >= 0.0
            F = np.maximum(F, 0.0)
        if self.bin_gains is not None:
            F = F * self.bin_gains[:width]
        kp = p.pileup
        ks_shadow = kp * p.pileup_shadow
        amb = 0.0 if ambient is None else np.asarray(ambient, dtype=float)[:, :, None]
        e_b = e_c = Ha = None
        if kp > 0:
            Fa = F + amb  # the ambient arrives with the return and piles up with it
            before = np.cumsum(Fa, axis=-1) - Fa
            e_b, e_c = np.exp(-kp * Fa), np.exp(-ks_shadow * before)
            Ha = -np.expm1(-kp * Fa) / kp * e_c
            H = Ha - amb
        else:
            H = F
        H.flags.writeable = False  # kept for the next render at these values: a caller cannot change it by mistake
        f = SimpleNamespace(g=g, ks=ks, alpha=alpha, Sa=Sa, sh=sh, rest=rest, E=E, e=e, pp=pp, amp=amp, resp=resp,
                            xt=xt, P=P, F_ok=F_ok, e_b=e_b, e_c=e_c, Ha=Ha, ks_shadow=ks_shadow, H=H)
        self._forward_cache = (key, f, conv, ambient)
        return f

    def _jacobian(self, x: np.ndarray, f: SimpleNamespace) -> np.ndarray:
        """d hist / d x (B, 9, W, n_unknowns) at the render ``f`` of ``x`` (:meth:`_forward`)."""
        p = self.p
        g = f.g
        a, b, z0, s, qs, r, c = g.a, g.b, g.z0, g.s, g.qs, g.r, g.c
        pos, Ssafe, slope, n_direct, path = g.pos, g.Ssafe, g.slope, g.n_direct, g.path
        ks, alpha, Sa, sh, rest, E, e, pp, amp = f.ks, f.alpha, f.Sa, f.sh, f.rest, f.E, f.e, f.pp, f.amp
        wsat = p.saturate_shading
        sat = p.saturation
        if g.G_u is None:  # the soft-bin kernels' derivative in u, on first need
            g.G_u = g.dense(self.kernel(g.t, derivative=True))
        G, G_u, place = g.G, g.G_u, g.place
        # per-ray partial derivatives of amp
        aw = self.amp_weight * g.hit
        dp_dlogrho = aw * sat * e * E * rest
        dp_dsh = aw * (sat * e * E * wsat / sh * rest + (0.0 if wsat == 1.0 else pp * (1.0 - wsat) * sh ** -wsat))
        dsh_dc = 1.0 + np.where(pos, ks * alpha * Sa / Ssafe * 4.0 * c, 0.0)
        # the derivatives in (a, b, z0) stacked on a leading axis of 3 (the same arithmetic, element by element, as
        # three separate arrays, in a third of the array operations)
        dr = np.empty((3,) + qs.shape)                                     # d r / d (a, b, z0)
        dr[:2] = -z0 * self.dirs_xy / (qs * qs)
        dr[2] = 1.0 / qs
        if self.light is None:
            dp_geo = aw * sat * e * (-2.0 * E / r) * rest * dr
            dc = np.zeros_like(dr)                                         # d c / d (a, b, z0)
            dc[:2] = self.dirs_xy / s - qs * np.stack([a, b]) / s ** 3
            du = dr / p.bin_size * self.scales
        else:
            bp = self.light[3]
            r_e, c_raw, w_e = g.r_e, g.c_raw, g.w_e
            inside = c_raw > 0.0  # the clamp's derivative
            dre = (r - w_e) / r_e * dr
            # d log(flux) / d x: inverse square in r_e and the beam (P_z / r_e)^bp
            dlog = -2.0 * dre / r_e + bp * (dr / r - dre / r_e)
            ds = np.stack([a / s, b / s, np.zeros_like(s)])
            dc = np.where(inside, self.light_dnum / (s * r_e) - c_raw * (ds / s + dre / r_e), 0.0)
            du = 0.5 * (dr + dre) / p.bin_size * self.scales
            dp_geo = dp_dlogrho * dlog  # d amp / d log(flux) is d amp / d log(albedo)
        logS = np.where(pos, np.log(Ssafe), 0.0)
        dsh = [None, None, None, None, Sa, ks * Sa * logS * alpha]                # d sh / d x4, x5
        nu = self.n_unknowns
        amp_direct = amp[..., :n_direct]
        A = np.zeros(amp_direct.shape + (nu,))   # d amp / d x
        B = np.zeros(amp_direct.shape + (nu,))   # amp * d u / d x
        A[..., :3] = np.moveaxis(dp_geo + dp_dsh * dsh_dc * dc, 0, -1)
        B[..., :3] = np.moveaxis(amp_direct * du * (1.0 if slope is None else slope[..., :n_direct]), 0, -1)
        if self.zone_albedo:
            zones = np.arange(N_ZONES)
            A[:, zones, :, 3 + zones] = dp_dlogrho.transpose(1, 0, 2)
        else:
            A[..., 3] = dp_dlogrho
        A[..., nu - 2] = dp_dsh * dsh[4]
        A[..., nu - 1] = dp_dsh * dsh[5]
        if g.echo is not None:  # the echo's rays: amplitude amp * echo(path), position 2 path / bin_size
            d_path = [du[k] * p.bin_size / self.scales for k in range(3)]
            amp_e = amp[..., n_direct:]  # amp_direct * echo (concatenated above)
            falloff = amp_e * (-self.echo_power / np.maximum(path, 1e-4))
            near = path > 1e-4
            A_e = A * g.echo[..., None]
            B_e = np.zeros_like(B)
            for k in range(3):
                A_e[..., k] += falloff * d_path[k] * near
                B_e[..., k] = amp_e * 2.0 * du[k] * (1.0 if slope is None else slope[..., n_direct:])
            A = np.concatenate([A, A_e], axis=2)
            B = np.concatenate([B, B_e], axis=2)
        dT = place(np.matmul(G.swapaxes(2, 3), A) + np.matmul(G_u.swapaxes(2, 3), B))  # (B, 9, W, k), sums over rays
        xt = f.xt
        dF = self._mix(np.matmul(f.resp, dT), axis_zone=1, crosstalk=xt if np.ndim(xt) == 0 else xt[..., None])
        if self.crosstalk_column is not None:  # d F / d crosstalk: every zone's share of the others
            dF[..., self.crosstalk_column] = (f.P.sum(axis=1, keepdims=True) - (1.0 - self.p.crosstalk_self) * f.P)
        if self.shaped:
            dF = dF * f.F_ok[..., None]
        if self.bin_gains is not None:
            dF = dF * self.bin_gains[:dF.shape[2], None]
        if p.pileup > 0:
            d_before = np.cumsum(dF, axis=2) - dF
            dH = (f.e_b * f.e_c)[..., None] * dF - f.ks_shadow * f.Ha[..., None] * d_before
        else:
            dH = dF
        return dH

    def kernel(self, t: np.ndarray, derivative: bool = False) -> np.ndarray:
        """The soft-bin kernel ``G`` at ``t = n - u`` (bins; :func:`~place_safe.recovery.forward.bin_kernel` with the
        model's width, integration and spline), or with ``derivative`` its derivative in ``u``."""
        if derivative:
            return bin_kernel(t, self.p.soft_bin_sigma, self.integrated, derivatives="u", spline=self.spline)[1]
        return bin_kernel(t, self.p.soft_bin_sigma, self.integrated, spline=self.spline)

    def soft_bin_window(self, u: np.ndarray, width: int):
        """The soft binning of rays at positions ``u`` (B, 9, R; bins) over the bins ``n = 0..width-1``, in a band of
        each zone's bins: returns ``(t, dense, place)`` with ``t = n - u`` at each ray's window bins (B, 9, R, 2 reach),
        ``dense`` the function that puts values there (:meth:`kernel` of ``t``) into each zone's band, (B, 9, R, L) at
        bins ``start + l`` (``start`` per frame and zone), and ``place`` the one that puts (B, 9, L, ...) arrays of the
        band at their bins of (B, 9, width, ...) (0 elsewhere, and bins outside the histogram dropped).

        Each ray's kernel is evaluated only at the ``2 reach`` bins nearest its position (a window that covers every
        bin within ``reach`` of ``u``, moved inside ``[-reach, width + reach)`` for rays beyond the histogram) and is
        0 elsewhere: beyond :data:`SOFT_BIN_REACH` widths the Gaussian is below ``exp(-40)`` of its peak, so the
        histograms are those of the kernel evaluated at every bin to rounding. A zone's rays lie within a few bins,
        so its band is some 20 bins where the histogram has 60-130.
        """
        reach = self.reach
        span = 2 * reach
        # first bin of each window, kept within [-reach, width - reach] (maximum / minimum in place: np.clip's
        # checks cost more than the arithmetic on these small arrays)
        lo = np.floor(u).astype(np.intp)
        lo -= reach - 1
        np.maximum(lo, -reach, out=lo)
        np.minimum(lo, width - reach, out=lo)
        t = (lo[..., None] + self._span) - u[..., None]  # n - u at the window's bins, (B, 9, R, span)
        start = lo.min(axis=-1)  # (B, 9): each zone's first band bin
        local = lo - start[..., None]
        band = int(local.max()) + span
        flat = local[..., None] + self._span
        flat += np.arange(0, u.size * band, band).reshape(u.shape + (1,))
        flat = flat.ravel()

        def dense(values):
            out = np.zeros(u.shape + (band,))
            out.reshape(-1)[flat] = values.reshape(-1)
            return out

        padded = width + reach + band  # band bins start + l at start + reach + l of rows this long
        at = (start + np.arange(reach, start.size * padded + reach, padded).reshape(start.shape))[..., None] \
            + np.arange(band)
        at = at.ravel()

        def place(x: np.ndarray) -> np.ndarray:
            out = np.zeros(start.shape + (padded,) + x.shape[3:])
            out.reshape((-1,) + x.shape[3:])[at] = x.reshape((-1,) + x.shape[3:])
            return out[:, :, reach:reach + width]

        return t, dense, place

    def responses(self, conv: np.ndarray) -> np.ndarray:
        """Each zone's whole causal response to a transient, (B, 9, W, W) (or (B, 1, W, W) when the zones share it),
        from the frames' pulse convolution matrices ``conv`` (B, W, W): the pulse, then the zone's pulse shape,
        learned response and own tail. All are causal convolutions, so their product is one per zone, built from its
        first column (one matrix product per render instead of two; the same histograms to rounding)."""
        if self.tail_mats is None:
            return conv[:, None]
        b, width = conv.shape[0], conv.shape[-1]
        first = np.matmul(self.tail_mats[:, :width, :width], conv[:, None, :, :1])[..., 0]  # (B, 9, W)
        return convolution_matrices(first.reshape(b * N_ZONES, width), width).reshape(b, N_ZONES, width, width)

    def _mix(self, h: np.ndarray, axis_zone: int = 1, crosstalk=None) -> np.ndarray:
        c = self.p.crosstalk if crosstalk is None else crosstalk
        out = (1.0 - c * (1.0 - self.p.crosstalk_self)) * h + c * h.sum(axis=axis_zone, keepdims=True)
        if self.grid_mix is not None:  # zones on axis 1 of (B, 9, W) or (B, 9, W, k)
            out = out + np.tensordot(self.grid_mix, h, axes=([1], [1])).swapaxes(0, 1)
        return out


__all__ = ["PlaneRenderer", "convolution_matrices", "N_UNKNOWNS", "N_ZONES"]
