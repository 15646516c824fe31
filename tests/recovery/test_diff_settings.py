"""What a calibration's ``diff`` section states, and the solver's options (``recovery.diff_settings``): the range
correction's series and bounds, the options' checks, and that neither needs torch."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from place_safe.recovery.diff_settings import SolverOptions


def test_the_settings_load_without_torch_and_are_the_solvers():
    """The module reads and checks a ``diff`` section without importing torch (a peak-only run never loads it), and
    ``recovery.differentiable`` names the same classes."""
    code = ("import sys; from place_safe.recovery.diff_settings import RangeCorrection, SolverOptions; "
            "RangeCorrection.from_dict({'coeffs': [0.001], 'domain': [0.02, 0.4]}); SolverOptions(rays=4); "
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300)
    assert out.stdout.strip() == "False", out.stderr
    from place_safe.recovery import diff_settings, differentiable

    assert differentiable.RangeCorrection is diff_settings.RangeCorrection
    assert differentiable.SolverOptions is diff_settings.SolverOptions


def test_range_correction_series_in_inverse_range():
    """A series named in ``inverse`` is a Chebyshev series in 1 / z0 over the domain (hi -> -1, lo -> +1);
    the others stay in z0; files without ``inverse`` read as before; a name that is no series, or an inverse
    series on a domain reaching 0, is refused."""
    from place_safe.exceptions import CalibrationError
    from place_safe.recovery.diff_settings import RangeCorrection, range_argument

    lo, hi = 0.05, 0.40
    c = RangeCorrection(coeffs=[0.0, 0.001], domain=[lo, hi], slope_b=[0.0, 0.01], inverse=["slope_b"])
    for z in (0.05, 0.1, 0.2, 0.4):
        u = 2.0 * (1.0 / z - 1.0 / hi) / (1.0 / lo - 1.0 / hi) - 1.0
        assert c.slopes(z)[1] == pytest.approx(0.01 * u)
        assert c(z) == pytest.approx(0.001 * (2.0 * (z - lo) / (hi - lo) - 1.0))
        assert range_argument(z, [lo, hi], True) == pytest.approx(u)
    assert c.slopes(0.01) == c.slopes(lo) and c.slopes(1.0) == c.slopes(hi)  # outside: the nearer end
    assert np.allclose(range_argument(np.array([0.05, 0.4]), [lo, hi], True), [1.0, -1.0])
    assert RangeCorrection.from_dict(c.to_dict()) == c
    assert RangeCorrection.from_dict({"coeffs": [0.001], "domain": [0.0, 1.0]}).inverse == []
    with pytest.raises(CalibrationError):
        RangeCorrection.from_dict({**c.to_dict(), "inverse": ["albedo"]})  # the albedo series is in ln z0
    with pytest.raises(CalibrationError):
        RangeCorrection(domain=[0.0, 1.0], slope_a=[0.001], inverse=["slope_a"])


@pytest.mark.parametrize("name", ["coeffs", "slope_a", "slope_b", "gain_a", "gain_b", "albedo"])
def test_a_range_correction_series_stays_within_its_fields_range_at_every_z0(name):
    """Property (hypothesis): a correction series read from a file is within its field's range wherever it is
    evaluated, not only coefficient by coefficient: 400 coefficients of 5 cm each summed to a plane moved by 20 m, and
    an albedo series of 300 x 3 overflowed ``exp`` and cost every plane ("numerical failure: math range error").
    A series that could leave the range is refused with one line naming it."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from place_safe.config import field_interval
    from place_safe.exceptions import CalibrationError
    from place_safe.recovery.diff_settings import RangeCorrection

    lo, hi = field_interval(RangeCorrection, name)
    bound = max(abs(lo), abs(hi))
    inverse = [name] if name != "albedo" else []

    @settings(max_examples=150, deadline=None)
    @given(coeffs=st.lists(st.floats(lo, hi), max_size=40), z0=st.floats(1e-4, 20.0), width=st.floats(1e-3, 1.0))
    def check(coeffs, z0, width):
        try:
            c = RangeCorrection(domain=[0.01, 0.01 + width], inverse=inverse, **{name: coeffs})
        except CalibrationError as exc:
            assert name in str(exc) and "\n" not in str(exc)
            return
        value = {"coeffs": c(z0), "albedo": c.log_albedo(z0)}.get(name)
        if value is None:
            a, b = c.slopes(z0, 1.0, 1.0)
            value = a if name.endswith("_a") else b
        assert abs(value) <= bound * (1 + 1e-9)

    check()
    with pytest.raises(CalibrationError, match=name):
        RangeCorrection.from_dict({"domain": [0.0, 0.01], name: [hi] * 400})


def test_range_correction_of_arrays_is_that_of_each_element():
    """The correction evaluated on arrays of planes (the covariance's moved points at once) is, element by element,
    the correction of each plane alone."""
    from place_safe.recovery.diff_settings import RangeCorrection

    c = RangeCorrection(coeffs=[0.0, 0.001, -0.0005], domain=[0.02, 0.4], slope_a=[0.002, 0.001],
                        gain_b=[0.01, -0.005], inverse=["coeffs"])
    z0, a, b = np.array([0.01, 0.05, 0.2, 0.5]), np.array([0.1, -0.2, 0.0, 0.3]), np.array([0.0, 0.1, -0.3, 0.2])
    da, db = c.slopes(z0, a, b)
    for i in range(len(z0)):
        assert c(float(z0[i])) == c(z0)[i]
        assert c.slopes(float(z0[i]), float(a[i]), float(b[i])) == (da[i], db[i])


@pytest.mark.parametrize("option, value, match", [
    ("rays", 0, "rays must be a whole number in 1..64"),
    ("rays", 10_000, "rays must be a whole number in 1..64"),
    ("rays", 6.0, "rays must be a whole number"),
    ("max_iterations", True, "max_iterations must be a whole number"),
    ("window_after_peak", 200, "window_after_peak must be a whole number in 1..128"),
    ("zone_albedo_spread", 0.0, "zone_albedo_spread must be a number above 0"),
    ("tolerance", math.inf, "tolerance must be a number above 0"),
    ("chi2_tolerance", math.nan, "chi2_tolerance must be a number above 0"),
    ("paper_lr", "0.01", "paper_lr must be a number above 0"),
    ("ambient", 1, "ambient must be true or false"),
    ("crosstalk_std", -0.01, "crosstalk_std must be 0 .held. or a number in 1e-06..0.5"),
    ("crosstalk_std", math.nan, "crosstalk_std must be 0"),
    ("crosstalk_std", True, "crosstalk_std must be 0"),
    ("crosstalk_std", 1e-300, "crosstalk_std must be 0"),  # its prior's row would overflow the normal equations
])
def test_solver_options_the_solver_cannot_run_with_are_refused_by_name(option, value, match):
    """A zero ray grid, a spread of 0 (every frame "SVD did not converge") or a 10000 x 10000 grid (a solve that never
    ends) fail when the options are made, naming the option."""
    with pytest.raises(ValueError, match=match):
        SolverOptions(**{option: value})
    assert SolverOptions(zone_albedo_spread=math.inf).zone_albedo_spread == math.inf  # untied: allowed
