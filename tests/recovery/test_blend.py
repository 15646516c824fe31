"""Two planes blended by their tilt variances (place_safe.recovery.blend)."""

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from place_safe.geometry import Plane
from place_safe.recovery.blend import axis_state, blend_weights, blended
from place_safe.recovery.estimator import PlaneEstimate


def _axis(plane):
    """``(n_x, n_y, z0)``: the state the blend combines."""
    return axis_state(plane)[0]


def _est(tilt, azimuth, offset, cov, method="x"):
    return PlaneEstimate(Plane.from_angles(tilt, azimuth, offset), albedo=0.5, residual=1.2,
                         covariance=np.asarray(cov, dtype=float), method_used=method)


def test_the_plane_that_reads_the_slope_better_counts_more_in_the_tilt_the_other_in_the_offset():
    """Equal variances: the midpoint of the two states (n_x, n_y, z0); a tilt variance 3 times the other's: weight 1/4
    on its tilt, while the axis crossing follows the offset variances (here 1/5 on the other's). The albedo and residual
    are the first estimate's, the method the name given."""
    a = _est(0.02, 0.0, 0.10, np.diag([1e-6, 1e-6, 1e-8]), "diff")
    b = _est(0.04, 0.0, 0.12, np.diag([1e-6, 1e-6, 1e-8]), "peak")
    m = blended(a, b, "diff+peak")
    assert blend_weights(a, b) == pytest.approx((0.5, 0.5))
    assert _axis(m.plane) == pytest.approx(0.5 * (_axis(a.plane) + _axis(b.plane)), abs=1e-12)
    assert (m.albedo, m.residual, m.method_used) == (0.5, 1.2, "diff+peak")
    assert abs(float(np.linalg.norm(m.plane.normal)) - 1.0) < 1e-12 and m.plane.normal[2] > 0
    worse = _est(0.02, 0.0, 0.10, np.diag([3e-6, 3e-6, 4e-8]))
    assert blend_weights(worse, b) == pytest.approx((0.25, 0.2))
    mixed = blended(worse, b, "m")
    assert _axis(mixed.plane)[:2] == pytest.approx(0.25 * _axis(worse.plane)[:2] + 0.75 * _axis(b.plane)[:2], abs=1e-12)
    assert mixed.plane.z0 == pytest.approx(0.2 * worse.plane.z0 + 0.8 * b.plane.z0, rel=1e-12)


def test_edges_return_one_estimate_and_missing_covariances_no_blend():
    a = _est(0.02, 0.0, 0.10, np.diag([1e-6, 1e-6, 1e-8]), "diff")
    sure = _est(0.04, 0.0, 0.12, np.diag([1e-30, 1e-30, 1e-30]), "peak")  # known exactly: all its weight
    out = blended(a, sure, "diff+peak")
    assert out.plane is sure.plane and out.covariance is sure.covariance and out.method_used == "peak"
    assert blended(sure, a, "peak+diff") is sure
    # its tilt known exactly, the offsets alike: the tilt is its, the axis crossing the mean, the offset's variance
    # bounded
    tilt_known = _est(0.04, 0.0, 0.12, np.diag([1e-14, 1e-14, 1e-8]), "peak")
    out = blended(a, tilt_known, "diff+peak")
    assert out.plane.normal == pytest.approx(tilt_known.plane.normal, abs=1e-9)
    assert out.plane.z0 == pytest.approx(0.5 * (a.plane.z0 + tilt_known.plane.z0), rel=1e-12)
    assert 0.25e-8 < out.covariance[2, 2] <= 1.5e-8  # (0.5 * 1e-4 + 0.5 * 1e-4)^2 = 1e-8 at perfect correlation
    bare = PlaneEstimate(a.plane, covariance=None)
    assert blended(a, bare, "m") is None and blended(bare, a, "m") is None
    assert blended(a, PlaneEstimate(None, reason="no return"), "m") is None
    zero = _est(0.0, 0.0, 0.1, np.zeros((3, 3)))
    assert blend_weights(zero, zero) is None and blended(zero, zero, "m") is None
    # the tilt all one's, the offset all the other's: a blend still, with a covariance over both
    tilt_sure = _est(0.02, 0.0, 0.10, np.diag([1e-16, 1e-16, 1.0]))
    off_sure = _est(0.04, 0.0, 0.12, np.diag([1e-6, 1e-6, 1e-16]))
    # (variances 1e-30 apart from 1e-11 are below rounding once carried to (n_x, n_y, z0) and back: no blend then, or
    # a covariance; never one that is not)
    extreme = blended(_est(0.02, 0.0, 0.10, np.diag([1e-30, 1e-30, 1.0])),
                      _est(0.04, 0.0, 0.12, np.diag([1e-6, 1e-6, 1e-30])), "m")
    assert extreme is None or np.all(np.linalg.eigvalsh(extreme.covariance) > 0)
    out = blended(tilt_sure, off_sure, "m")
    assert out.method_used == "m" and out.plane.z0 == pytest.approx(off_sure.plane.z0)
    assert out.plane.normal == pytest.approx(tilt_sure.plane.normal) and np.all(np.isfinite(out.covariance))


@settings(max_examples=300, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), rho=st.floats(-1.0, 1.0), scale_b=st.floats(1e-3, 1e3),
       tilts=st.sampled_from([(0.01, 0.02), (0.6, 0.9), (1.2, 1.35)]))
@example(seed=311, rho=1.0, scale_b=11.0, tilts=(0.01, 0.02))  # CI's counterexample to a model without the Jacobians
def test_the_blends_covariance_holds_whatever_the_two_errors_correlation(seed, rho, scale_b, tilts):
    """Property: for any covariances C_a, C_b and any joint covariance of the two errors with them as marginals
    (cross term C_a^1/2 K C_b^1/2 with K a contraction), the blend's stated covariance is at least the covariance
    of its error: ``W J_a e_a + (I - W) J_b e_b`` in ``(n_x, n_y, z0)``, where the blend combines the planes (``J``
    each plane's Jacobian there), carried back to ``(n_x, n_y, d)`` at the blended plane. The stated one never claims
    more than the planes give. (With perfectly correlated errors the bound is tight in one direction, so a model of
    the error that leaves out the Jacobians is off by more than the rounding there: seed 311.) Planes near level and
    steep ones (0.6-1.35 rad), where the Jacobians differ from the identity."""
    rng = np.random.default_rng(seed)

    def spd(scale):
        m = rng.normal(size=(3, 3))
        return scale * (m @ m.T + 0.05 * np.eye(3))

    ca, cb = spd(1e-6), spd(1e-6 * scale_b)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    k = rho * q  # a contraction: singular values |rho| <= 1
    la, lb = np.linalg.cholesky(ca), np.linalg.cholesky(cb)
    cab = la @ k @ lb.T
    a = PlaneEstimate(Plane.from_angles(tilts[0], 0.2, 0.1), covariance=ca)  # near level, or steep: the Jacobians
    b = PlaneEstimate(Plane.from_angles(tilts[1], 0.3, 0.1), covariance=cb)  # of the axis crossing then matter
    m = blended(a, b, "m")
    w, wd = blend_weights(a, b)
    if m is None or m is a or m.method_used != "m":
        return  # an edge: one estimate unchanged
    ja, jb = axis_state(a.plane)[1], axis_state(b.plane)[1]
    ua, ub = np.diag([w, w, wd]) @ ja, (np.eye(3) - np.diag([w, w, wd])) @ jb
    back = np.linalg.inv(axis_state(m.plane)[1])
    true = back @ (ua @ ca @ ua.T + ub @ cb @ ub.T + ua @ cab @ ub.T + ub @ cab.T @ ua.T) @ back.T
    gap = np.linalg.eigvalsh(m.covariance - true)
    assert gap.min() >= -1e-9 * np.abs(m.covariance).max()


def test_perfectly_correlated_scalar_errors_are_bounded_exactly():
    """Convention check: with both covariances proportional to one matrix the bound is (w s_a + (1 - w) s_b)^2 in
    that direction, the variance of the blend of perfectly correlated errors (level planes: there (n_x, n_y, z0) and
    (n_x, n_y, d) are the same coordinates)."""
    base = np.diag([1e-6, 2e-6, 1e-8])
    a = PlaneEstimate(Plane.from_angles(0.0, 0.0, 0.1), covariance=base)
    b = PlaneEstimate(Plane.from_angles(0.0, 0.0, 0.12), covariance=4.0 * base)
    m = blended(a, b, "m")
    w, wd = blend_weights(a, b)
    assert w == pytest.approx(0.8) and wd == pytest.approx(0.8)
    assert m.covariance == pytest.approx((w * 1.0 + (1 - w) * 2.0) ** 2 * base, rel=1e-9)
    assert float(m.plane.offset) == pytest.approx(0.8 * a.plane.offset + 0.2 * b.plane.offset, rel=1e-12)


def test_a_matrix_that_is_no_covariance_is_not_blended():
    """A covariance with a negative or NaN eigenvalue (a broken estimate), on either side, gives no blend (the caller
    then returns one plane whole), never a blended covariance that is indefinite or claims a zero variance."""
    a = _est(0.02, 0.0, 0.10, np.diag([1e-6, 1e-6, 1e-8]), "diff")
    for bad in ([[1e-6, 0, 5e-6], [0, 1e-6, 0], [5e-6, 0, 1e-8]], np.diag([-1e-6, 1e-6, 1e-8]),
                np.diag([np.nan, 1e-6, 1e-8]), np.zeros((2, 2))):
        b = PlaneEstimate(Plane.from_angles(0.03, 0.0, 0.11), covariance=np.asarray(bad, dtype=float))
        assert blended(a, b, "m") is None and blended(b, a, "m") is None


def test_diff_blends_nothing_closer_than_the_near_fallback_range_even_without_a_limit():
    """A calibration that blends but has no chi-square limit (none could be chosen, or a hand-edited file) still
    returns peak's plane closer than NEAR_FALLBACK_RANGE."""
    from place_safe.recovery.diff_settings import NEAR_FALLBACK_RANGE
    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.recovery.estimator import Uncertainty

    est = DifferentiableEstimator(uncertainty=Uncertainty(blend=True))
    d = _est(0.02, 0.0, 0.03, np.diag([1e-6, 1e-6, 1e-8]), "diff")
    p = _est(0.021, 0.0, 0.03, np.diag([1e-6, 1e-6, 1e-8]), "peak")
    assert p.plane.offset < NEAR_FALLBACK_RANGE
    out = est._checked(d, p)
    assert out.method_used == "peak" and out.plane is p.plane
    far_d = _est(0.02, 0.0, 0.2, np.diag([1e-6, 1e-6, 1e-8]), "diff")
    far_p = _est(0.021, 0.0, 0.2, np.diag([1e-6, 1e-6, 1e-8]), "peak")
    assert est._checked(far_d, far_p).method_used == "diff+peak"


def test_the_blend_keeps_the_axis_crossing_of_two_planes_that_agree_on_it_however_they_tilt():
    """Two steep planes that meet the optical axis at the same point but disagree in tilt: the blend meets it there
    too (a blend of d would not: d moves by about z0 sin(tilt) times the tilt's difference), and its stated covariance,
    carried back to (n_x, n_y, d), is a covariance whose offset part grows with that tilt."""
    a = _est(0.45, 0.3, 0.15, np.diag([1e-6, 1e-6, 1e-8]), "diff")
    steeper = Plane.from_angles(0.46, 0.3, 0.15)  # 0.01 rad steeper, the same z0
    b = PlaneEstimate(Plane(steeper.normal, a.plane.z0 * steeper.normal[2]), covariance=np.diag([1e-6, 1e-6, 4e-8]))
    assert b.plane.z0 == pytest.approx(a.plane.z0, rel=1e-12)
    m = blended(a, b, "m")
    assert m.plane.z0 == pytest.approx(a.plane.z0, rel=1e-12)
    assert a.plane.offset < m.plane.offset < b.plane.offset or b.plane.offset < m.plane.offset < a.plane.offset
    assert np.all(np.linalg.eigvalsh(m.covariance) > 0)
