"""The differentiable forward imaging model of the TMF8820 (Sifferman et al., RA-L 2023), in torch.

For each zone, rays leave the sensor through the zone's rectangle on ``z = 1``. A ray that meets a
surface at range ``r`` (m) with cosine of incidence ``c`` returns, with a co-located light
(Phong shading),

    I = albedo * (c + w_s * max(2 c^2 - 1, 0) ** alpha)        (``2c^2 - 1 = cos 2theta = R . V``)

photons that a SPAD pixel of zone gain ``g`` counts, soft-saturating with the inverse square law,

    p = s * (1 - exp(-g * I / (s * r^2)))

at the bin position ``u = r / bin_size + bin_offset + zone_offset`` (bins of one-way range). Each
ray is soft-binned with a Gaussian of ``soft_bin_sigma`` bins; a zone's transient is the
solid-angle weighted mean over its rays times ``rays_per_zone`` (so quadratures of any size share
one scale). The transient is convolved with the laser pulse (the reference histogram, floor
removed, normalised to peak 1, stretched in time by ``ref_time_scale``), zones leak
``crosstalk`` of every other zone's histogram, and a constant ``floor`` is added. The unit's own terms (crosstalk by
neighbour in the 3x3 grid, the cover-glass return, the multipath echo, the learned response, per-zone timing, gain and
tails, pile-up) are described in :class:`ForwardParams`; their priors are in
:data:`place_safe.calibration.forward_fit.PRIORS`.

Shapes: ``B`` frames, 9 zones, ``R`` rays per zone, 128 bins. Everything is batched over frames
and differentiable in the plane, reflectance and every camera parameter.
"""

from __future__ import annotations

import math
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Collection

import numpy as np
import torch

from place_safe.sensor.frame import N_BINS, N_ZONES, ZONE_KIND, ZONE_RECTS
# the parameters live without torch (a calibration is read, and peak runs, without the renderer)
from place_safe.recovery.tangent_einsum import einsum2, many_tangents_active
from place_safe.recovery.forward_params import (ECHO_REFERENCE_RANGE, WARP_KNOTS, WARP_SPACING, ForwardParams,
                                                _GRID_SELECTORS)

_SQRT_2PI = math.sqrt(2.0 * math.pi)


def grid_crosstalk_matrix(grid, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The neighbour crosstalk (``ForwardParams.crosstalk_grid``, 8 weights by displacement) as a (9, 9) matrix
    ``M[to, from]``: zone ``to`` receives ``grid[k]`` of the histogram of the zone displaced by
    ``GRID_DISPLACEMENTS[k]`` from it (zones without such a neighbour, at the grid's edge, receive nothing)."""
    g = torch.as_tensor(grid, dtype=dtype)
    return torch.einsum("k,ktf->tf", g, torch.as_tensor(_GRID_SELECTORS, dtype=dtype))


#: Parameters that are tensors inside the model (everything but the ray count).
TENSOR_PARAMS = tuple(name for name in ForwardParams.model_fields if name != "rays_per_zone")


def mount_rotation(tilt) -> torch.Tensor:
    """Rotation matrix (3, 3) from the optical frame to the reported sensor frame (Rodrigues).

    ``tilt`` is ``(rx, ry)`` in radians, the x and y components of a rotation vector (a tensor, so
    calibration can differentiate through it).
    """
    t = tilt if torch.is_tensor(tilt) else torch.as_tensor(np.asarray(tilt, dtype=float))
    zero = torch.zeros((), dtype=t.dtype)
    k = torch.stack([torch.stack([zero, zero, t[1]]), torch.stack([zero, zero, -t[0]]),
                     torch.stack([-t[1], t[0], zero])])
    angle2 = t[0] * t[0] + t[1] * t[1]
    angle = torch.sqrt(angle2 + 1e-30)
    a = torch.where(angle2 > 1e-16, torch.sin(angle) / angle, 1.0 - angle2 / 6.0)
    b = torch.where(angle2 > 1e-16, (1.0 - torch.cos(angle)) / (angle2 + 1e-30), 0.5 - angle2 / 24.0)
    return torch.eye(3, dtype=t.dtype) + a * k + b * (k @ k)


def params_to_tensors(p: ForwardParams, dtype: torch.dtype = torch.float64) -> dict[str, torch.Tensor]:
    """The parameters as a dict of tensors (scalars, or (9,) for the per-zone ones)."""
    return {k: torch.as_tensor(np.asarray(getattr(p, k), dtype=float), dtype=dtype) for k in TENSOR_PARAMS}


def tensors_to_params(t: dict[str, torch.Tensor], rays_per_zone: int) -> ForwardParams:
    vals = {}
    for k, v in t.items():
        a = v.detach().cpu().numpy()
        vals[k] = [float(x) for x in a] if a.ndim else float(a)
    return ForwardParams(rays_per_zone=rays_per_zone, **vals)


# ---------------------------------------------------------------------------------------------
# Rays
# ---------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ZoneRays:
    """Ray directions (9, R, 3) (unit) and quadrature weights (9, R) summing to 1 per zone."""

    directions: torch.Tensor
    weights: torch.Tensor

    @property
    def count(self) -> int:
        return int(self.directions.shape[1])

    @classmethod
    def stratified(cls, n: int = 8, dtype: torch.dtype = torch.float64) -> "ZoneRays":
        """Deterministic n x n midpoint grid on each zone rectangle, weighted by solid angle.

        The weight of a grid cell is ``dx dy / (1 + x^2 + y^2)^(3/2)``, the solid angle it subtends,
        so the weighted mean equals the mean over rays uniform in solid angle.
        """
        if n < 1:
            raise ValueError("stratified rays need n >= 1")
        t = (np.arange(n) + 0.5) / n
        dirs, wts = [], []
        for x0, x1, y0, y1 in ZONE_RECTS:
            gx, gy = np.meshgrid(x0 + (x1 - x0) * t, y0 + (y1 - y0) * t, indexing="ij")
            v = np.stack([gx.ravel(), gy.ravel(), np.ones(n * n)], axis=1)
            norm2 = (v * v).sum(axis=1)
            w = norm2 ** -1.5
            dirs.append(v / np.sqrt(norm2)[:, None])
            wts.append(w / w.sum())
        return cls(torch.as_tensor(np.array(dirs), dtype=dtype), torch.as_tensor(np.array(wts), dtype=dtype))

    @classmethod
    def random(cls, n: int = 2304, generator: np.random.Generator | None = None,
               dtype: torch.dtype = torch.float64) -> "ZoneRays":
        """``n`` rays per zone drawn uniformly in solid angle (rejection sampling), equal weights.

        This is the paper's sampling; it is what the ``paper`` mode of differentiable rendering uses.
        """
        rng = generator if generator is not None else np.random.default_rng()
        dirs = []
        for x0, x1, y0, y1 in ZONE_RECTS:
            # density on z=1 of uniform solid angle is proportional to (1+x^2+y^2)^-1.5
            cmax = (1 + min(x0 ** 2, x1 ** 2) * (x0 * x1 > 0) + min(y0 ** 2, y1 ** 2) * (y0 * y1 > 0)) ** -1.5
            got: list[np.ndarray] = []
            count = 0
            while count < n:
                m = 2 * (n - count) + 16
                x = rng.uniform(x0, x1, m)
                y = rng.uniform(y0, y1, m)
                keep = rng.uniform(0, cmax, m) < (1 + x * x + y * y) ** -1.5
                v = np.stack([x[keep], y[keep], np.ones(keep.sum())], axis=1)
                got.append(v)
                count += len(v)
            v = np.concatenate(got)[:n]
            dirs.append(v / np.linalg.norm(v, axis=1, keepdims=True))
        d = torch.as_tensor(np.array(dirs), dtype=dtype)
        return cls(d, torch.full(d.shape[:2], 1.0 / n, dtype=dtype))


# ---------------------------------------------------------------------------------------------
# Model
# ---------------------------------------------------------------------------------------------
def pulse_kernel(reference: torch.Tensor, time_scale: torch.Tensor, ref_floor: torch.Tensor,
                 tail_weight: torch.Tensor | None = None, tail_decay: torch.Tensor | None = None,
                 soft_bin: torch.Tensor | None = None, sigma: torch.Tensor | None = None) -> torch.Tensor:
    """Laser pulse in zone bins from reference histograms (..., 128) -> (..., K).

    The floor is removed, the tail after the peak smoothed (:data:`TAIL_SMOOTHING`), the pulse
    normalised to peak 1 and sampled at zone-bin lags
    ``k = 0..K-1``, i.e. at reference bins ``k / time_scale`` (linear interpolation). With a
    ``tail_weight`` the pulse is then convolved with ``delta + w exp(-k / tail_decay)``, k >= 1.
    With ``soft_bin`` > 0 that fraction of the pulse is instead the paper's rescaling: every reference
    bin ``i`` soft-binned at zone lag ``i * time_scale`` with a Gaussian of ``sigma`` (zone bins),
    normalised to peak 1. Every step but the two normalisations and the tail's start is linear in the reference:
    :class:`PulseMatrices` is the same map as matrices (numpy, for the solver's per-frame pulse).
    """
    ref = torch.clamp(reference - ref_floor, min=0.0)
    ref = _smooth_tail(ref)
    peak = ref.amax(dim=-1, keepdim=True)
    ref = ref / torch.clamp(peak, min=1e-12)
    k_len = pulse_length(time_scale)
    kernel = _resample(ref, time_scale, k_len)
    if soft_bin is not None and (torch.is_grad_enabled() or float(soft_bin) > 0.0):
        soft = _soft_resample(ref, time_scale, sigma, k_len)
        soft = soft / torch.clamp(soft.amax(dim=-1, keepdim=True), min=1e-12)
        kernel = (1.0 - soft_bin) * kernel + soft_bin * soft
    if tail_weight is None or (not torch.is_grad_enabled() and float(tail_weight) == 0.0):
        return kernel
    return _tail_convolve(kernel, tail_weight, tail_decay)


def pulse_length(time_scale) -> int:
    """The pulse kernel's length K (zone bins) for the reference's ``time_scale``: lags up to the last reference bin."""
    return int(math.floor((N_BINS - 1) * float(torch.as_tensor(time_scale).detach()))) + 1


def _resample(ref: torch.Tensor, time_scale: torch.Tensor, k_len: int) -> torch.Tensor:
    """The reference (..., 128) at zone-bin lags ``0..k_len-1``, reference bins ``k / time_scale`` (linear
    interpolation): (..., k_len). Linear in ``ref``."""
    lags = torch.arange(k_len, dtype=ref.dtype)
    pos = lags / time_scale  # reference-bin coordinate of each lag
    lo = torch.clamp(torch.floor(pos), 0, N_BINS - 2)
    frac = pos - lo
    lo_i = lo.long()
    a = ref[..., lo_i]
    b = ref[..., lo_i + 1]
    return a * (1 - frac) + b * frac


def _soft_resample(ref: torch.Tensor, time_scale: torch.Tensor, sigma: torch.Tensor, k_len: int) -> torch.Tensor:
    """The paper's rescaling of the reference (..., 128): each reference bin ``i`` soft-binned at zone lag
    ``i * time_scale`` with a Gaussian of ``sigma`` (zone bins), not normalised: (..., k_len). Linear in ``ref``."""
    lags = torch.arange(k_len, dtype=ref.dtype)
    centres = torch.arange(N_BINS, dtype=ref.dtype) * time_scale
    zz = (lags.view(-1, 1) - centres.view(1, -1)) / sigma
    return ref @ torch.exp(-0.5 * zz * zz).T  # (..., K)


def _tail_convolve(kernel: torch.Tensor, tail_weight: torch.Tensor, tail_decay: torch.Tensor) -> torch.Tensor:
    """``kernel`` (..., K) convolved with ``delta + w exp(-k / tail_decay)``, k >= 1, truncated to K (causal).
    Linear in ``kernel``."""
    k_len = kernel.shape[-1]
    k = torch.arange(1, k_len, dtype=kernel.dtype)
    tail = tail_weight * torch.exp(-k / tail_decay)
    # causal convolution truncated to the kernel's length: kernel[j] += sum_k tail[k-1] kernel[j-k]
    idx = torch.arange(k_len).view(-1, 1) - k.long().view(1, -1)  # (K, K-1)
    gathered = kernel[..., torch.clamp(idx, min=0)] * (idx >= 0)
    return kernel + (gathered * tail).sum(-1)


#: Rows of the identity :class:`PulseMatrices` passes through the tail's convolution at once (bounds its memory).
PULSE_ROWS_AT_ONCE = 32


class PulseMatrices:
    """:func:`pulse_kernel` of fixed parameters as matrices (numpy, float64): the solver prepares each frame's pulse
    with a few array operations instead of some forty torch ones (a tenth of the time at one frame), the same kernels
    to rounding. Each linear step is :func:`pulse_kernel`'s own code applied to the identity: the tail smoothing
    for each start bin (built when a reference first peaks there), the resampling, the paper's rescaling, the tail.

    ``params``: the model's tensors (:attr:`ForwardModel.t`): ``ref_time_scale``, ``ref_floor``, ``tail_weight``,
    ``tail_decay``, ``pulse_soft_bin``, ``soft_bin_sigma``."""

    def __init__(self, params: dict) -> None:
        with torch.no_grad():
            self.floor = float(params["ref_floor"])
            time_scale = params["ref_time_scale"].detach().to(torch.float64)
            self.k_len = pulse_length(time_scale)
            eye = torch.eye(N_BINS, dtype=torch.float64)
            self.resample = _resample(eye, time_scale, self.k_len).numpy()  # (128, K): row i is bin i's weights
            self.soft_bin = float(params["pulse_soft_bin"])
            self.soft = (_soft_resample(eye, time_scale, params["soft_bin_sigma"].detach().to(torch.float64),
                                        self.k_len).numpy() if self.soft_bin > 0.0 else None)
            w = params["tail_weight"].detach().to(torch.float64)
            decay = params["tail_decay"].detach().to(torch.float64)
            eye = torch.eye(self.k_len, dtype=torch.float64)
            # the identity's rows a few at a time: the tail's gather is (rows, K, K - 1), 2 GB for all 509 rows at once
            self.tail = (torch.cat([_tail_convolve(eye[i:i + PULSE_ROWS_AT_ONCE], w, decay)
                                    for i in range(0, self.k_len, PULSE_ROWS_AT_ONCE)]).numpy()
                         if float(w) != 0.0 else None)
        self._smooth: dict[int, np.ndarray] = {}

    def smoothing(self, start: int) -> np.ndarray:
        """(128, 128): a reference times it is the reference with its tail smoothed from bin ``start`` on
        (:func:`_smooth_tail`)."""
        m = self._smooth.get(start)
        if m is None:
            with torch.no_grad():
                eye = torch.eye(N_BINS, dtype=torch.float64)
                m = self._smooth[start] = _smooth_tail(eye, torch.full((N_BINS, 1), start)).numpy()
        return m

    def __call__(self, reference: np.ndarray) -> np.ndarray:
        """The pulse kernels (B, K) of reference histograms (B, 128)."""
        ref = np.maximum(np.asarray(reference, dtype=float) - self.floor, 0.0)
        start = np.minimum(ref.argmax(axis=-1) + TAIL_AFTER_PEAK, N_BINS - 1)  # as _smooth_tail finds it
        out = np.empty((len(ref), self.k_len))
        for i, s in enumerate(start):
            r = ref[i] @ self.smoothing(int(s))
            r = r / max(r.max(), 1e-12)
            k = r @ self.resample
            if self.soft is not None:
                soft = r @ self.soft
                k = (1.0 - self.soft_bin) * k + self.soft_bin * (soft / max(soft.max(), 1e-12))
            out[i] = k if self.tail is None else k @ self.tail
        return out


#: Width (reference bins) of the Gaussian that smooths the reference pulse after its peak. The
#: tail holds a few hundred counts per bin, so its Poisson noise (a few per cent) would reach every
#: model histogram multiplied by the whole transient (~1e6 counts); the physical tail is smooth.
TAIL_SMOOTHING = 2.0
#: Bins after the reference's peak from which its tail is smoothed (:func:`_smooth_tail`, :class:`PulseMatrices`).
TAIL_AFTER_PEAK = 3


def _smooth_tail(ref: torch.Tensor, start: torch.Tensor | None = None) -> torch.Tensor:
    """The reference (..., 128) with its tail (from :data:`TAIL_AFTER_PEAK` bins after the peak on) Gaussian-smoothed.
    ``start`` (..., 1): the tail's first bin instead (for :class:`PulseMatrices`: for a fixed start the map is
    linear)."""
    half = int(math.ceil(3 * TAIL_SMOOTHING))
    taps = torch.exp(-0.5 * (torch.arange(-half, half + 1, dtype=ref.dtype) / TAIL_SMOOTHING) ** 2)
    taps = taps / taps.sum()
    bins = torch.arange(ref.shape[-1])
    if start is None:
        start = torch.clamp(ref.argmax(dim=-1, keepdim=True) + TAIL_AFTER_PEAK, max=ref.shape[-1] - 1)
    in_tail = bins >= start
    # the tail alone: bins before it hold the tail's first value, so the peak does not leak in
    tail = torch.where(in_tail, ref, torch.gather(ref, -1, start).expand_as(ref))
    flat = tail.reshape(-1, 1, ref.shape[-1])
    padded = torch.nn.functional.pad(flat, (half, half), mode="replicate")
    smooth = torch.nn.functional.conv1d(padded, taps.view(1, 1, -1)).reshape(ref.shape)
    return torch.where(in_tail, smooth, ref)


def apply_pileup(hist: torch.Tensor, k: torch.Tensor, shadow: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Coates pile-up of expected counts (..., N) with ``k`` = 1 / (laser cycles x detectors).

    ``shadow`` (blend in [0, 1], :class:`ForwardParams` ``pileup_shadow``) weights the earlier bins' shadowing:
    ``(1 - exp(-k h_b)) / k exp(-k shadow sum_{j<b} h_j)``; 1 (the default) is Coates' formula.
    ``k = 0`` returns ``hist`` unchanged (the limit of the formula). Within
    :func:`~place_safe.recovery.tangent_einsum.many_tangents` (a calibration's Jacobian, dozens of tangents at once) its
    derivatives are written out (:class:`_Pileup`, first order only); elsewhere it is the formula in torch.
    """
    if not torch.is_grad_enabled() and float(k) == 0.0:
        return hist
    if not many_tangents_active():
        return _Pileup.forward(hist, k, shadow)
    dtype = torch.result_type(hist, k)
    dtype = dtype if dtype.is_floating_point else torch.get_default_dtype()
    return _Pileup.apply(hist.to(dtype), torch.as_tensor(k, dtype=dtype), torch.as_tensor(shadow, dtype=dtype))


class _Pileup(torch.autograd.Function):
    """:func:`apply_pileup` with its derivatives written out: ``y = P E`` with ``P = (1 - exp(-k h)) / k`` and
    ``E = exp(-k s c)``, ``c`` the counts in the earlier bins (``k`` clamped at 1e-30, whose derivative is then 0):

    ``dy = exp(-k h) E dh - k s y dc + ((h exp(-k h) - P) / k E - s c y) dk - k c y ds``, ``dc`` the earlier bins'
    ``dh`` summed. Autograd through the formula takes each tangent through a dozen operations; this is four on the
    tangents, the factors made once (``vmap`` over ``jvp`` in the forward fit's Jacobian)."""

    generate_vmap_rule = True

    @staticmethod
    def forward(hist, k, shadow):
        before = torch.cumsum(hist, dim=-1) - hist  # counts in earlier bins
        kk = torch.clamp(k, min=1e-30)
        return -torch.expm1(-kk * hist) / kk * torch.exp(-kk * shadow * before)

    @staticmethod
    def setup_context(ctx, inputs, output):
        hist, k, shadow = inputs
        ctx.set_materialize_grads(False)  # an input without a tangent gets None, not a tensor of zeros
        ctx.save_for_backward(hist, k, shadow, output)
        ctx.save_for_forward(hist, k, shadow, output)

    @staticmethod
    def _factors(hist, k, shadow, y):
        """d y / d h (the bin's own), d y / d c, d y / d k and d y / d s (each broadcast to ``hist``)."""
        before = torch.cumsum(hist, dim=-1) - hist
        kk = torch.clamp(k, min=1e-30)
        e = torch.exp(-kk * hist)
        big_e = torch.exp(-kk * shadow * before)
        own = e * big_e
        d_c = -(kk * shadow) * y
        live = (k >= 1e-30).to(hist.dtype)  # the clamp's derivative
        d_k = live * ((hist * e + torch.expm1(-kk * hist) / kk) / kk * big_e - shadow * before * y)
        d_s = -kk * before * y
        return own, d_c, d_k, d_s

    @staticmethod
    def jvp(ctx, d_hist, d_k, d_shadow):
        hist, k, shadow, y = ctx.saved_tensors
        own, d_c, d_y_k, d_y_s = _Pileup._factors(hist, k, shadow, y)
        terms = []
        if d_hist is not None:
            terms.append(own * d_hist + d_c * (torch.cumsum(d_hist, dim=-1) - d_hist))
        if d_k is not None:
            terms.append(d_y_k * d_k)
        if d_shadow is not None:
            terms.append(d_y_s * d_shadow)
        return sum(terms[1:], terms[0]) if terms else torch.zeros_like(y)

    @staticmethod
    def backward(ctx, grad):
        if grad is None:
            return None, None, None
        hist, k, shadow, y = ctx.saved_tensors
        own, d_c, d_y_k, d_y_s = _Pileup._factors(hist, k, shadow, y)
        g_c = grad * d_c  # each bin's gradient on the earlier bins' counts: a reversed, exclusive cumulative sum
        g_hist = grad * own + (torch.flip(torch.cumsum(torch.flip(g_c, (-1,)), dim=-1), (-1,)) - g_c)

        def reduce(g: torch.Tensor, like: torch.Tensor) -> torch.Tensor:
            return g.sum_to_size(like.shape) if like.dim() else g.sum()

        return g_hist, reduce(grad * d_y_k, k), reduce(grad * d_y_s, shadow)


def ambient_pileup(hist: torch.Tensor, ambient: torch.Tensor, k: torch.Tensor | float,
                   shadow: torch.Tensor | float = 1.0) -> torch.Tensor:
    """Expected counts (B, 9, N) of a return ``hist`` above the ambient ``ambient`` (B, 9, counts per bin as it
    arrives), both through the pile-up (:func:`apply_pileup`): ``pileup(hist + ambient) - ambient``.

    A SPAD that has fired on the return is blind to the ambient photons after it, so after a bright return the
    ambient reads lower than before it (the real sweep at 10 cm: bins 100-127 hold 48-78 % of bins 0-7's ambient,
    least in the brightest zones). Zero ambient is :func:`apply_pileup`."""
    a = torch.as_tensor(ambient, dtype=hist.dtype).unsqueeze(-1)
    return apply_pileup(hist + a, k, shadow) - a


def pulse_shape_matrix(widths, skews, n: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Each zone's pulse-shape correction (:class:`ForwardParams` ``zone_pulse_widths`` ``w``, ``zone_pulse_skews``
    ``s``) as causal (9, n, n) matrices: convolution with ``delta + w B2 + (w - s) B3``, where ``B2 = (1, -2, 1)`` and
    ``B3 = (1, -3, 3, -1)`` at lags 0.. are the backward second and third differences. The correction keeps the
    pulse's area and mean time and adds ``2 w`` bins^2 to its variance and ``6 s`` bins^3 to its third central
    moment (``B2``'s moments about lag 0 are 0, 0, 2, 6 and ``B3``'s 0, 0, 0, -6). Causal, so a histogram's first
    ``W`` bins depend on its first ``W`` only."""
    w = torch.as_tensor(widths, dtype=dtype).view(-1, 1)
    s = torch.as_tensor(skews, dtype=dtype).view(-1, 1)
    b2 = torch.tensor([1.0, -2.0, 1.0, 0.0], dtype=dtype)
    b3 = torch.tensor([1.0, -3.0, 3.0, -1.0], dtype=dtype)
    delta = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=dtype)
    return causal_matrix(delta + w * b2 + (w - s) * b3, n)


#: Length (bins) of each zone's own tail (:class:`ForwardParams` ``zone_tail_*``). At the longest decay
#: allowed (8 bins; calibration finds 2-5) the tail has fallen to 0.25 % of its start by then.
ZONE_TAIL_BINS = 48


def zone_tail_taps(weights, decays, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Each zone's tail (9, :data:`ZONE_TAIL_BINS`): ``w_z exp(-k / tau_z)`` at lags ``k = 1..``."""
    k = torch.arange(1, ZONE_TAIL_BINS + 1, dtype=dtype)
    w = torch.as_tensor(weights, dtype=dtype).view(-1, 1)
    tau = torch.as_tensor(decays, dtype=dtype).view(-1, 1)
    return w * torch.exp(-k / tau)


def warp_positions(u: torch.Tensor, warp) -> tuple[torch.Tensor, torch.Tensor]:
    """Bin positions ``u`` (any shape) moved by the TDC's integral non-linearity, and the slope ``d u' / d u``.

    ``warp`` (:data:`WARP_KNOTS`,) are the shifts (bins) at bins ``0, 8, ..., 128`` less their least-squares straight
    line over the knots (an integral non-linearity is the departure from the best straight line: a constant is
    ``bin_offset``, a slope ``bin_size``), interpolated linearly between the knots and held at the end values
    outside. Zeros (the default) move nothing; so does any straight line. The gauge is over all knots: a fit whose
    returns reach only some of them can still tilt those against ``bin_size`` (the real sweep did, 0.01408 -> 0.01353
    m), so fit the warp with ``bin_offset`` and ``bin_size`` held (docs/results.md, the unit model, step 4)."""
    w = torch.as_tensor(warp, dtype=u.dtype)
    k = torch.arange(WARP_KNOTS, dtype=u.dtype) - 0.5 * (WARP_KNOTS - 1)
    w = w - w.mean() - k * (k * w).sum() / (k * k).sum()
    x = torch.clamp(u, 0.0, float(N_BINS)) / WARP_SPACING
    i = torch.clamp(torch.floor(x).long(), max=WARP_KNOTS - 2)
    f = x - i
    shift = w[i] * (1.0 - f) + w[i + 1] * f
    inside = (u > 0.0) & (u < float(N_BINS))
    slope = torch.where(inside, (w[i + 1] - w[i]) / WARP_SPACING, torch.zeros_like(u))
    return u + shift, 1.0 + slope


#: Half-width (bins) of the running mean that :func:`bin_widths` divides out of ``ForwardParams.bin_gains``.
BIN_GAIN_SMOOTHING = 4


def bin_widths(gains) -> torch.Tensor:
    """The bins' relative widths (N,) from ``ForwardParams.bin_gains`` (N,): each gain divided by the mean of the
    gains within :data:`BIN_GAIN_SMOOTHING` bins of it (fewer at the ends), so only their bin-to-bin pattern acts.

    A level sweep cannot tell a slow trend of the bins' widths from the fall of the brightness with range and the
    return's tail (each frame's albedo is free, and a return sits in neighbouring bins at neighbouring ranges), so
    the smooth part is not part of the model: a fit that tried it traded a +-50 % trend over 50 bins against the
    tails. Gains all 1 (the default) give widths all exactly 1."""
    g = torch.as_tensor(gains)
    k = 2 * BIN_GAIN_SMOOTHING + 1
    box = torch.ones(1, 1, k, dtype=g.dtype)
    pad = BIN_GAIN_SMOOTHING
    total = torch.nn.functional.conv1d(g.view(1, 1, -1), box, padding=pad).view(-1)
    count = torch.nn.functional.conv1d(torch.ones_like(g).view(1, 1, -1), box, padding=pad).view(-1)
    return g * count / total


def causal_matrix(kernel: torch.Tensor, n: int) -> torch.Tensor:
    """Causal convolution with ``kernel`` (..., K) as matrices (..., n, n): ``M[j, i] = kernel[j - i]`` for
    ``0 <= j - i < K``, else 0. A matrix product batches well under ``torch.func`` (the sliding windows it
    replaces were copied once per tangent: the calibration's Jacobian took 3x longer)."""
    k_len = kernel.shape[-1]
    if k_len < n:
        kernel = torch.nn.functional.pad(kernel, (0, n - k_len))
    idx = torch.arange(n)
    lag = idx.view(-1, 1) - idx.view(1, -1)
    return kernel[..., torch.clamp(lag, 0, n - 1)] * ((lag >= 0) & (lag < k_len))


def add_zone_tails(hist: torch.Tensor, taps: torch.Tensor) -> torch.Tensor:
    """Histograms (B, 9, N) plus each zone's tail: ``h_z[j] + sum_k taps[z, k-1] h_z[j - k]`` (causal)."""
    kernel = torch.cat([torch.ones_like(taps[:, :1]), taps], dim=-1)  # (9, 1 + L): the histogram, then its tail
    # each zone's own matrix, never expanded per frame (nor per tangent: einsum2)
    return einsum2("bzk,znk->bzn", hist, causal_matrix(kernel, hist.shape[-1]))


def response_matrix(kernel, n: int, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The learned impulse response (``ForwardParams.response_kernel``, weights at lags 1..) as an (n, n) causal
    matrix: the identity plus the weights below the diagonal."""
    w = torch.as_tensor(kernel, dtype=dtype)
    return causal_matrix(torch.cat([torch.ones(1, dtype=dtype), w]), n)


def add_response(hist: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Histograms (B, 9, N) convolved with the learned impulse response ``delta + sum_k kernel[k-1] delta(k)``."""
    return hist @ response_matrix(kernel, hist.shape[-1], hist.dtype).T  # (one matrix: vmap folds tangents into rows)


def convolve_pulse(transient: torch.Tensor, kernel: torch.Tensor) -> torch.Tensor:
    """Causal convolution of transients (B, Z, N) with per-frame kernels (B, K) -> (B, Z, N)."""
    return einsum2("bzk,bnk->bzn", transient, causal_matrix(kernel, transient.shape[-1]))


def bin_kernel(t, sigma, integrated: float, derivatives: bool | str = False, spline: float = 0.0):
    """The soft binning's kernel at ``t = n - u`` (bins; numpy or torch arrays): ``(1 - integrated)`` times the
    unit-area Gaussian of ``sigma`` bins sampled at ``t`` plus ``integrated`` times that Gaussian integrated over the
    bin, ``Phi((t + 1/2) / sigma) - Phi((t - 1/2) / sigma)`` (:class:`ForwardParams` ``soft_bin_integrated``); with
    ``spline`` 1 the quadratic B-spline convolved with the Gaussian instead (:func:`spline_bin_kernel`, whose ``t``
    steps by one bin along its last axis, as every caller's does: ``n`` consecutive bins).

    With ``derivatives`` returns ``(K, dK/du, dK/dsigma)``; for the integrated part ``dK/du = G(t - 1/2) - G(t + 1/2)``
    and ``dK/dsigma = -((t + 1/2) G(t + 1/2) - (t - 1/2) G(t - 1/2)) / sigma`` (``G`` the Gaussian). With
    ``derivatives="u"`` returns ``(K, dK/du)`` only.
    """
    if spline:
        return spline_bin_kernel(t, sigma, derivatives)
    if isinstance(t, torch.Tensor):
        exp, erf = torch.exp, torch.special.erf
    else:
        from scipy.special import erf
        exp = np.exp

    def gauss(x):
        z = x / sigma
        return exp(-0.5 * z * z) / (sigma * _SQRT_2PI), z

    g, z = gauss(t)
    w = float(integrated)
    if w == 0.0:  # the sampled Gaussian alone
        if not derivatives:
            return g
        return (g, g * z / sigma) if derivatives == "u" else (g, g * z / sigma, g * (z * z - 1.0) / sigma)
    inv = 1.0 / sigma
    k = (1.0 - w) * g + w * 0.5 * (erf((t + 0.5) * (inv / math.sqrt(2.0))) - erf((t - 0.5) * (inv / math.sqrt(2.0))))
    if not derivatives:
        return k
    g_p, g_m = gauss(t + 0.5)[0], gauss(t - 0.5)[0]
    k_u = (1.0 - w) * g * t * inv * inv + w * (g_m - g_p)
    if derivatives == "u":
        return k, k_u
    k_s = (1.0 - w) * g * ((t * inv) ** 2 - 1.0) * inv - w * ((t + 0.5) * g_p - (t - 0.5) * g_m) * inv
    return k, k_u, k_s


#: Gaussian widths beyond the quadratic B-spline's support at which :func:`spline_bin_kernel` is set to 0 (its value
#: there is below 1e-15 of its peak; the terms it is made of cancel only to rounding, ~1e-16 of bin^2 in float64)
SPLINE_SUPPORT_SIGMAS = 8.0


def spline_bin_kernel(t, sigma, derivatives: bool | str = False):
    """The quadratic B-spline (the unit box convolved with itself twice, support [-3/2, 3/2] bins) convolved with the
    unit-area Gaussian of ``sigma`` bins, at ``t = n - u`` (numpy or torch arrays whose last axis steps by one bin):
    the soft binning of :class:`ForwardParams` ``soft_bin_spline``. Its sum over consecutive bins is 1, its centroid
    ``u`` and its variance ``1/4 + sigma^2`` for every sub-bin position ``u`` (a B-spline of degree 2 reproduces
    polynomials up to degree 2).

    Written as the third difference of the Gaussian's third integral ``G3(x) = (x^2 + sigma^2) / 2 Phi(x / sigma) +
    sigma x / 2 phi(x / sigma)`` over the half-integer points ``t + 3/2, t + 1/2, t - 1/2, t - 3/2``: one evaluation
    per half-integer point, shared by neighbouring bins. ``dK/du = -(third difference of G2)``, ``G2(x) = x
    Phi(x / sigma) + sigma phi(x / sigma)``, and ``dK/dsigma = sigma (third difference of Phi(x / sigma))`` (the
    Gaussian's width obeys the heat equation). With ``derivatives`` returns ``(K, dK/du, dK/dsigma)``, with
    ``derivatives="u"`` ``(K, dK/du)``.
    """
    if isinstance(t, torch.Tensor):
        exp, erf, xp = torch.exp, torch.special.erf, torch
        steps = torch.arange(t.shape[-1] + 3, dtype=t.dtype)
        points = t[..., :1] - 1.5 + steps  # the half-integer points t_0 - 3/2 ... t_last + 3/2

        def third_difference(f):
            return f[..., 3:] - 3.0 * f[..., 2:-1] + 3.0 * f[..., 1:-2] - f[..., :-3]
    else:
        from scipy.special import erf
        exp, xp = np.exp, np
        points = np.asarray(t)[..., :1] - 1.5 + np.arange(np.shape(t)[-1] + 3)

        def third_difference(f):
            return np.diff(f, n=3, axis=-1)
    z = points / sigma
    Phi = 0.5 * (1.0 + erf(z / math.sqrt(2.0)))
    phi = exp(-0.5 * z * z) / _SQRT_2PI
    g3 = 0.5 * (points * points + sigma * sigma) * Phi + 0.5 * sigma * points * phi
    inside = xp.abs(t) <= 1.5 + SPLINE_SUPPORT_SIGMAS * sigma
    k = third_difference(g3) * inside
    if not derivatives:
        return k
    g2 = points * Phi + sigma * phi
    k_u = -third_difference(g2) * inside
    if derivatives == "u":
        return k, k_u
    return k, k_u, sigma * third_difference(Phi) * inside


class _SoftBin(torch.autograd.Function):
    """``T[b, z, n] = sum_r amp[b, z, r] G(n - u[b, z, r])``, ``G`` the Gaussian of width ``sigma`` (bins,
    unit area), with its derivatives written out. With ``integrated`` > 0 (a float, not differentiated) ``G`` is
    :func:`bin_kernel`'s blend with the Gaussian integrated over each bin.

    The (B, 9, R, N) Gaussian is the largest array of the model. Forward-mode derivatives by autograd would
    build it again for every tangent (the calibration's Jacobian has ~50); here the Gaussian and its
    derivatives in ``u`` and ``sigma`` are made once and every tangent is a matrix product with them.
    """

    generate_vmap_rule = True

    @staticmethod
    def forward(amp, u, sigma, bins, integrated, spline):
        g = bin_kernel(bins.view(1, 1, 1, -1) - u.unsqueeze(-1), sigma, integrated, spline=spline)
        return torch.einsum("bzr,bzrn->bzn", amp, g)

    @staticmethod
    def setup_context(ctx, inputs, output):
        amp, u, sigma, bins, integrated, spline = inputs
        ctx.integrated, ctx.spline = integrated, spline
        ctx.set_materialize_grads(False)  # an input without a tangent gets None, not a tensor of zeros
        ctx.save_for_backward(amp, u, sigma, bins)
        ctx.save_for_forward(amp, u, sigma, bins)

    @staticmethod
    def _parts(amp, u, sigma, bins, integrated, spline):
        """G, dG/du, dG/dsigma (:func:`bin_kernel`)."""
        return bin_kernel(bins.view(1, 1, 1, -1) - u.unsqueeze(-1), sigma, integrated, derivatives=True, spline=spline)

    @staticmethod
    def jvp(ctx, d_amp, d_u, d_sigma, _d_bins, _d_integrated, _d_spline):
        amp, u, sigma, bins = ctx.saved_tensors
        # only the kernels the tangents need (inputs without one get None: set_materialize_grads)
        wanted = True if d_sigma is not None else ("u" if d_u is not None else False)
        parts = bin_kernel(bins.view(1, 1, 1, -1) - u.unsqueeze(-1), sigma, ctx.integrated, derivatives=wanted,
                           spline=ctx.spline)
        g = parts if wanted is False else parts[0]
        # the amplitudes' and the positions' tangents in one contraction over the rays, both kernels side by side
        rays, kernels = [], []
        if d_amp is not None:
            rays.append(d_amp)
            kernels.append(g)
        if d_u is not None:
            rays.append(amp * d_u)
            kernels.append(parts[1])
        terms = []
        if rays:
            terms.append(einsum2("bzr,bzrn->bzn", rays[0], kernels[0]) if len(rays) == 1 else
                         einsum2("bzr,bzrn->bzn", torch.cat(torch.broadcast_tensors(*rays), dim=-1),
                                 torch.cat(kernels, dim=-2)))
        if d_sigma is not None:
            terms.append(d_sigma * torch.einsum("bzr,bzrn->bzn", amp, parts[2]))
        if not terms:
            return torch.zeros(amp.shape[:2] + bins.shape, dtype=amp.dtype)
        return terms[0] if len(terms) == 1 else terms[0] + terms[1]

    @staticmethod
    def backward(ctx, grad):
        if grad is None:
            return None, None, None, None, None, None
        amp, u, sigma, bins = ctx.saved_tensors
        g, g_u, g_s = _SoftBin._parts(amp, u, sigma, bins, ctx.integrated, ctx.spline)
        d_amp = torch.einsum("bzn,bzrn->bzr", grad, g)
        d_u = amp * torch.einsum("bzn,bzrn->bzr", grad, g_u)
        d_sigma = (amp * torch.einsum("bzn,bzrn->bzr", grad, g_s)).sum().reshape(sigma.shape)
        return d_amp, d_u, d_sigma, None, None, None


def soft_bin(amp: torch.Tensor, u: torch.Tensor, sigma: torch.Tensor, bins: torch.Tensor,
             integrated: float = 0.0, spline: float = 0.0) -> torch.Tensor:
    """Transients (B, 9, N) of ray amplitudes ``amp`` (B, 9, R) at bin positions ``u`` (B, 9, R), each spread
    by a unit-area Gaussian of ``sigma`` bins over the bin centres ``bins`` (N,, consecutive); ``integrated`` (blend in
    [0, 1], :func:`bin_kernel`) integrates it over each bin instead; ``spline`` 1 spreads it by the quadratic B-spline
    convolved with that Gaussian (:func:`spline_bin_kernel`)."""
    amp, u = torch.broadcast_tensors(amp, u)
    return _SoftBin.apply(amp, u, torch.as_tensor(sigma, dtype=amp.dtype), bins.to(amp.dtype), float(integrated),
                          float(spline))


class ForwardModel:
    """Renders 9x128 zone histograms from per-ray returns or from a plane.

    ``params`` are held as tensors (``self.t``) so calibration can optimise them; ``rays`` is the
    quadrature. Use :meth:`render_plane` for planes and :meth:`render_returns` for anything a ray
    caster gives (the MuJoCo sensor). ``fitted``: names of the parameters a calibration will optimise;
    ``echo_gain`` and ``glass_gains`` among them have their returns rendered while derivatives are taken even
    when the parameters start at zero (:meth:`add_echo_and_glass`).
    """

    def __init__(self, params: ForwardParams | None = None, rays: ZoneRays | None = None,
                 dtype: torch.dtype = torch.float64, fitted: Collection[str] = ()) -> None:
        self.params = params if params is not None else ForwardParams()
        self.dtype = dtype
        self.rays = rays if rays is not None else ZoneRays.stratified(8, dtype=dtype)
        self.t = params_to_tensors(self.params, dtype)
        # whether the echo and the glass are rendered while derivatives are taken (they double the rays' soft
        # binning): when the parameters the model is built with have them, or a fit will optimise them
        self._echo = self.params.echo_gain != 0.0 or "echo_gain" in fitted
        self._glass = any(v != 0.0 for v in self.params.glass_gains) or "glass_gains" in fitted
        # the terms that are the identity at their defaults (each zone's pulse shape, the learned response, the zones'
        # tails, the grid crosstalk, the bins' widths, the time warp) are rendered while derivatives are taken only
        # where a fit names them, if it names any (None: every such term, as for a model built without ``fitted``)
        self._fitted = frozenset(fitted) if fitted else None
        self.bins = torch.arange(N_BINS, dtype=dtype)
        self._kind = torch.as_tensor(ZONE_KIND)
        d = self.rays.directions.to(dtype)
        self._tangent = d[..., :2] / d[..., 2:]  # (9, R, 2) ray coordinates on z = 1

    def ray_geometry(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Directions (9, R, 3) and weights (9, R) after the field-of-view scales.

        Scaling a zone's rectangle by ``s`` moves each ray to ``(s x, s y, 1)``; weights are
        re-weighted by the ratio of solid-angle densities so the quadrature stays uniform in solid angle.
        """
        t = self.t
        scale = torch.stack([t["centre_fov_scale"], t["edge_fov_scale"], t["corner_fov_scale"]])[self._kind]
        scale = scale.view(N_ZONES, 1, 1)
        xy = self._tangent * scale
        n2_old = 1.0 + (self._tangent ** 2).sum(-1)
        n2_new = 1.0 + (xy ** 2).sum(-1)
        dirs = torch.cat([xy, torch.ones_like(xy[..., :1])], dim=-1) / torch.sqrt(n2_new).unsqueeze(-1)
        w = self.rays.weights.to(self.dtype) * (n2_new / n2_old) ** -1.5
        return dirs, w / w.sum(dim=1, keepdim=True)

    # -- pieces ------------------------------------------------------------------------------
    def _renders(self, names: tuple[str, ...], away_from_default: bool) -> bool:
        """Whether a term that is the identity at its default values is rendered: where its parameters
        (``names``) are away from their defaults, or while derivatives are taken and a fit may move them (the
        model's ``fitted`` names one of them, or the model was built without ``fitted``). Skipping it elsewhere
        changes neither the histogram nor any derivative the fit takes, only its time."""
        if away_from_default:
            return True
        if not torch.is_grad_enabled():
            return False
        return self._fitted is None or any(n in self._fitted for n in names)

    def bin_scales(self) -> torch.Tensor:
        """Each zone's time scale (``ForwardParams.zone_bin_scales``) shaped (1, 9, 1) to multiply ``range / bin_size``."""
        return self.t["zone_bin_scales"].view(1, N_ZONES, 1)

    def zone_gains(self) -> torch.Tensor:
        t = self.t
        one = torch.ones((), dtype=self.dtype)
        base = torch.stack([one, t["edge_gain"], t["corner_gain"]])[self._kind]
        return base * t["zone_gains"]

    def pulse(self, reference: torch.Tensor) -> torch.Tensor:
        t = self.t
        return pulse_kernel(torch.as_tensor(reference, dtype=self.dtype), t["ref_time_scale"], t["ref_floor"],
                            t["tail_weight"], t["tail_decay"], t["pulse_soft_bin"], t["soft_bin_sigma"])

    def render_returns(self, ranges: torch.Tensor, cos_inc: torch.Tensor, albedo: torch.Tensor,
                       reference: torch.Tensor, weights: torch.Tensor | None = None,
                       specular_weight: torch.Tensor | None = None,
                       specular_exponent: torch.Tensor | None = None,
                       hit: torch.Tensor | None = None, kernel: torch.Tensor | None = None,
                       n_bins: int = N_BINS, light: tuple | None = None, pulse_only: bool = False,
                       ambient: torch.Tensor | None = None) -> torch.Tensor:
        """Histograms (B, 9, n_bins) from per-ray returns (the first ``n_bins`` bins; default all 128).

        ranges, cos_inc: (B, 9, R) range along the ray (m) and cosine of incidence (>= 0).
        albedo: (B,) or (B, 9, R) reflectance; specular_weight / specular_exponent likewise
        (default: the model's parameters). weights: (9, R) or (B, 9, R) quadrature weights summing
        to 1 per zone (default: this model's rays). hit: (B, 9, R) bool, False for rays that miss.
        reference: (B, 128) reference histograms, or pass a precomputed pulse ``kernel`` (B, K).
        light: optional ``(emitter_ranges, light_cos, beam)`` (B, 9, R) of a separate emitter
        (:meth:`plane_light`); without it the emitter sits at the receiver (the ray's own range and cosine,
        a uniform beam). pulse_only: stop after the pulse convolution (finish with :meth:`after_pulse`). ambient:
        (B, 9) counts per bin, see :meth:`after_pulse`.
        """
        amp, u = self.ray_arrivals(ranges, cos_inc, albedo, weights, specular_weight, specular_exponent, hit, light)
        hist = self.bin_arrivals(amp, u, reference, kernel, n_bins)
        return hist if pulse_only else self.after_pulse(hist, ambient)

    def ray_arrivals(self, ranges: torch.Tensor, cos_inc: torch.Tensor, albedo: torch.Tensor,
                     weights: torch.Tensor | None = None, specular_weight: torch.Tensor | None = None,
                     specular_exponent: torch.Tensor | None = None, hit: torch.Tensor | None = None,
                     light: tuple | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """What each ray brings back and when (:meth:`render_returns`' arguments): its counts (shading, inverse
        square, saturation, gains, quadrature weight) and its bin position (the TDC's warp applied), both (B, 9, R'),
        with the multipath echo and the cover-glass return appended along the rays (:meth:`add_echo_and_glass`)."""
        t = self.t
        r = torch.as_tensor(ranges, dtype=self.dtype)
        c = torch.clamp(torch.as_tensor(cos_inc, dtype=self.dtype), min=0.0)
        ks = t["specular_weight"] if specular_weight is None else _per_ray(specular_weight, r)
        alpha = t["specular_exponent"] if specular_exponent is None else _per_ray(specular_exponent, r)
        rho = _per_ray(albedo, r)
        r_light, beam = r, None
        if light is not None:
            r_light, c, beam = light
            c = torch.clamp(c, min=0.0)
        spec = torch.clamp(2.0 * c * c - 1.0, min=0.0)
        # pow with a zero base has an infinite derivative in the exponent at 0; keep it finite
        spec = torch.where(spec > 0, torch.pow(torch.clamp(spec, min=1e-30), alpha), torch.zeros_like(spec))
        shade = torch.clamp(c + ks * spec, min=1e-12)
        s = t["saturation"]
        w_sat = t["saturate_shading"]
        g = self.zone_gains().view(1, N_ZONES, 1)
        w_g = t["saturate_gain"]
        r_safe = torch.clamp(r_light, min=1e-4)
        flux = g ** w_g * rho * shade ** w_sat / (s * r_safe * r_safe)
        if beam is not None:
            flux = flux * beam
        photons = s * -torch.expm1(-flux) * shade ** (1.0 - w_sat) * g ** (1.0 - w_g)
        w = self.ray_geometry()[1] if weights is None else torch.as_tensor(weights, dtype=self.dtype)
        w = w.expand_as(photons) if w.dim() == 2 else w
        amp = photons * w * float(self.params.rays_per_zone)
        if hit is not None:
            amp = amp * torch.as_tensor(hit, dtype=self.dtype)
        path = r if light is None else 0.5 * (r + r_light)  # one-way range: half the light's path
        u = path / t["bin_size"] * self.bin_scales() + t["bin_offset"] + t["zone_offsets"].view(1, N_ZONES, 1)
        amp, u = self.add_echo_and_glass(amp, u, path)
        if self._renders(("time_warp",), bool(torch.any(t["time_warp"] != 0))):
            u = warp_positions(u, t["time_warp"])[0]  # the TDC's integral non-linearity (direct, echo and glass)
        return amp, u

    def bin_arrivals(self, amp: torch.Tensor, u: torch.Tensor, reference: torch.Tensor,
                     kernel: torch.Tensor | None = None, n_bins: int = N_BINS) -> torch.Tensor:
        """The zone histograms (B, 9, n_bins) of ray counts ``amp`` at bin positions ``u`` (B, 9, R'): each ray
        soft-binned, the transient convolved with the laser pulse (from ``reference`` (B, 128), or the precomputed
        ``kernel`` (B, K))."""
        t = self.t
        transient = soft_bin(amp, u, t["soft_bin_sigma"], self.bins[:n_bins], float(t["soft_bin_integrated"]),
                             float(t["soft_bin_spline"]))
        if kernel is None:
            kernel = self.pulse(torch.as_tensor(reference, dtype=self.dtype).expand(amp.shape[0], N_BINS))
        return convolve_pulse(transient, kernel)

    def add_echo_and_glass(self, amp: torch.Tensor, u: torch.Tensor,
                           path: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Ray amplitudes and bin positions (B, 9, R) with the multipath echo and the cover-glass return appended
        (along the ray axis; the soft binning then renders them with the rays).

        Echo: every ray again at twice its one-way range ``path`` (m, at the zone's time scale ``zone_bin_scales``), ``echo_gain (ECHO_REFERENCE_RANGE / path)^p``
        (``p = echo_power``, 2 by default)
        times its amplitude (light that the surface sends back to the sensor's face, which sends it to the
        surface again: one more round trip, and its spread over the face's solid angle falls with the range
        squared). Exact for a surface parallel to the sensor's face; for a tilted one it is the first-order term.
        Glass: one return per zone of ``glass_gains`` (counts per unit-area transient) at zero range plus
        ``glass_delay`` bins, the same in every frame (the package's cover glass). Nothing is appended when
        both are zero; while derivatives are taken, when the parameters the model was built with have them (a fit
        starts them just above zero, :data:`place_safe.calibration.forward_fit.NONZERO_START`) or its ``fitted``
        names them.
        """
        t = self.t
        grad = torch.is_grad_enabled()
        if (self._echo if grad else float(t["echo_gain"]) != 0.0):
            echo = t["echo_gain"] * (ECHO_REFERENCE_RANGE / torch.clamp(path, min=1e-4)) ** t["echo_power"]
            u_echo = (2.0 * path / t["bin_size"] * self.bin_scales() + t["bin_offset"]
                      + t["zone_offsets"].view(1, N_ZONES, 1))
            amp, u = torch.broadcast_tensors(amp, u)
            amp = torch.cat([amp, amp * echo], dim=-1)
            u = torch.cat([u, u_echo.expand_as(u)], dim=-1)
        if (self._glass if grad else bool(torch.any(t["glass_gains"] != 0))):
            amp, u = torch.broadcast_tensors(amp, u)
            b = amp.shape[0]
            g_amp = t["glass_gains"].view(1, N_ZONES, 1).expand(b, N_ZONES, 1)
            g_u = (t["bin_offset"] + t["glass_delay"] + t["zone_offsets"]).view(1, N_ZONES, 1).expand(b, N_ZONES, 1)
            amp = torch.cat([amp, g_amp.to(amp.dtype)], dim=-1)
            u = torch.cat([u, g_u.to(u.dtype)], dim=-1)
        return amp, u

    #: Parameters that act only after the pulse convolution (:meth:`after_pulse`): a calibration's derivatives in
    #: them need not render the rays again.
    AFTER_PULSE = ("response_kernel", "zone_tail_weights", "zone_tail_decays", "crosstalk", "crosstalk_self",
                   "crosstalk_grid", "pileup", "floor", "pileup_shadow", "zone_pulse_widths", "zone_pulse_skews",
                   "bin_gains")

    def after_pulse(self, hist: torch.Tensor, ambient: torch.Tensor | None = None) -> torch.Tensor:
        """The zone histograms (B, 9, N) after the pulse convolution -> what the sensor reports: each zone's pulse
        shape (width, skew), the learned response, its own tail, crosstalk, the bins' widths, pile-up and the constant
        floor (the parameters of :attr:`AFTER_PULSE`).

        ``ambient`` (B, 9), counts per bin: the frames' ambient light as it arrives (before any pile-up), which then
        takes part in the pile-up with the return (:func:`ambient_pileup`); the result is the return's counts above
        that ambient (negative where the return's counts shadow the ambient after it). None: the return alone (the
        model as it was: the sensor's floor, measured after the return, is subtracted from the data instead)."""
        t = self.t
        shaped = self._renders(("zone_pulse_widths", "zone_pulse_skews"),
                               bool(torch.any(t["zone_pulse_widths"] != 0)) or bool(torch.any(t["zone_pulse_skews"] != 0)))
        if shaped:
            shape = pulse_shape_matrix(t["zone_pulse_widths"], t["zone_pulse_skews"], hist.shape[-1], self.dtype)
            hist = einsum2("bzk,znk->bzn", hist, shape)
        if self._renders(("response_kernel",), bool(torch.any(t["response_kernel"] != 0))):
            hist = add_response(hist, t["response_kernel"])
        if self._renders(("zone_tail_weights", "zone_tail_decays"), bool(torch.any(t["zone_tail_weights"] != 0))):
            hist = add_zone_tails(hist, zone_tail_taps(t["zone_tail_weights"], t["zone_tail_decays"], self.dtype))
        # the crosstalk as one (9, 9) matrix M[to, from]: each zone keeps its histogram and gets ``crosstalk`` of the
        # total of the others and ``crosstalk x crosstalk_self`` of its own, plus the neighbour grid
        c = t["crosstalk"]
        mix = (1.0 - c * (1.0 - t["crosstalk_self"])) * torch.eye(N_ZONES, dtype=self.dtype) + c
        if self._renders(("crosstalk_grid",), bool(torch.any(t["crosstalk_grid"] != 0))):
            mix = mix + grid_crosstalk_matrix(t["crosstalk_grid"], self.dtype)
        hist = einsum2("tf,bfn->btn", mix, hist)
        if shaped:
            hist = torch.clamp(hist, min=0.0)  # the shape correction's negative lobes beside a sharp pulse: no counts
        if self._renders(("bin_gains",), bool(torch.any(t["bin_gains"] != 1))):
            hist = hist * bin_widths(t["bin_gains"])[:hist.shape[-1]]  # the TDC's bin widths (its DNL)
        if ambient is not None:
            return ambient_pileup(hist, ambient, t["pileup"], t["pileup_shadow"]) + t["floor"]
        return apply_pileup(hist, t["pileup"], t["pileup_shadow"]) + t["floor"]

    def plane_returns(self, normal: torch.Tensor, offset: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Ranges, cosines of incidence and hit mask (B, 9, R) of this model's rays on planes.

        normal: (B, 3) unit normals (n_z > 0), offset: (B,) distances (m).
        """
        n = torch.as_tensor(normal, dtype=self.dtype)
        d = torch.as_tensor(offset, dtype=self.dtype)
        cos = torch.einsum("zrk,bk->bzr", self.ray_geometry()[0], n)
        hit = cos > 1e-6
        ranges = d.view(-1, 1, 1) / torch.where(hit, cos, torch.ones_like(cos))
        return ranges, cos, hit

    def plane_light(self, normal: torch.Tensor, offset: torch.Tensor, ranges: torch.Tensor,
                    hit: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """Emitter range, light cosine and beam weight (B, 9, R) of this model's rays on planes, or None
        when the emitter sits at the receiver with a uniform beam (the paper's model; nothing to add).

        The ray meets the plane at ``P = r v``; the emitter is at ``E = (bx, by, 0)``:
        ``r_e = |P - E|``, ``cos = (d - n . E) / r_e``, ``beam = (P_z / r_e)^beam_power``.
        """
        t = self.t
        if not torch.is_grad_enabled() and not bool(torch.any(t["baseline"] != 0)) and float(t["beam_power"]) == 0.0:
            return None
        n = torch.as_tensor(normal, dtype=self.dtype)
        d = torch.as_tensor(offset, dtype=self.dtype)
        v = self.ray_geometry()[0]  # (9, R, 3)
        bx, by = t["baseline"][0], t["baseline"][1]
        r = torch.where(hit, ranges, torch.ones_like(ranges))
        w_e = v[..., 0] * bx + v[..., 1] * by  # (9, R)
        r_e = torch.sqrt(torch.clamp(r * r - 2.0 * r * w_e + bx * bx + by * by, min=1e-12))
        n_e = n[:, 0] * bx + n[:, 1] * by  # (B,)
        cos = (d - n_e).view(-1, 1, 1) / r_e
        beam = torch.pow(torch.clamp(r * v[..., 2] / r_e, min=1e-12), t["beam_power"])
        return r_e, cos, beam

    def render_plane(self, normal: torch.Tensor, offset: torch.Tensor, albedo: torch.Tensor,
                     reference: torch.Tensor, specular_weight: torch.Tensor | None = None,
                     specular_exponent: torch.Tensor | None = None,
                     kernel: torch.Tensor | None = None, n_bins: int = N_BINS,
                     pulse_only: bool = False, ambient: torch.Tensor | None = None) -> torch.Tensor:
        """Histograms (B, 9, n_bins) of planes ``n . x = d`` with albedo (B,) (``pulse_only``, ``ambient``: see
        :meth:`render_returns`)."""
        ranges, cos, hit = self.plane_returns(normal, offset)
        return self.render_returns(ranges, cos, albedo, reference, specular_weight=specular_weight,
                                   specular_exponent=specular_exponent, hit=hit, kernel=kernel, n_bins=n_bins,
                                   light=self.plane_light(normal, offset, ranges, hit), pulse_only=pulse_only,
                                   ambient=ambient)


@contextmanager
def single_thread():
    """Run small torch computations on one thread (restored afterwards).

    Tensors of a frame's pulse are tiny; torch's intra-op thread pool only adds hand-over waits, and on a
    busy machine (two cores shared with other work) those waits cost 20 ms a call instead of 0.3 ms.
    """
    n = torch.get_num_threads()
    if n == 1:
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _per_ray(value, like: torch.Tensor) -> torch.Tensor:
    v = torch.as_tensor(value, dtype=like.dtype)
    if v.dim() == 1:
        return v.view(-1, 1, 1)
    return v


#: Relative model error used when fitting the forward model to a sensor (2 % of the counts in a
#: bin): the model does not describe a real sensor to the Poisson noise level of a 1e5-count bin,
#: and without this term the brightest bins of the closest frames would dominate the fit. The
#: estimator's own weighting is ``ForwardParams.model_error``.
MODEL_ERROR = 0.02


def residual_weights(hists: np.ndarray, model_error: float = MODEL_ERROR) -> np.ndarray:
    """Inverse standard deviation of each histogram bin: Poisson noise plus relative model error."""
    h = np.clip(np.asarray(hists, dtype=float), 0.0, None)
    return 1.0 / np.sqrt(h + 1.0 + (model_error * h) ** 2)
