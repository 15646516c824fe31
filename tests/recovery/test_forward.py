"""Forward imaging model: gradients, analytic cases, parameters I/O, batching."""

import math

import numpy as np
import pytest
import torch

from place_safe.exceptions import CalibrationError
from place_safe.recovery.forward import (ForwardModel, ForwardParams, PulseMatrices, ZoneRays, apply_pileup, bin_kernel,
                                         bin_widths, params_to_tensors, pulse_kernel, soft_bin)
from place_safe.geometry import Plane
from place_safe.sensor.frame import N_BINS, ZONE_DIRECTIONS
from place_safe.evaluation.synthetic import default_reference


def delta_reference(floor: float = 135.14) -> torch.Tensor:
    """A reference whose pulse is a delta at lag 0 (after the floor is removed)."""
    ref = torch.full((1, N_BINS), floor, dtype=torch.float64)
    ref[0, 0] += 1000.0
    return ref


def test_fronto_parallel_peaks_where_geometry_says():
    d = 0.15
    n = torch.tensor([[0.0, 0.0, 1.0]])
    for sigma in (0.5, 1.5):
        params = ForwardParams(crosstalk=0.0, soft_bin_sigma=sigma)
        model = ForwardModel(params, ZoneRays.stratified(1))  # one ray per zone, through its centre
        h = model.render_plane(n, torch.tensor([d]), torch.tensor([1.0]), delta_reference())[0].numpy()
        ranges = d / ZONE_DIRECTIONS[:, 2]
        expected = ranges / params.bin_size + params.bin_offset
        np.testing.assert_array_equal(h.argmax(1), np.round(expected).astype(int))
        if sigma > 1:  # a wide Gaussian sampled at whole bins keeps its centroid exactly
            centroid = (h * np.arange(N_BINS)).sum(1) / h.sum(1)
            np.testing.assert_allclose(centroid, expected, atol=1e-9)


def test_pulse_delays_peak_by_its_own_peak_lag():
    params = ForwardParams(crosstalk=0.0)
    model = ForwardModel(params, ZoneRays.stratified(1))
    ref = torch.as_tensor(default_reference())[None]
    kernel = model.pulse(ref)[0].numpy()
    h0 = model.render_plane(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.2]), torch.tensor([1.0]), delta_reference())[0]
    h1 = model.render_plane(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([0.2]), torch.tensor([1.0]), ref)[0]
    assert int(h1[4].argmax() - h0[4].argmax()) == int(np.argmax(kernel))
    # the reference peaks near bin 14 and is rescaled by ~0.279: a lag of about 4 zone bins
    assert 3 <= int(np.argmax(kernel)) <= 5


def test_inverse_square_falloff_without_saturation():
    params = ForwardParams(saturation=1e9, crosstalk=0.0, soft_bin_sigma=1.5)
    model = ForwardModel(params, ZoneRays.stratified(4))
    n = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    h = model.render_plane(n, torch.tensor([0.1, 0.2]), torch.tensor([1.0, 1.0]), delta_reference().expand(2, -1))
    ratio = h[0].sum() / h[1].sum()
    assert ratio.item() == pytest.approx(4.0, rel=1e-6)


def test_saturation_limits_counts():
    params = ForwardParams(crosstalk=0.0)
    model = ForwardModel(params, ZoneRays.stratified(4))
    n = torch.tensor([[0.0, 0.0, 1.0]])
    h = model.render_plane(n, torch.tensor([0.001]), torch.tensor([1e6]), delta_reference())
    # every ray saturates at s photons; the zone total is at most s * rays_per_zone
    assert h[0].sum(1).max().item() <= params.saturation * params.rays_per_zone * 1.0001


def test_crosstalk_mixes_zones():
    params = ForwardParams(crosstalk=0.01)
    model = ForwardModel(params, ZoneRays.stratified(2))
    ranges = torch.full((1, 9, 4), 0.1, dtype=torch.float64)
    cos = torch.ones_like(ranges)
    hit = torch.zeros_like(ranges, dtype=torch.bool)
    hit[0, 4] = True  # only the centre zone sees anything
    h = model.render_returns(ranges, cos, torch.tensor([1.0]), delta_reference(), hit=hit)[0]
    assert torch.allclose(h[0], 0.01 * h[4])
    assert torch.allclose(h[1], h[0])


def test_pileup_shifts_histograms_earlier():
    flux = torch.exp(-0.5 * ((torch.arange(40.0, dtype=torch.float64) - 20) / 1.5) ** 2) * 1e6
    piled = apply_pileup(flux, torch.tensor(1e-6, dtype=torch.float64))
    mean = lambda h: float((h * torch.arange(40.0)).sum() / h.sum())
    assert mean(piled) < mean(flux) - 0.1
    assert torch.allclose(apply_pileup(flux, torch.tensor(0.0)), flux)
    weak = apply_pileup(flux, torch.tensor(1e-15, dtype=torch.float64))
    assert torch.allclose(weak, flux, rtol=1e-6)


def test_gradcheck_float64():
    params = ForwardParams(pileup=1e-7, tail_weight=0.1, edge_fov_scale=0.95)
    model = ForwardModel(params, ZoneRays.stratified(2))
    ref = torch.as_tensor(default_reference())[None]

    def f(normal_xy, offset, albedo, bin_offset, saturation, pileup, fov):
        # pile-up in units of 1e-7 so the finite-difference step suits its scale
        model.t["bin_offset"], model.t["saturation"], model.t["pileup"] = bin_offset, saturation, pileup * 1e-7
        model.t["corner_fov_scale"] = fov
        n = torch.cat([normal_xy, torch.ones(1, 1, dtype=torch.float64)], dim=1)
        n = n / n.norm(dim=1, keepdim=True)
        return model.render_plane(n, offset, albedo, ref)[..., 10:30]

    inputs = (torch.tensor([[0.1, -0.2]], dtype=torch.float64, requires_grad=True),
              torch.tensor([0.08], dtype=torch.float64, requires_grad=True),
              torch.tensor([2.0], dtype=torch.float64, requires_grad=True),
              torch.tensor(9.5, dtype=torch.float64, requires_grad=True),
              torch.tensor(300.0, dtype=torch.float64, requires_grad=True),
              torch.tensor(1.0, dtype=torch.float64, requires_grad=True),
              torch.tensor(0.9, dtype=torch.float64, requires_grad=True))
    assert torch.autograd.gradcheck(f, inputs, eps=1e-6, atol=1e-4, rtol=1e-4)


def test_batched_equals_single():
    model = ForwardModel(ForwardParams(), ZoneRays.stratified(3))
    ref = torch.as_tensor(default_reference())
    planes = [Plane.from_angles(0.2, 0.5, 0.1), Plane.from_angles(0.4, -2.0, 0.25)]
    n = torch.as_tensor(np.array([p.normal for p in planes]))
    d = torch.as_tensor(np.array([p.offset for p in planes]))
    both = model.render_plane(n, d, torch.tensor([1.0, 2.0]), ref.expand(2, -1))
    one = model.render_plane(n[1:], d[1:], torch.tensor([2.0]), ref[None])
    assert torch.allclose(both[1:], one)


def test_random_rays_are_uniform_in_solid_angle():
    rng = np.random.default_rng(3)
    rays = ZoneRays.random(20000, rng)
    strat = ZoneRays.stratified(64)
    # mean direction per zone agrees between the two quadratures
    mean_r = (rays.directions * rays.weights[..., None]).sum(1)
    mean_s = (strat.directions * strat.weights[..., None]).sum(1)
    assert torch.allclose(mean_r, mean_s, atol=2e-3)


def test_pulse_kernel_is_normalised():
    ref = torch.as_tensor(default_reference())[None]
    k = pulse_kernel(ref, torch.tensor(0.27887, dtype=torch.float64), torch.tensor(135.14, dtype=torch.float64))
    # normalised to peak 1 in reference bins; resampled at zone-bin lags the maximum lands near it
    assert 0.5 < k.max().item() <= 1.0
    assert (k >= 0).all()


def test_pulse_matrices_are_pulse_kernel():
    """Property (hypothesis): the solver's matrix form of the pulse (:class:`PulseMatrices`) gives
    :func:`pulse_kernel`'s kernels to rounding, for any time scale, floor, tail, soft-binning and reference (real ones,
    scaled, shifted, with noise, flat, all below the floor, and with a peak in the last bins)."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    base = np.asarray(default_reference(), dtype=float)

    @settings(max_examples=40, deadline=None)
    @given(scale=st.floats(0.12, 0.6), floor=st.floats(0.0, 400.0), tail=st.sampled_from([0.0, 0.3, 2.0]),
           decay=st.floats(0.5, 8.0), soft=st.sampled_from([0.0, 0.02, 1.0]), sigma=st.floats(0.2, 2.0),
           shift=st.integers(-20, 100), gain=st.floats(0.0, 50.0), seed=st.integers(0, 2 ** 16))
    def check(scale, floor, tail, decay, soft, sigma, shift, gain, seed):
        rng = np.random.default_rng(seed)
        refs = np.stack([np.roll(base, shift) * gain + rng.poisson(50.0, N_BINS), np.full(N_BINS, floor),
                         rng.poisson(200.0, N_BINS).astype(float)])
        params = ForwardParams(ref_time_scale=scale, ref_floor=floor, tail_weight=tail, tail_decay=decay,
                               pulse_soft_bin=soft, soft_bin_sigma=sigma)
        t = params_to_tensors(params, torch.float64)
        with torch.no_grad():
            want = pulse_kernel(torch.as_tensor(refs), t["ref_time_scale"], t["ref_floor"], t["tail_weight"],
                                t["tail_decay"], t["pulse_soft_bin"], t["soft_bin_sigma"]).numpy()
        got = PulseMatrices(t)(refs)
        assert got.shape == want.shape
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12)

    check()


def test_structural_choices_default_to_the_model_as_it_was():
    """Old parameter files (without the structural fields) load and render as before."""
    d = ForwardParams().to_dict()
    for k in ("pulse_soft_bin", "saturate_shading", "crosstalk_self", "saturate_gain"):
        d.pop(k)
    p = ForwardParams.from_dict(d)
    assert (p.pulse_soft_bin, p.saturate_shading, p.crosstalk_self, p.saturate_gain) == (0.0, 1.0, 0.0, 1.0)
    with pytest.raises(CalibrationError):
        ForwardParams(saturate_shading=1.5)


def test_crosstalk_self_adds_the_zone_itself():
    ref = torch.as_tensor(default_reference())[None]
    plane = Plane.from_angles(0.2, 0.5, 0.1)
    n, d = torch.as_tensor(plane.normal)[None], torch.tensor([plane.offset])
    h = {}
    for cs in (0.0, 1.0):
        model = ForwardModel(ForwardParams(crosstalk=0.01, crosstalk_self=cs), ZoneRays.stratified(3))
        h[cs] = model.render_plane(n, d, torch.tensor([1.0]), ref)[0]
    direct = ForwardModel(ForwardParams(crosstalk=0.0), ZoneRays.stratified(3)).render_plane(n, d, torch.tensor([1.0]), ref)[0]
    assert torch.allclose(h[1.0] - h[0.0], 0.01 * direct, rtol=1e-9, atol=1e-6)


def test_unshaded_saturation_scales_with_shading_after_saturating():
    """With saturate_shading = 0 a fully saturated return still scales with the cosine of incidence."""
    ref = torch.as_tensor(default_reference())[None]
    tot = {}
    for w in (0.0, 1.0):
        model = ForwardModel(ForwardParams(saturate_shading=w, crosstalk=0.0, specular_weight=0.0),
                             ZoneRays.stratified(3))
        vals = []
        for theta in (0.0, 0.5):
            plane = Plane.from_angles(theta, 0.0, 0.01)
            vals.append(float(model.render_plane(torch.as_tensor(plane.normal)[None], torch.tensor([plane.offset]),
                                                 torch.tensor([50.0]), ref)[0, 4].sum()))
        tot[w] = vals[1] / vals[0]
    assert tot[1.0] > 0.97          # saturated: the shading hardly matters
    assert tot[0.0] < 0.93          # shading multiplies after saturation


def test_gains_outside_the_saturation_keep_zone_ratios_at_every_range():
    """With saturate_gain = 0 a zone's gain scales its saturated counts, so the ratio of two zones' counts is
    the same close up (saturated) and far away; inside the saturation (1) it shrinks towards 1 close up."""
    ref = torch.as_tensor(default_reference())[None]
    gains = [1.0] * 9
    gains[0] = 2.0
    ratio = {}
    for w in (0.0, 1.0):
        model = ForwardModel(ForwardParams(saturate_gain=w, zone_gains=gains, crosstalk=0.0), ZoneRays.stratified(3))
        ratio[w] = []
        for d in (0.01, 0.3):
            h = model.render_plane(torch.tensor([[0.0, 0.0, 1.0]]), torch.tensor([d]), torch.tensor([50.0]), ref)[0]
            ratio[w].append(float(h[0].sum() / h[2].sum()))  # zone 1 (gain 2) over zone 3 (a corner, gain 1)
    assert ratio[0.0][0] == pytest.approx(ratio[0.0][1], rel=1e-3)
    assert ratio[1.0][0] < 0.8 * ratio[1.0][1]


def test_soft_binned_pulse_is_smoother_than_interpolated():
    ref = torch.as_tensor(default_reference())[None]
    ts, fl = torch.tensor(0.27887, dtype=torch.float64), torch.tensor(135.14, dtype=torch.float64)
    lin = pulse_kernel(ref, ts, fl)
    soft = pulse_kernel(ref, ts, fl, soft_bin=torch.tensor(1.0, dtype=torch.float64),
                        sigma=torch.tensor(0.5, dtype=torch.float64))
    assert abs(int(lin.argmax()) - int(soft.argmax())) <= 1
    assert soft.max().item() == pytest.approx(1.0)
    assert (soft > 0.05).sum() >= (lin > 0.05).sum()


def test_a_file_without_the_learned_response_reads_as_none():
    """Forward parameters written before the learned impulse response (no ``response_kernel`` key) load with
    zero weights, which render exactly what the model rendered before."""
    from place_safe.recovery.forward_params import RESPONSE_LAGS

    d = ForwardParams().to_dict()
    d.pop("response_kernel")
    old = ForwardParams.from_dict(d)
    assert old.response_kernel == [0.0] * RESPONSE_LAGS


def test_the_learned_response_adds_delayed_copies_of_the_histogram():
    """A weight ``w`` at lag ``k`` adds ``w`` times the histogram ``k`` bins later (causal, per zone)."""
    from place_safe.recovery.forward import add_response
    from place_safe.recovery.forward_params import RESPONSE_LAGS

    hist = torch.zeros(1, 9, 40, dtype=torch.float64)
    hist[0, :, 5] = 100.0
    kernel = torch.zeros(RESPONSE_LAGS, dtype=torch.float64)
    kernel[14] = 0.02  # lag 15
    out = add_response(hist, kernel)
    expected = hist.clone()
    expected[0, :, 20] = 2.0
    torch.testing.assert_close(out, expected)


def test_a_file_without_the_unit_terms_renders_the_model_as_it_was():
    """Forward parameters written before the unit terms of version 3 (no ``crosstalk_grid``, ``glass_*``,
    ``echo_gain``, ``centre_fov_scale`` keys) load with the defaults, which render exactly what the model rendered
    before: the same histograms as parameters that never had them."""
    from place_safe.evaluation.synthetic import default_reference

    d = ForwardParams(crosstalk=0.01, pileup=1e-7).to_dict()
    for key in ("crosstalk_grid", "glass_gains", "glass_delay", "echo_gain", "centre_fov_scale"):
        d.pop(key)
    old = ForwardParams.from_dict(d)
    assert old.crosstalk_grid == [0.0] * 8 and old.glass_gains == [0.0] * 9 and old.echo_gain == 0.0
    assert old.centre_fov_scale == 1.0
    model = ForwardModel(old, ZoneRays.stratified(4))
    normal = torch.tensor([[0.1, -0.05, 1.0]], dtype=torch.float64)
    normal = normal / normal.norm()
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    with torch.no_grad():
        plain = model.render_plane(normal, torch.tensor([0.12]), torch.tensor([3.0]), ref)
        amp = torch.rand(1, 9, 16, dtype=torch.float64)
        u = torch.rand(1, 9, 16, dtype=torch.float64) * 50
        a2, u2 = model.add_echo_and_glass(amp, u, u * 0.01)
    assert a2.shape == amp.shape  # nothing appended when the terms are off
    with torch.enable_grad():
        again = model.render_plane(normal, torch.tensor([0.12]), torch.tensor([3.0]), ref)
    torch.testing.assert_close(plain, again.detach())


def test_terms_a_fit_will_optimise_are_rendered_under_differentiation_from_zero():
    """A model built with echo and glass at zero appends their returns while derivatives are taken only when
    ``fitted`` names them: a fit that starts them at zero still gets their derivatives."""
    amp = torch.rand(1, 9, 16, dtype=torch.float64)
    u = torch.rand(1, 9, 16, dtype=torch.float64) * 50
    for fitted, rays in (((), 16), (("echo_gain",), 32), (("glass_gains",), 17), (("echo_gain", "glass_gains"), 33)):
        model = ForwardModel(ForwardParams(), ZoneRays.stratified(4), fitted=fitted)
        with torch.enable_grad():
            a2, u2 = model.add_echo_and_glass(amp, u, u * 0.01)
        assert a2.shape[-1] == u2.shape[-1] == rays, fitted
        with torch.no_grad():  # without derivatives only terms that are not zero are rendered
            assert model.add_echo_and_glass(amp, u, u * 0.01)[0].shape == amp.shape


def test_identity_terms_a_fit_does_not_name_are_skipped_with_the_same_histogram_and_derivatives():
    """A model built with ``fitted`` skips, while derivatives are taken, the terms that are the identity at their
    defaults and that the fit does not name (each zone's pulse shape, the learned response, the grid crosstalk, the
    bins' widths, the time warp): the histogram and its forward-mode derivatives in the fitted parameters are those
    of a model built without ``fitted``, which renders every term."""
    from torch.func import jvp

    from place_safe.evaluation.synthetic import default_reference

    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None].expand(2, -1)
    normal = torch.tensor([[0.1, -0.05, 1.0], [0.0, 0.2, 1.0]], dtype=torch.float64)
    normal = normal / normal.norm(dim=1, keepdim=True)
    offset, albedo = torch.tensor([0.12, 0.3], dtype=torch.float64), torch.tensor([3.0, 2.0], dtype=torch.float64)
    fitted = ("bin_offset", "soft_bin_sigma", "crosstalk", "zone_tail_weights", "pileup")
    derivs = []
    for kw in ({}, {"fitted": fitted}):
        model = ForwardModel(ForwardParams(), ZoneRays.stratified(3), **kw)
        base = {n: model.t[n] for n in fitted}

        def f(*values, model=model, base=base):
            for n, v in zip(fitted, values):
                model.t[n] = v
            return model.render_plane(normal, offset, albedo, ref)

        tangents = tuple(torch.ones_like(v) * (k + 1) for k, v in enumerate(base.values()))
        derivs.append(jvp(f, tuple(base.values()), tangents))
    torch.testing.assert_close(derivs[0][0], derivs[1][0], rtol=0, atol=0)
    torch.testing.assert_close(derivs[0][1], derivs[1][1], rtol=1e-12, atol=1e-9)
    assert float(derivs[0][1].abs().max()) > 0
    model = ForwardModel(ForwardParams(), ZoneRays.stratified(3), fitted=fitted)
    with torch.enable_grad():
        assert not model._renders(("time_warp",), False) and not model._renders(("bin_gains",), False)
        assert model._renders(("zone_tail_weights", "zone_tail_decays"), False)
        assert model._renders(("time_warp",), True)  # a warp away from zero is rendered whatever is fitted
    assert ForwardModel(ForwardParams())._fitted is None


def test_grid_crosstalk_reaches_only_the_named_neighbours():
    """A weight at displacement (dx, dy) takes that share of the zone at (x + dx, y + dy) in the 3x3 grid, and of
    no other zone; zones at the grid's edge have no neighbour beyond it."""
    from place_safe.recovery.forward import grid_crosstalk_matrix
    from place_safe.recovery.forward_params import GRID_DISPLACEMENTS, _grid_positions

    pos = _grid_positions()
    for k, (dx, dy) in enumerate(GRID_DISPLACEMENTS):
        w = torch.zeros(8, dtype=torch.float64)
        w[k] = 0.1
        m = grid_crosstalk_matrix(w).numpy()
        for to in range(9):
            for frm in range(9):
                expect = 0.1 if tuple(pos[frm] - pos[to]) == (dx, dy) else 0.0
                assert m[to, frm] == pytest.approx(expect)


def test_echo_and_glass_appear_where_they_belong():
    """The multipath echo of a level plane at range r sits at twice the range, its size echo_gain (0.1 m / r)^2 of
    the direct return's; the cover-glass return sits at zero range plus glass_delay and is the same for any
    plane."""
    from place_safe.evaluation.synthetic import default_reference

    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    base = ForwardParams(soft_bin_sigma=0.5)
    with torch.no_grad():
        def render(p, z):
            return ForwardModel(p, ZoneRays.stratified(4)).render_plane(normal, torch.tensor([z]), torch.tensor([3.0]),
                                                                         ref)[0, 4].numpy()
        z = 0.2
        direct = render(base, z)
        echo = render(ForwardParams(soft_bin_sigma=0.5, echo_gain=0.5), z) - direct
        peak_direct, peak_echo = int(direct.argmax()), int(echo.argmax())
        assert abs((peak_echo - peak_direct) - z / base.bin_size) <= 1.5
        assert echo.sum() / direct.sum() == pytest.approx(0.5 * (0.1 / z) ** 2, rel=0.05)
        glass = ForwardParams(glass_gains=[50.0] * 9, glass_delay=2.0)
        g1 = render(glass, 0.2) - render(base, 0.2)
        g2 = render(glass, 0.3) - render(base, 0.3)
    np.testing.assert_allclose(g1, g2, atol=1e-9)
    assert g1.max() > 5.0
    assert int(np.argmax(g1)) < peak_direct


def test_a_file_without_the_version_4_terms_renders_the_model_as_it_was():
    """Forward parameters written before version 4 (no ``echo_power``, ``pileup_shadow``, ``zone_pulse_*`` keys)
    load with the defaults (inverse-square echo, Coates pile-up, the reference's pulse shape) and render the same
    histograms as before."""
    d = ForwardParams(crosstalk=0.01, pileup=2e-7, echo_gain=0.05).to_dict()
    for key in ("echo_power", "pileup_shadow", "zone_pulse_widths", "zone_pulse_skews"):
        d.pop(key)
    old = ForwardParams.from_dict(d)
    assert old.echo_power == 2.0 and old.pileup_shadow == 1.0
    assert old.zone_pulse_widths == [0.0] * 9 and old.zone_pulse_skews == [0.0] * 9
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    with torch.no_grad():
        h = ForwardModel(old, ZoneRays.stratified(4)).render_plane(normal, torch.tensor([0.15]), torch.tensor([3.0]),
                                                                   ref)
        # the same thing written out by hand: the version 3 echo law and Coates' formula
        p3 = ForwardParams(crosstalk=0.01, pileup=0.0, echo_gain=0.05)
        raw = ForwardModel(p3, ZoneRays.stratified(4)).render_plane(normal, torch.tensor([0.15]), torch.tensor([3.0]),
                                                                    ref)
        before = torch.cumsum(raw, -1) - raw
        coates = -torch.expm1(-2e-7 * raw) / 2e-7 * torch.exp(-2e-7 * before)
    torch.testing.assert_close(h, coates)


def test_pulse_shape_keeps_area_and_mean_and_adds_the_stated_moments():
    """The zone's pulse-shape correction keeps the histogram's area and mean time, adds 2 w bins^2 to its variance
    and 6 s bins^3 to its third central moment."""
    from place_safe.recovery.forward import pulse_shape_matrix

    n = 64
    k = torch.arange(n, dtype=torch.float64)
    h = torch.exp(-0.5 * ((k - 30.0) / 2.5) ** 2) + 0.3 * torch.exp(-0.5 * ((k - 33.0) / 3.0) ** 2)

    def moments(x):
        a = x.sum()
        m = (k * x).sum() / a
        return a, m, (((k - m) ** 2) * x).sum() / a, (((k - m) ** 3) * x).sum() / a

    a0, m0, v0, t0 = moments(h)
    for w, s in ((0.2, 0.0), (-0.1, 0.05), (0.05, -0.2)):
        shape = pulse_shape_matrix([w] * 9, [s] * 9, n)
        assert torch.allclose(shape[0], shape[8])
        a, m, v, t = moments(shape[0] @ h)
        assert float(a) == pytest.approx(float(a0), rel=1e-12)
        assert float(m) == pytest.approx(float(m0), abs=1e-9)
        assert float(v - v0) == pytest.approx(2.0 * w, abs=1e-9)
        assert float(t - t0) == pytest.approx(6.0 * s, abs=1e-9)


def test_pileup_without_shadowing_compresses_each_bin_on_its_own():
    """``pileup_shadow = 0``: each bin is compressed by its own counts only, so a bright peak leaves the bins
    after it as they were (relative to the peak the tail grows with brightness); 1 is Coates' formula, which lowers
    them."""
    h = torch.tensor([[0.0, 10.0, 4000.0, 50.0, 20.0]], dtype=torch.float64)
    k = torch.tensor(1e-4, dtype=torch.float64)
    own = apply_pileup(h, k, 0.0)
    torch.testing.assert_close(own, -torch.expm1(-k * h) / k)
    coates = apply_pileup(h, k, 1.0)
    assert float(coates[0, 3]) < float(own[0, 3])
    assert float(own[0, 3] / own[0, 2]) > float(h[0, 3] / h[0, 2])


def test_the_echo_falls_with_the_stated_power_of_range():
    """``echo_power`` 0: the echo is ``echo_gain`` of the direct return at every range."""
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    with torch.no_grad():
        for z in (0.08, 0.25):
            def render(p):
                return ForwardModel(p, ZoneRays.stratified(4)).render_plane(normal, torch.tensor([z]),
                                                                            torch.tensor([3.0]), ref)[0, 4].numpy()
            direct = render(ForwardParams())
            echo = render(ForwardParams(echo_gain=0.02, echo_power=0.0)) - direct
            assert echo.sum() / direct.sum() == pytest.approx(0.02, rel=0.05)


def test_bin_gains_scale_each_bin_before_the_pileup_and_old_files_read_as_nominal():
    """``bin_gains`` (version 5, the TDC's bin widths) multiply bin ``b``'s expected counts before the pile-up, the
    same in every zone, through their bin-to-bin pattern (:func:`bin_widths`); a file without the key loads with every
    bin nominal (1) and renders as before."""
    d = ForwardParams(pileup=2e-7).to_dict()
    d.pop("bin_gains")
    old = ForwardParams.from_dict(d)
    assert old.bin_gains == [1.0] * N_BINS
    gains = list(1.0 + 0.04 * np.sin(np.arange(N_BINS) * 1.3))
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    with torch.no_grad():
        def render(p):
            return ForwardModel(p, ZoneRays.stratified(4)).render_plane(normal, torch.tensor([0.12]),
                                                                        torch.tensor([3.0]), ref)
        raw = render(ForwardParams())
        torch.testing.assert_close(render(old), apply_pileup(raw, torch.tensor(2e-7, dtype=torch.float64)))
        g = bin_widths(torch.as_tensor(gains, dtype=torch.float64))
        torch.testing.assert_close(render(ForwardParams(bin_gains=gains)), raw * g)
        torch.testing.assert_close(render(ForwardParams(bin_gains=gains, pileup=2e-7)),
                                   apply_pileup(raw * g, torch.tensor(2e-7, dtype=torch.float64)))
        # a narrower render uses the first bins' gains
        narrow = ForwardModel(ForwardParams(bin_gains=gains), ZoneRays.stratified(4)).render_plane(
            normal, torch.tensor([0.12]), torch.tensor([3.0]), ref, n_bins=48)
        torch.testing.assert_close(narrow, (raw * g)[..., :48], atol=1e-9, rtol=1e-9)


def test_bin_widths_keep_the_bin_to_bin_pattern_and_drop_a_slow_trend():
    """Only the bins' pattern acts: a constant or a slow trend of the gains gives widths of (nearly) 1, an
    alternating pattern passes almost unchanged."""
    n = torch.arange(N_BINS, dtype=torch.float64)
    torch.testing.assert_close(bin_widths(torch.full((N_BINS,), 1.3, dtype=torch.float64)),
                               torch.ones(N_BINS, dtype=torch.float64))
    slow = bin_widths(1.0 + 0.3 * n / N_BINS)
    assert float((slow[8:-8] - 1.0).abs().max()) < 1e-3
    alt = 1.0 + 0.03 * (-1.0) ** n
    assert float((bin_widths(alt)[8:-8] - alt[8:-8]).abs().max()) < 0.004


def test_time_warp_moves_returns_by_the_interpolated_shift():
    """``time_warp`` (version 5): a return at bin position ``u`` appears at ``u + warp(u)``, the knots' values less
    their straight line, interpolated linearly; zeros and straight lines move nothing (they are ``bin_offset`` and
    ``bin_size``), and a file without the key reads as zeros."""
    from place_safe.recovery.forward import WARP_KNOTS, warp_positions

    d = ForwardParams().to_dict()
    d.pop("time_warp")
    assert ForwardParams.from_dict(d).time_warp == [0.0] * WARP_KNOTS
    u = torch.tensor([3.0, 16.0, 20.0, 24.0, 40.0, 77.0], dtype=torch.float64)
    line = 0.3 - 0.02 * torch.arange(WARP_KNOTS, dtype=torch.float64)
    moved, slope = warp_positions(u, line)
    torch.testing.assert_close(moved, u)
    torch.testing.assert_close(slope, torch.ones_like(u))
    bow = torch.zeros(WARP_KNOTS, dtype=torch.float64)
    bow[2], bow[3] = 0.5, -0.3  # bins 16 and 24
    k = torch.arange(WARP_KNOTS, dtype=torch.float64) - 0.5 * (WARP_KNOTS - 1)
    w = bow - bow.mean() - k * (k * bow).sum() / (k * k).sum()
    moved, slope = warp_positions(u, bow + line)  # the line added changes nothing
    torch.testing.assert_close(moved[1:4], u[1:4] + torch.stack([w[2], 0.5 * (w[2] + w[3]), w[3]]))
    torch.testing.assert_close(slope[2], 1.0 + (w[3] - w[2]) / 8.0)
    assert float(w[2]) > 0.45 and float(w[3]) < -0.3


def test_a_bright_return_shadows_the_ambient_after_it():
    """``ambient_pileup``: the ambient takes part in the pile-up. With no ambient it is ``apply_pileup``; after a
    bright return the ambient reads lower than before it by Coates' factor ``exp(-k shadow N)`` (N the return's
    counts), so the counts above the arriving ambient go negative there; without pile-up it is the return alone."""
    from place_safe.recovery.forward import ambient_pileup

    h = torch.zeros((1, 9, 40), dtype=torch.float64)
    h[0, :, 10] = 2e5
    k = torch.tensor(1e-6, dtype=torch.float64)
    torch.testing.assert_close(ambient_pileup(h, torch.zeros((1, 9), dtype=torch.float64), k, 0.5),
                               apply_pileup(h, k, 0.5))
    a = torch.full((1, 9), 120.0, dtype=torch.float64)
    torch.testing.assert_close(ambient_pileup(h, a, torch.tensor(0.0, dtype=torch.float64)), h)
    out = ambient_pileup(h, a, k, 0.5)
    before, after = float(out[0, 4, 5]) + 120.0, float(out[0, 4, 30]) + 120.0
    assert after < before
    # after the return: arriving ambient times exp(-k shadow (N_return + earlier ambient)), per-bin compression aside
    expected = 120.0 * math.exp(-1e-6 * 0.5 * (2e5 + 120.0 * 30)) * (-math.expm1(-1e-6 * 120.0) / (1e-6 * 120.0))
    assert after == pytest.approx(expected, rel=1e-9)
    # through the model: the same as rendering the return and piling it up with the ambient by hand
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    normal = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    p = ForwardParams(pileup=3e-7, pileup_shadow=0.4)
    with torch.no_grad():
        m = ForwardModel(p, ZoneRays.stratified(4))
        raw = ForwardModel(ForwardParams(), ZoneRays.stratified(4)).render_plane(normal, torch.tensor([0.1]),
                                                                                 torch.tensor([3.0]), ref)
        got = m.render_plane(normal, torch.tensor([0.1]), torch.tensor([3.0]), ref, ambient=a)
    torch.testing.assert_close(got, apply_pileup(raw + 120.0, torch.tensor(3e-7, dtype=torch.float64), 0.4) - 120.0)


def test_zone_bin_scales_move_each_zones_return_with_range_and_old_files_read_as_one():
    """``zone_bin_scales`` (version 6): zone ``z``'s return sits at ``range / bin_size * scale_z + bin_offset +
    zone_offset_z``: with one ray a zone, exactly a zone offset of ``(scale_z - 1) range_z / bin_size`` bins, growing
    with the range; the glass at zero range does not move; a file without the key reads as ones, the model as it
    was."""
    d = ForwardParams().to_dict()
    d.pop("zone_bin_scales")
    assert ForwardParams.from_dict(d).zone_bin_scales == [1.0] * 9
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]
    normal = torch.tensor([[0.05, -0.03, 1.0]], dtype=torch.float64)
    normal = normal / normal.norm()
    scales = list(np.linspace(0.97, 1.04, 9))
    p = ForwardParams(soft_bin_sigma=0.3, zone_offsets=list(np.linspace(-0.3, 0.2, 9)))
    rays = ZoneRays.stratified(1)
    for z0 in (0.1, 0.3):
        with torch.no_grad():
            scaled = ForwardModel(p.model_copy(update={"zone_bin_scales": scales}), rays).render_plane(
                normal, torch.tensor([z0]), torch.tensor([3.0]), ref)
            r = ForwardModel(p, rays).plane_returns(normal, torch.tensor([z0]))[0][0, :, 0].numpy()
            moved = p.model_copy(update={"zone_offsets": list(np.asarray(p.zone_offsets)
                                                              + (np.asarray(scales) - 1.0) * r / p.bin_size)})
            offset = ForwardModel(moved, rays).render_plane(normal, torch.tensor([z0]), torch.tensor([3.0]), ref)
            plain = ForwardModel(p, rays).render_plane(normal, torch.tensor([z0]), torch.tensor([3.0]), ref)
        torch.testing.assert_close(scaled, offset)
        assert float((scaled - plain).abs().max()) > 0.1 * float(plain.max())
    glass = ForwardParams(glass_gains=[50.0] * 9, glass_delay=2.0)
    with torch.no_grad():
        far = torch.tensor([5.0])  # the direct return beyond the histogram: the glass alone
        a = ForwardModel(glass, rays).render_plane(normal, far, torch.tensor([1e-9]), ref)
        b = ForwardModel(glass.model_copy(update={"zone_bin_scales": scales}), rays).render_plane(
            normal, far, torch.tensor([1e-9]), ref)
    torch.testing.assert_close(a, b)


def test_integrated_soft_binning_keeps_each_rays_count_and_centroid_at_any_sub_bin_position():
    """Property (hypothesis): the kernel integrated over each bin (``soft_bin_integrated`` 1) sums to 1 over the bins
    for any position and width, and its centroid departs from the position only by the rounding of a Gaussian
    arrival to its bin (Fourier series ``sum_k exp(-2 pi^2 k^2 sigma^2) / (pi k)``: 0.0023 bins at sigma 0.5); the
    Gaussian sampled at the bin centres swings by +-1.4 % in sum and +-0.023 bins in centroid at sigma 0.5."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    n = np.arange(-40.0, 41.0)

    @settings(max_examples=200, deadline=None)
    @given(u=st.floats(-5.0, 5.0), sigma=st.floats(0.2, 3.0))
    def check(u, sigma):
        k = bin_kernel(n - u, sigma, 1.0)
        assert abs(k.sum() - 1.0) < 1e-12
        bound = sum(math.exp(-2.0 * math.pi ** 2 * j * j * sigma * sigma) / (math.pi * j) for j in range(1, 20))
        assert abs((n * k).sum() - u) <= bound + 1e-9

    check()
    sampled = [bin_kernel(n - u, 0.5, 0.0) for u in (0.0, 0.5)]
    assert abs(sampled[0].sum() - sampled[1].sum()) > 0.02
    assert abs((n * bin_kernel(n - 0.25, 0.5, 0.0)).sum() - 0.25) > 0.02


def test_integrated_soft_binning_derivatives_are_exact():
    """The kernel's derivatives in the position and the width match finite differences, and the soft binning's
    backward and forward-mode derivatives (hand written) match autograd's numerical check, for the blend too."""
    t = np.linspace(-4.0, 4.0, 33) + 0.13
    for w in (0.0, 0.6, 1.0):
        _, k_u, k_s = bin_kernel(t, 0.6, w, derivatives=True)
        h = 1e-6
        np.testing.assert_allclose(k_u, -(bin_kernel(t + h, 0.6, w) - bin_kernel(t - h, 0.6, w)) / (2 * h), atol=1e-8)
        np.testing.assert_allclose(k_s, (bin_kernel(t, 0.6 + h, w) - bin_kernel(t, 0.6 - h, w)) / (2 * h), atol=1e-8)
    g = torch.Generator().manual_seed(3)
    amp = torch.rand(1, 9, 5, dtype=torch.float64, generator=g, requires_grad=True)
    u = (torch.rand(1, 9, 5, dtype=torch.float64, generator=g) * 20 + 3).requires_grad_()
    sigma = torch.tensor(0.55, dtype=torch.float64, requires_grad=True)
    bins = torch.arange(30, dtype=torch.float64)
    for w in (0.0, 0.7, 1.0):
        assert torch.autograd.gradcheck(lambda a, x, s: soft_bin(a, x, s, bins, w), (amp, u, sigma),
                                        check_forward_ad=True)


@pytest.mark.parametrize("field, acting", [("soft_bin_integrated", {"soft_bin_integrated": 1.0}),
                                           ("soft_bin_spline", {"soft_bin_spline": 1.0, "soft_bin_sigma": 0.22})])
def test_a_file_without_a_later_soft_binning_renders_the_model_as_it_was(field, acting):
    """Parameters written before version 7 (no ``soft_bin_integrated``) or 8 (no ``soft_bin_spline``) load with 0, the
    Gaussian sampled at the bin centres, and render exactly as before; set, the field moves counts (it acts)."""
    d = ForwardParams(soft_bin_sigma=0.54).to_dict()
    d.pop(field)
    old = ForwardParams.from_dict(d)
    assert getattr(old, field) == 0.0
    normal = torch.tensor([[0.1, -0.05, 1.0]], dtype=torch.float64)
    normal = normal / normal.norm()
    ref = torch.as_tensor(default_reference(), dtype=torch.float64)[None]

    def render(p):
        with torch.no_grad():
            return ForwardModel(p, ZoneRays.stratified(4)).render_plane(normal, torch.tensor([0.12]),
                                                                         torch.tensor([3.0]), ref)

    torch.testing.assert_close(render(old), render(ForwardParams(soft_bin_sigma=0.54)), rtol=0, atol=0)
    assert not torch.allclose(render(old), render(old.replace(**acting)))


def test_spline_soft_binning_keeps_each_rays_count_centroid_and_width_at_any_sub_bin_position():
    """Property (hypothesis): the quadratic B-spline convolved with the Gaussian (``soft_bin_spline`` 1) sums to 1 over
    the bins, keeps its centroid at the ray's position and its variance at 1/4 + sigma^2 for any position and width,
    down to sigma 0.01 (where the sampled Gaussian swings by tens of per cent), in numpy and in torch alike."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    n = np.arange(-40.0, 41.0)

    @settings(max_examples=200, deadline=None)
    @given(u=st.floats(-5.0, 5.0), sigma=st.floats(0.01, 3.0))
    def check(u, sigma):
        k = bin_kernel(n - u, sigma, 0.0, spline=1.0)
        assert abs(k.sum() - 1.0) < 1e-12
        assert abs((n * k).sum() - u) < 1e-10
        assert abs(((n - u) ** 2 * k).sum() - 0.25 - sigma * sigma) < 1e-9
        assert np.all(k >= -1e-12)  # rounding of the third difference (terms up to ~(1.5 + 8 sigma)^2 / 2)
        kt = bin_kernel(torch.as_tensor(n - u), torch.tensor(sigma, dtype=torch.float64), 0.0, spline=1.0)
        np.testing.assert_allclose(kt.numpy(), k, atol=1e-12)

    check()


def test_spline_soft_binning_derivatives_are_exact():
    """The spline kernel's derivatives in the position and the width match finite differences, and the soft binning's
    hand-written backward and forward-mode derivatives match autograd's numerical check."""
    t = np.arange(-6.0, 7.0) + 0.13
    for sigma in (0.05, 0.3, 0.9):
        _, k_u, k_s = bin_kernel(t, sigma, 0.0, derivatives=True, spline=1.0)
        h = 1e-6
        np.testing.assert_allclose(k_u, -(bin_kernel(t + h, sigma, 0.0, spline=1.0)
                                          - bin_kernel(t - h, sigma, 0.0, spline=1.0)) / (2 * h), atol=1e-7)
        np.testing.assert_allclose(k_s, (bin_kernel(t, sigma + h, 0.0, spline=1.0)
                                         - bin_kernel(t, sigma - h, 0.0, spline=1.0)) / (2 * h), atol=1e-7)
    g = torch.Generator().manual_seed(4)
    amp = torch.rand(1, 9, 5, dtype=torch.float64, generator=g, requires_grad=True)
    u = (torch.rand(1, 9, 5, dtype=torch.float64, generator=g) * 20 + 3).requires_grad_()
    sigma = torch.tensor(0.3, dtype=torch.float64, requires_grad=True)
    bins = torch.arange(30, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda a, x, s: soft_bin(a, x, s, bins, 0.0, 1.0), (amp, u, sigma),
                                    check_forward_ad=True)


def test_the_spline_soft_binning_is_a_structural_choice_of_one_soft_binning():
    """``soft_bin_spline`` is 0 or 1 and excludes the integrated soft binning (one line each)."""
    with pytest.raises(CalibrationError, match="soft_bin_spline must be 0 or 1"):
        ForwardParams(soft_bin_spline=0.5)
    with pytest.raises(CalibrationError, match="exclude each other"):
        ForwardParams(soft_bin_spline=1.0, soft_bin_integrated=1.0)


def test_a_file_without_the_ambient_slope_loads_with_a_flat_floor():
    """Parameters written before version 9 (no ``ambient_slope``) load with 0, the flat floor; out of its range it is
    refused."""
    d = ForwardParams(ambient_slope=0.2).to_dict()
    assert d["ambient_slope"] == 0.2
    d.pop("ambient_slope")
    assert ForwardParams.from_dict(d).ambient_slope == 0.0
    with pytest.raises(CalibrationError, match="ambient_slope"):
        ForwardParams.from_dict({**d, "ambient_slope": 2.0})


def test_a_saturation_beyond_any_count_is_refused_when_the_file_is_read():
    """forward.saturation = 1e308 loaded, and then every frame's diff solve failed numerically ("SVD did not
    converge"); a calibration file with it now gives a one-line error naming the field."""
    from place_safe.calibration import Calibration
    from place_safe.exceptions import CalibrationError

    assert ForwardParams(saturation=1e9).saturation == 1e9
    cal = Calibration.from_dict({"format": "place_safe.calibration/1", "forward": {"saturation": 1e308}})
    with pytest.raises(CalibrationError, match="saturation") as e:
        cal.forward()
    assert "\n" not in str(e.value)


def test_the_pileups_written_out_derivatives_are_the_formulas():
    """``apply_pileup``'s derivatives (written out, :class:`_Pileup`, within ``many_tangents`` as in the forward fit's
    Jacobian) in the counts, ``k`` and the shadow blend against autograd through Coates' formula: forward mode, many
    tangents at once (vmap), and reverse mode; integer counts piled up as floats."""
    from torch.func import jvp, vmap

    from place_safe.recovery.tangent_einsum import many_tangents

    with many_tangents():
        _check_pileup_derivatives(jvp, vmap)
    # outside the block it is the formula itself: second order works (within it, torch ends forward mode at a jvp)
    k = torch.tensor(2e-3, dtype=torch.float64)
    h = torch.tensor([[3.0, 5.0, 7.0]], dtype=torch.float64)
    from torch.func import hessian
    torch.testing.assert_close(torch.func.jacfwd(torch.func.jacfwd(lambda c: apply_pileup(h, c).sum()))(k),
                               hessian(lambda c: apply_pileup(h, c).sum())(k))
    assert float(hessian(lambda c: apply_pileup(h, c).sum())(k)) != 0.0


def _check_pileup_derivatives(jvp, vmap):
    """The body of the test above, run within ``many_tangents``."""

    def formula(h, k, s):
        before = torch.cumsum(h, dim=-1) - h
        return -torch.expm1(-k * h) / k * torch.exp(-k * s * before)

    g = torch.Generator().manual_seed(4)
    h = 1000.0 * torch.rand((3, 9, 20), dtype=torch.float64, generator=g)
    k, s = torch.tensor(3e-5, dtype=torch.float64), torch.tensor(0.6, dtype=torch.float64)
    torch.testing.assert_close(apply_pileup(h, k, s), formula(h, k, s), rtol=1e-15, atol=0.0)
    dh = torch.randn((4,) + h.shape, dtype=torch.float64, generator=g)
    dk, ds = 1e-6 * torch.randn(4, dtype=torch.float64, generator=g), torch.randn(4, dtype=torch.float64, generator=g)
    for f_ours, f_theirs in ((apply_pileup, formula),):
        got = vmap(lambda a, b, c: jvp(f_ours, (h, k, s), (a, b, c))[1])(dh, dk, ds)
        want = vmap(lambda a, b, c: jvp(f_theirs, (h, k, s), (a, b, c))[1])(dh, dk, ds)
        torch.testing.assert_close(got, want, rtol=1e-10, atol=1e-10)
    # one input's tangent alone (the others' come as None)
    torch.testing.assert_close(jvp(lambda a: apply_pileup(a, k, s), (h,), (dh[0],))[1],
                               jvp(lambda a: formula(a, k, s), (h,), (dh[0],))[1], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(jvp(lambda b: apply_pileup(h, b, s), (k,), (dk[0],))[1],
                               jvp(lambda b: formula(h, b, s), (k,), (dk[0],))[1], rtol=1e-10, atol=1e-10)
    # reverse mode, and the Coates default (a Python float shadow)
    for shadow in (s, 1.0):
        hr, kr = h.clone().requires_grad_(), k.clone().requires_grad_()
        w = torch.randn(h.shape, dtype=torch.float64, generator=g)
        got = torch.autograd.grad((apply_pileup(hr, kr, shadow) * w).sum(), (hr, kr))
        want = torch.autograd.grad((formula(hr, kr, shadow) * w).sum(), (hr, kr))
        for a, b in zip(got, want):
            torch.testing.assert_close(a, b, rtol=1e-10, atol=1e-12)
    sr = s.clone().requires_grad_()
    w = torch.randn(h.shape, dtype=torch.float64, generator=g)
    torch.testing.assert_close(torch.autograd.grad((apply_pileup(h, k, sr) * w).sum(), sr)[0],
                               torch.autograd.grad((formula(h, k, sr) * w).sum(), sr)[0], rtol=1e-10, atol=1e-12)
    counts = torch.tensor([[5, 5, 5]])
    torch.testing.assert_close(apply_pileup(counts, torch.tensor(0.1, dtype=torch.float64)),
                               formula(counts.double(), torch.tensor(0.1, dtype=torch.float64), 1.0))
