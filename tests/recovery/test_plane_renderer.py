"""The fast numpy plane renderer agrees with the torch forward model, Jacobian included."""

import math

import numpy as np
import pytest
import torch
from torch.func import jacfwd

from place_safe.recovery.forward import ForwardModel, ForwardParams, ZoneRays
from place_safe.recovery.plane_renderer import PlaneRenderer, convolution_matrices
from place_safe.evaluation.synthetic import default_reference


def _check(params: ForwardParams, x: np.ndarray, width: int = 70, ambient: np.ndarray | None = None) -> None:
    rays = ZoneRays.stratified(4)
    model = ForwardModel(params, rays)
    renderer = PlaneRenderer(params, rays)
    kernel = model.pulse(torch.as_tensor(default_reference())[None])
    conv = convolution_matrices(kernel.numpy(), width)

    def f(xt):
        a, b, z0 = xt[0], xt[1], xt[2]
        s = torch.sqrt(1 + a * a + b * b)
        n = torch.stack([a, b, torch.ones_like(a)]) / s
        return model.render_plane(n[None], (z0 / s).reshape(1), torch.exp(xt[3]).reshape(1), None,
                                  specular_weight=xt[4].reshape(1), specular_exponent=torch.exp(xt[5]).reshape(1),
                                  kernel=kernel, ambient=amb_t)[0, :, :width] - model.t["floor"]

    amb_t = None if ambient is None else torch.as_tensor(ambient, dtype=torch.float64)[None]

    xt = torch.tensor(x)
    h_ref = f(xt).numpy()
    j_ref = jacfwd(f)(xt).numpy()
    h, j = renderer.render(x[None], conv, jacobian=True, ambient=None if ambient is None else ambient[None])
    np.testing.assert_allclose(h[0], h_ref, rtol=1e-9, atol=1e-9 * h_ref.max())
    for k in range(6):
        scale = np.abs(j_ref[..., k]).max()
        np.testing.assert_allclose(j[0, ..., k], j_ref[..., k], atol=1e-9 * scale)


def test_matches_torch_model_published_params():
    _check(ForwardParams(), np.array([0.1, -0.2, 0.12, math.log(3.0), 0.15, math.log(1.8)]))


def test_matches_torch_model_with_extensions():
    p = ForwardParams(pileup=2e-7, tail_weight=0.2, tail_decay=3.0, edge_fov_scale=0.93, corner_fov_scale=0.9,
                      zone_offsets=list(np.linspace(-0.5, 0.5, 9)), zone_gains=list(np.linspace(0.8, 1.2, 9)))
    _check(p, np.array([-0.3, 0.25, 0.07, math.log(5.0), 0.3, math.log(2.5)]))


def test_convolution_matrix_is_causal_convolution():
    k = np.array([[1.0, 0.5, 0.25]])
    m = convolution_matrices(k, 6)[0]
    t = np.array([0, 1.0, 0, 0, 2.0, 0])
    np.testing.assert_allclose(m @ t, np.convolve(t, k[0])[:6])


def test_matches_torch_model_with_structural_choices():
    """The renderer follows the structural blends (pulse soft binning, saturation before shading, crosstalk
    including the zone, zone gains inside or outside the saturation) exactly, derivatives included."""
    for w_sat, xt_self, soft, w_gain in ((0.0, 1.0, 1.0, 1.0), (0.4, 0.3, 0.5, 0.0), (1.0, 0.0, 0.0, 0.3)):
        p = ForwardParams(saturate_shading=w_sat, crosstalk_self=xt_self, pulse_soft_bin=soft, crosstalk=0.02,
                          pileup=1e-7, saturate_gain=w_gain, zone_gains=list(np.linspace(0.7, 1.3, 9)))
        _check(p, np.array([0.2, 0.1, 0.05, math.log(4.0), 0.2, math.log(2.0)]))


def test_matches_torch_model_with_emitter_baseline():
    """The emitter beside the receiver (its range, cosine and beam profile) is rendered and differentiated
    exactly as in the torch model, close up (where it matters) and with the other extensions on."""
    p = ForwardParams(baseline=[0.003, -0.0015], beam_power=1.7, pileup=1e-7, saturate_shading=0.4,
                      edge_fov_scale=0.95, crosstalk=0.01)
    _check(p, np.array([0.2, -0.1, 0.03, math.log(2.0), 0.1, math.log(2.0)]))
    _check(p, np.array([-0.35, 0.3, 0.15, math.log(4.0), 0.2, math.log(1.5)]))


def test_matches_torch_model_with_zone_tails():
    """Each zone's own tail (weights and decays per zone) is rendered and differentiated exactly as in the
    torch model, with pile-up and crosstalk acting after it."""
    p = ForwardParams(zone_tail_weights=list(np.linspace(0.0, 0.08, 9)), zone_tail_decays=list(np.linspace(1.5, 4.0, 9)),
                      pileup=1e-7, crosstalk=0.02, crosstalk_self=0.5, tail_weight=0.02, tail_decay=5.0)
    _check(p, np.array([0.15, -0.05, 0.06, math.log(3.0), 0.1, math.log(2.0)]))
    _check(p, np.array([-0.3, 0.2, 0.2, math.log(1.0), 0.2, math.log(1.5)]))


def test_matches_torch_model_with_a_learned_impulse_response():
    """The learned impulse response (non-negative weights at lags 1..24 bins, a second bump included) is rendered
    and differentiated exactly as in the torch model, alone and together with the zones' own tails."""
    from place_safe.recovery.forward_params import RESPONSE_LAGS

    kernel = np.zeros(RESPONSE_LAGS)
    kernel[:4] = [0.3, 0.1, 0.05, 0.02]
    kernel[14:17] = [0.01, 0.02, 0.01]
    _check(ForwardParams(response_kernel=list(kernel), pileup=1e-7, crosstalk=0.01),
           np.array([0.1, 0.05, 0.08, math.log(3.0), 0.1, math.log(2.0)]))
    p = ForwardParams(response_kernel=list(kernel), zone_tail_weights=list(np.linspace(0.0, 0.08, 9)),
                      zone_tail_decays=list(np.linspace(1.5, 4.0, 9)))
    _check(p, np.array([-0.2, 0.1, 0.15, math.log(2.0), 0.2, math.log(1.5)]))


def test_matches_torch_model_with_grid_crosstalk_glass_and_echo():
    """The unit terms of version 3 (crosstalk by neighbour displacement in the 3x3 grid, the cover-glass return
    at zero range, the multipath echo at twice the range) are rendered and differentiated exactly as in the torch
    model, alone, together, and with the emitter beside the receiver."""
    grid = list(np.linspace(0.002, 0.016, 8))
    glass = list(np.linspace(5.0, 40.0, 9))
    x = np.array([0.12, -0.08, 0.07, math.log(3.0), 0.1, math.log(2.0)])
    _check(ForwardParams(crosstalk_grid=grid), x)
    _check(ForwardParams(glass_gains=glass, glass_delay=2.5), x)
    _check(ForwardParams(echo_gain=0.05), x)
    p = ForwardParams(crosstalk_grid=grid, glass_gains=glass, glass_delay=1.0, echo_gain=0.08, pileup=1e-7,
                      crosstalk=0.01, zone_offsets=list(np.linspace(-0.5, 0.5, 9)))
    _check(p, np.array([-0.25, 0.2, 0.18, math.log(2.0), 0.2, math.log(1.5)]))
    _check(ForwardParams(echo_gain=0.05, baseline=[0.003, -0.0015], beam_power=1.2), x)


def test_matches_torch_model_with_echo_falloff_pileup_shadow_and_pulse_shapes():
    """The terms of version 4 (the echo's falloff power, the pile-up's shadowing blend, each zone's pulse width
    and skew) are rendered and differentiated exactly as in the torch model, alone and together."""
    x = np.array([0.12, -0.08, 0.07, math.log(3.0), 0.1, math.log(2.0)])
    widths = list(np.linspace(-0.2, 0.2, 9))
    skews = list(np.linspace(0.15, -0.1, 9))
    _check(ForwardParams(echo_gain=0.05, echo_power=0.3), x)
    _check(ForwardParams(pileup=3e-7, pileup_shadow=0.0), x)
    _check(ForwardParams(pileup=3e-7, pileup_shadow=0.4, crosstalk=0.01), x)
    _check(ForwardParams(zone_pulse_widths=widths, zone_pulse_skews=skews), x)
    p = ForwardParams(zone_pulse_widths=widths, zone_pulse_skews=skews, echo_gain=0.02, echo_power=0.0,
                      pileup=2e-7, pileup_shadow=0.2, zone_tail_weights=list(np.linspace(0.0, 0.08, 9)),
                      glass_gains=list(np.linspace(5.0, 40.0, 9)), crosstalk_grid=list(np.linspace(0.002, 0.016, 8)),
                      baseline=[0.003, -0.0015], beam_power=1.2)
    _check(p, np.array([-0.25, 0.2, 0.18, math.log(2.0), 0.2, math.log(1.5)]))


def test_matches_torch_model_with_bin_gains():
    """The bins' widths (version 5) are rendered and differentiated exactly as in the torch model, alone and with
    the pile-up and the pulse shapes."""
    x = np.array([0.12, -0.08, 0.07, math.log(3.0), 0.1, math.log(2.0)])
    gains = list(1.0 + 0.05 * np.cos(np.arange(128) * 0.9))
    _check(ForwardParams(bin_gains=gains), x)
    _check(ForwardParams(bin_gains=gains, pileup=3e-7, pileup_shadow=0.4, crosstalk=0.01,
                         zone_pulse_widths=list(np.linspace(-0.2, 0.2, 9))), x)


def test_matches_torch_model_with_time_warp():
    """The TDC's integral non-linearity (version 5) moves the direct return, the echo and the glass as in the torch
    model, with the warp's slope in the derivatives."""
    x = np.array([0.12, -0.08, 0.07, math.log(3.0), 0.1, math.log(2.0)])
    warp = list(0.4 * np.sin(np.arange(17) * 0.7))
    _check(ForwardParams(time_warp=warp), x)
    _check(ForwardParams(time_warp=warp, echo_gain=0.03, echo_power=1.0, glass_gains=list(np.linspace(5.0, 40.0, 9)),
                         pileup=2e-7, bin_gains=list(1.0 + 0.05 * np.cos(np.arange(128) * 0.9))),
           np.array([-0.25, 0.2, 0.18, math.log(2.0), 0.2, math.log(1.5)]))


def test_matches_torch_model_with_zone_bin_scales():
    """Each zone's time scale (version 6) moves the direct return and the echo as in the torch model, the glass not,
    with the scale in the derivatives (co-located emitter and beside the receiver)."""
    x = np.array([0.12, -0.08, 0.07, math.log(3.0), 0.1, math.log(2.0)])
    scales = list(np.linspace(0.96, 1.05, 9))
    _check(ForwardParams(zone_bin_scales=scales), x)
    _check(ForwardParams(zone_bin_scales=scales, echo_gain=0.03, echo_power=1.0,
                         glass_gains=list(np.linspace(5.0, 40.0, 9)), pileup=2e-7, baseline=[0.003, -0.0015],
                         beam_power=1.2, time_warp=list(0.4 * np.sin(np.arange(17) * 0.7))),
           np.array([-0.25, 0.2, 0.18, math.log(2.0), 0.2, math.log(1.5)]))


def test_matches_torch_model_with_the_ambient_through_the_pile_up():
    """The ambient as it arrives (per zone) goes through the pile-up with the return, as in the torch model: the
    counts above it, negative after a bright return (its shadow), derivatives included; with no pile-up it is the
    return alone."""
    x = np.array([0.05, -0.1, 0.06, math.log(3.0), 0.1, math.log(2.0)])
    ambient = np.linspace(80.0, 160.0, 9)
    params = ForwardParams(pileup=2e-6, pileup_shadow=0.7, zone_tail_weights=[0.02] * 9)
    _check(params, x, ambient=ambient)
    rays = ZoneRays.stratified(4)
    kernel = ForwardModel(params, rays).pulse(torch.as_tensor(default_reference())[None]).numpy()
    conv = convolution_matrices(kernel, 70)
    renderer = PlaneRenderer(params, rays)
    h = renderer.render(x[None], conv, ambient=ambient[None])[0]
    assert h[:, -10:].max() < 0.0  # the ambient after the return is shadowed
    plain = PlaneRenderer(params.replace(pileup=0.0), rays)
    np.testing.assert_array_equal(plain.render(x[None], conv, ambient=ambient[None]), plain.render(x[None], conv))


def test_matches_torch_model_with_spline_soft_binning():
    """The quadratic B-spline soft binning (version 8) renders and differentiates as in the torch model, with the
    cover-glass return, the echo and per-zone albedos."""
    x = np.array([0.07, -0.04, 0.11, math.log(3.4), 0.12, math.log(1.8)])
    _check(ForwardParams(soft_bin_spline=1.0, soft_bin_sigma=0.22), x)
    _check(ForwardParams(soft_bin_spline=1.0, soft_bin_sigma=0.05, echo_gain=0.03, echo_power=1.0,
                         glass_gains=[0.5] * 9), x)


def test_matches_torch_model_with_integrated_soft_binning():
    """The soft binning integrated over each bin (version 7), fully and blended, renders and differentiates as in
    the torch model, the echo and the glass included."""
    x = np.array([0.12, -0.08, 0.07, math.log(3.0), 0.1, math.log(2.0)])
    _check(ForwardParams(soft_bin_integrated=1.0, soft_bin_sigma=0.54), x)
    _check(ForwardParams(soft_bin_integrated=0.4, soft_bin_sigma=0.7, echo_gain=0.03, echo_power=1.0,
                         glass_gains=list(np.linspace(5.0, 40.0, 9)), pileup=2e-7, baseline=[0.003, -0.0015],
                         beam_power=1.2, zone_bin_scales=list(np.linspace(0.96, 1.05, 9))),
           np.array([-0.25, 0.2, 0.18, math.log(2.0), 0.2, math.log(1.5)]))


def test_responses_made_once_give_the_same_renders_and_the_band_covers_rays_beyond_the_histogram():
    """The per-frame responses (pulse, pulse shape, learned response and zone tails folded into one causal matrix per
    zone) render what the pulse matrices render, Jacobian included; rays whose windows reach past either end of the
    histogram (a plane beyond it, a zone offset before bin 0) are rendered as the kernel evaluated at every bin."""
    from place_safe.recovery.forward import bin_kernel
    from place_safe.recovery.forward_params import RESPONSE_LAGS

    kernel = np.zeros(RESPONSE_LAGS)
    kernel[:3] = [0.2, 0.05, 0.01]
    p = ForwardParams(response_kernel=list(kernel), zone_tail_weights=list(np.linspace(0.01, 0.08, 9)),
                      zone_tail_decays=list(np.linspace(1.5, 4.0, 9)), zone_pulse_widths=[0.2] * 9,
                      zone_pulse_skews=[0.1] * 9, pileup=1e-7, crosstalk=0.01)
    rays = ZoneRays.stratified(4)
    renderer = PlaneRenderer(p, rays, zone_albedo=True)
    pulse = ForwardModel(p, rays).pulse(torch.as_tensor(default_reference())[None]).numpy()
    conv = convolution_matrices(np.repeat(pulse, 2, axis=0), 50)
    x = np.array([[0.2, -0.1, 0.1] + [math.log(3.0)] * 9 + [0.1, math.log(2.0)],
                  [-0.3, 0.2, 0.3] + [math.log(2.0)] * 9 + [0.2, math.log(1.5)]])
    h, j = renderer.render(x, conv, jacobian=True)
    h2, j2 = renderer.render(x, renderer.responses(conv), jacobian=True)
    np.testing.assert_allclose(h2, h, rtol=1e-12, atol=1e-12 * np.abs(h).max())
    np.testing.assert_allclose(j2, j, rtol=1e-12, atol=1e-12 * np.abs(j).max())
    u = np.array([[[-8.3, -0.4, 3.2, 48.7, 49.6, 63.0, 200.0]]])
    t, dense, place = renderer.soft_bin_window(u, 50)
    g, g_u = dense(renderer.kernel(t)), dense(renderer.kernel(t, derivative=True))
    full, full_u, _ = bin_kernel(np.arange(50) - u[..., None], p.soft_bin_sigma, 0.0, derivatives=True)
    amp = np.linspace(1.0, 2.0, u.shape[-1])
    np.testing.assert_allclose(place(np.matmul(amp, g)), np.matmul(amp, full), atol=1e-15)
    np.testing.assert_allclose(place(np.matmul(amp, g_u)), np.matmul(amp, full_u), atol=1e-15)


def test_the_frames_own_crosstalk_as_an_unknown_renders_as_the_model_and_its_derivative_is_the_models():
    """With ``free_crosstalk`` the crosstalk is an unknown after the albedo: the histograms are the torch model's with that
    crosstalk (with pile-up, grid crosstalk and the zone in its own share), and its Jacobian column is the model's change
    with it (central differences of the torch model); the other columns stay where they were, so held at the calibrated
    value the renderer is the one without the unknown."""
    rays = ZoneRays.stratified(4)
    base = ForwardParams(pileup=2e-7, crosstalk=0.004, crosstalk_self=0.3, crosstalk_grid=[0.002] * 8)
    x6 = np.array([0.15, -0.1, 0.09, math.log(4.0), 0.2, math.log(2.0)])
    c = 0.011
    x7 = np.concatenate([x6[:4], [c], x6[4:]])
    renderer = PlaneRenderer(base, rays, free_crosstalk=True)
    assert renderer.n_unknowns == 7 and renderer.crosstalk_column == 4
    kernel = ForwardModel(base, rays).pulse(torch.as_tensor(default_reference())[None])
    conv = convolution_matrices(kernel.numpy(), 70)
    h, j = renderer.render(x7[None], conv, jacobian=True)

    def torch_render(crosstalk: float) -> np.ndarray:
        model = ForwardModel(base.model_copy(update={"crosstalk": crosstalk}), rays)
        a, b, z0 = (torch.tensor(v, dtype=torch.float64) for v in x6[:3])
        s = torch.sqrt(1 + a * a + b * b)
        n = torch.stack([a, b, torch.ones_like(a)]) / s
        out = model.render_plane(n[None], (z0 / s).reshape(1), torch.tensor([math.exp(x6[3])], dtype=torch.float64),
                                 None, specular_weight=torch.tensor([x6[4]], dtype=torch.float64),
                                 specular_exponent=torch.tensor([math.exp(x6[5])], dtype=torch.float64), kernel=kernel)
        return (out[0, :, :70] - model.t["floor"]).numpy()

    ref = torch_render(c)
    np.testing.assert_allclose(h[0], ref, rtol=1e-9, atol=1e-9 * ref.max())
    eps = 1e-6
    fd = (torch_render(c + eps) - torch_render(c - eps)) / (2 * eps)
    np.testing.assert_allclose(j[0, ..., 4], fd, atol=1e-6 * np.abs(fd).max())
    held = PlaneRenderer(base.model_copy(update={"crosstalk": c}), rays)
    h6, j6 = held.render(x6[None], conv, jacobian=True)
    np.testing.assert_allclose(h[0], h6[0], rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.delete(j[0], 4, axis=-1), j6[0], rtol=1e-12, atol=1e-12 * np.abs(j6).max())


def test_reused_renders_are_the_renders_made_afresh():
    """A render at the unknowns of the last one (the solver's Jacobian at an accepted step), or at its plane with another
    albedo and shading (the albedo's first guesses), gives bit for bit what a renderer without a past gives; the kept
    arrays follow the values, not the caller's arrays (changed in place after a render, or another pulse matrix of the
    same shape), and :meth:`PlaneRenderer.forget` drops them."""
    p = ForwardParams(pileup=2e-7, crosstalk=0.004, baseline=[0.002, 0.001], beam_power=0.5, echo_gain=0.05,
                      zone_tail_weights=[0.03] * 9, zone_tail_decays=[3.0] * 9, time_warp=list(np.linspace(0, 0.3, 17)))
    rays = ZoneRays.stratified(4)
    pulse = ForwardModel(p, rays).pulse(torch.as_tensor(default_reference())[None]).numpy()
    used = PlaneRenderer(p, rays, zone_albedo=True)
    conv = used.responses(convolution_matrices(pulse, 60))
    other = used.responses(convolution_matrices(pulse * 1.5, 60))
    amb = np.full((1, 9), 40.0)
    x = np.array([[0.2, -0.1, 0.1] + [math.log(3.0)] * 9 + [0.1, math.log(2.0)]])
    brighter = x.copy()
    brighter[0, 3:12] += 0.4
    brighter[0, -1] += 0.2

    def fresh(xs, c, jac):
        return PlaneRenderer(p, rays, zone_albedo=True).render(xs, c, jacobian=jac, ambient=amb)

    used.render(x, conv, ambient=amb)
    h, j = used.render(x, conv, jacobian=True, ambient=amb)   # the whole render reused
    h0, j0 = fresh(x, conv, True)
    np.testing.assert_array_equal(h, h0)
    np.testing.assert_array_equal(j, j0)
    np.testing.assert_array_equal(used.render(brighter, conv, ambient=amb), fresh(brighter, conv, False))  # rays reused
    h, j = used.render(brighter, conv, jacobian=True, ambient=amb)
    h0, j0 = fresh(brighter, conv, True)
    np.testing.assert_array_equal(h, h0)
    np.testing.assert_array_equal(j, j0)
    np.testing.assert_array_equal(used.render(brighter, other, ambient=amb), fresh(brighter, other, False))
    moved = brighter.copy()
    used.render(moved, conv, ambient=amb)
    moved[0, :3], moved[0, -2] = [-0.1, 0.3, 0.2], 0.3  # the caller's array changed in place after the render
    np.testing.assert_array_equal(used.render(moved, conv, ambient=amb), fresh(moved, conv, False))
    used.render(brighter, conv, ambient=amb)
    kept = brighter.copy()
    brighter[0, :3], brighter[0, -2] = [-0.1, 0.3, 0.2], 0.3
    h, j = used.render(kept, conv, jacobian=True, ambient=amb)  # the values rendered before the change
    h0, j0 = fresh(kept, conv, True)
    np.testing.assert_array_equal(h, h0)
    np.testing.assert_array_equal(j, j0)
    with pytest.raises(ValueError, match="read-only"):  # the kept histograms cannot be changed by mistake
        h[...] = 0.0
    used.forget()
    assert used._rays_cache is None and used._forward_cache is None
