"""Property-based tests of every estimator on bad data: ``Estimator.estimate`` never raises, and what
it returns is either no plane with a reason, or a finite plane in front of the sensor (unit normal,
``n_z > 0``, ``offset > 0``). Frames are built directly (not from files) so the estimators see
what library callers can hand them: strings, objects, ragged and complex arrays, NaN, saturation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from place_safe.recovery import METHODS, make_estimator
from place_safe.config import field_range
from place_safe.recovery.forward import ForwardParams
from place_safe.recovery.points import PeakParams
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame
from place_safe.sensor.histogram import COUNT_MAX
from estimates import assert_safe

ESTIMATORS = {m: make_estimator(m) for m in METHODS}
FAST = [m for m in METHODS if m != "diff"]


@pytest.fixture(scope="module")
def base(synthetic_frames) -> Frame:
    return synthetic_frames[0]


floats = st.floats(allow_nan=True, allow_infinity=True, width=64)
counts = st.one_of(
    hnp.arrays(np.float64, (N_ZONES, N_BINS), elements=floats),
    hnp.arrays(np.float64, (N_ZONES, N_BINS), elements=st.floats(0, 2 * COUNT_MAX)),
    hnp.arrays(np.int64, (N_ZONES, N_BINS), elements=st.integers(-10, COUNT_MAX)),
    st.just(np.zeros((N_ZONES, N_BINS))),
    st.just(np.full((N_ZONES, N_BINS), float(COUNT_MAX))),
    st.just(np.zeros((N_ZONES, N_BINS), dtype=complex) + 1j),
    st.just(np.array([[object()] * N_BINS] * N_ZONES)),
    st.just("hists"),
    st.just([["12"] * N_BINS] * N_ZONES),
    st.just([[1.0, 2.0], [3.0]]),
    st.just(None),
    hnp.arrays(np.float64, hnp.array_shapes(max_dims=3, max_side=12), elements=st.floats(0, 100)),
)
references = st.one_of(
    st.none(),
    hnp.arrays(np.float64, (N_BINS,), elements=st.floats(0, 1e5)),
    hnp.arrays(np.float64, (N_BINS,), elements=floats),
    st.just(np.zeros(N_BINS)),
    st.just(np.zeros(N_BINS, dtype=complex)),
    st.just("ref"),
)
distances = st.one_of(
    st.none(),
    hnp.arrays(np.float64, (N_ZONES,), elements=floats),
    hnp.arrays(np.float64, (N_ZONES,), elements=st.floats(0, 2)),
    st.just(np.full(N_ZONES, 0.1, dtype=complex)),
    st.just(["0.1"] * N_ZONES),
    st.just([[0.1], [0.2, 0.3]]),
)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(method=st.sampled_from(FAST), hists=counts, reference=references, dist=distances,
       conf=st.one_of(st.none(), hnp.arrays(np.float64, (N_ZONES,), elements=floats)))
def test_fast_estimators_never_raise_on_bad_frames(method, hists, reference, dist, conf):
    assert_safe(ESTIMATORS[method].estimate(Frame(hists, reference, dist, conf)))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(hists=counts, reference=references)
def test_diff_never_raises_on_bad_frames(hists, reference):
    est = ESTIMATORS["diff"]
    frame = Frame(hists, reference)
    assert_safe(est.estimate(frame))
    for e in est.estimate_many([frame, frame]):
        assert_safe(e)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(hists=counts, reference=references, std=st.sampled_from([1e-6, 1e-3, 0.05, 0.5]),
       crosstalk=st.sampled_from([0.0, 0.01, 0.5]))
def test_diff_with_each_frames_own_crosstalk_never_raises_on_bad_frames(hists, reference, std, crosstalk):
    """The frame's crosstalk solved with the plane (SolverOptions.crosstalk_std, from its smallest allowed prior to its
    widest, about a crosstalk from none to the bound): bad frames still get a safe estimate or a reason."""
    from dataclasses import replace

    from place_safe.recovery.differentiable import DifferentiableEstimator, SolverOptions
    from place_safe.recovery.forward import ForwardParams

    est = DifferentiableEstimator(ForwardParams(crosstalk=crosstalk), options=replace(SolverOptions(), crosstalk_std=std))
    frame = Frame(hists, reference)
    for e in est.estimate_many([frame, frame]):
        assert_safe(e)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(method=st.sampled_from(METHODS), scale=st.floats(1e-3, 1e3), zone=st.integers(0, N_ZONES - 1),
       value=st.sampled_from([0.0, float(COUNT_MAX), 1e9, np.nan]))
def test_perturbed_real_frames_are_safe(base, method, scale, zone, value):
    """A good frame scaled, with one zone blanked, clipped or poisoned: never a NaN plane or one behind the sensor."""
    h = np.array(base.hists, dtype=float) * scale
    h[zone] = value
    assert_safe(ESTIMATORS[method].estimate(Frame(h, base.reference, base.distances, base.confidences)))


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(scale=st.floats(1e-3, 1e3), zones=st.lists(st.integers(0, N_ZONES - 1), min_size=1, max_size=6, unique=True),
       value=st.sampled_from([0.0, float(COUNT_MAX), 1e9, np.nan]), std=st.sampled_from([1e-6, 0.005, 0.5]))
def test_perturbed_frames_with_each_frames_own_crosstalk_are_safe(base, scale, zones, value, std):
    """A good frame scaled, with up to six zones blanked, clipped or poisoned, read with the frame's crosstalk solved (it
    may run to its bounds where the zones that show it are gone): never a NaN plane or one behind the sensor."""
    from dataclasses import replace

    from place_safe.recovery.differentiable import DifferentiableEstimator, SolverOptions
    from place_safe.recovery.forward import ForwardParams

    h = np.array(base.hists, dtype=float) * scale
    h[zones] = value
    est = DifferentiableEstimator(ForwardParams(crosstalk=0.01), options=replace(SolverOptions(), crosstalk_std=std))
    assert_safe(est.estimate(Frame(h, base.reference, base.distances, base.confidences)))


def test_non_frames_get_a_reason():
    for est in ESTIMATORS.values():
        for thing in (None, "frame", 3, {"hists": []}):
            e = est.estimate(thing)
            assert e.plane is None and "expected a Frame" in e.reason


@pytest.mark.parametrize("name, reference", [
    ("all zeros", np.zeros(N_BINS)),
    ("below the floor", np.full(N_BINS, 40.0)),
    ("peak in the first bin", np.r_[5000.0, np.full(N_BINS - 1, 30.0)]),
    ("peak in the last bin", np.r_[np.full(N_BINS - 1, 30.0), 5000.0]),
    ("saturated", np.r_[np.full(14, 30.0), float(COUNT_MAX), np.full(N_BINS - 15, 30.0)]),
])
def test_diff_refuses_an_invalid_reference(base, name, reference):
    est = ESTIMATORS["diff"]
    frame = Frame(base.hists, reference, base.distances, base.confidences, truth=base.truth)
    for e in (est.estimate(frame), est.estimate_many([frame, base])[0]):
        assert e.plane is None and "reference histogram" in e.reason


def test_complex_counts_never_give_a_plane(base):
    for method, est in ESTIMATORS.items():
        f = Frame(np.asarray(base.hists) + 0j, np.asarray(base.reference) + 0j,
                  np.asarray(base.distances) + 0j, base.confidences)
        e = est.estimate(f)
        assert e.plane is None, method


# -- any accepted parameter set: the ranges ForwardParams / PeakParams declare keep every estimator safe -----
def _in(b, integer=False):
    lo = max(b.lo, -1e6)
    hi = min(b.hi, 1e6)
    if integer:
        return st.integers(int(lo) + (1 if b.lo_open else 0), min(int(hi), 4096))
    return st.floats(lo, hi, exclude_min=b.lo_open, exclude_max=b.hi_open, allow_nan=False)


def _params_strategy(model, required=()):
    fields = {}
    for name in model.model_fields:
        b = field_range(model, name)
        if not (math.isfinite(b.lo) or math.isfinite(b.hi)):
            continue  # a field without a range (the sub-bin estimator's name)
        if b.min_length is not None and b.min_length == b.max_length:
            fields[name] = st.lists(_in(b), min_size=b.min_length, max_size=b.max_length)
        elif name in ("residual_coeffs", "phase_coeffs", "coeffs", "slope_a", "slope_b"):
            fields[name] = st.lists(_in(b), max_size=6).map(lambda v: v[: len(v) // 2 * 2])
        else:
            fields[name] = _in(b, integer=name == "rays_per_zone")
    req = {k: fields.pop(k) for k in required}
    return st.fixed_dictionaries(req, optional=fields)


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(d=_params_strategy(ForwardParams))
def test_diff_is_safe_for_any_accepted_forward_parameters(synthetic_frames, d):
    from place_safe.exceptions import CalibrationError
    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.recovery.forward import ForwardParams

    try:
        params = ForwardParams.from_dict(d)
    except CalibrationError:
        return  # e.g. a cross-field rule; the ranges themselves are what is exercised
    for e in DifferentiableEstimator(params).estimate_many(synthetic_frames[:2]):
        assert_safe(e)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(d=_params_strategy(PeakParams, required=("m", "b")))
def test_point_methods_are_safe_for_any_accepted_parameters(synthetic_frames, d):
    from place_safe.exceptions import CalibrationError
    from place_safe.recovery.peak import PeakEstimator
    from place_safe.recovery.points import PeakParams
    from place_safe.recovery.proprietary import ProprietaryEstimator

    try:
        params = PeakParams.from_dict(d)
    except CalibrationError:
        return  # residual_domain with lo >= hi
    for est in (PeakEstimator(params), ProprietaryEstimator(params)):
        for f in synthetic_frames[:3]:
            assert_safe(est.estimate(f))


@pytest.mark.parametrize("args, kwargs, kind", [
    (("foo",), {}, "ConfigError"),
    (("PEAK",), {}, "ConfigError"),
    (("peak",), {"foo": 1}, "ArgumentTypeError"),
    (("diff",), {"mode": "x"}, "ConfigError"),
    ((None,), {}, "ArgumentTypeError"),
])
def test_make_estimator_refuses_a_method_or_option_in_one_line_of_the_packages_kind(args, kwargs, kind):
    """A task script's mistake in the method or an option is one line of place_safe's own errors (a plain ValueError
    or TypeError before: an adversarial round, session 74), still a ValueError or a TypeError for older callers."""
    from place_safe.exceptions import PlaceSafeError

    with pytest.raises(PlaceSafeError) as info:
        make_estimator(*args, **kwargs)
    assert type(info.value).__name__ == kind and "\n" not in str(info.value)
    assert isinstance(info.value, ValueError if kind == "ConfigError" else TypeError)
