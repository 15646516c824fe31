"""PlaneEstimate's file form and the Uncertainty settings (covariance floor, chi-square limit)."""

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.calibration import Calibration
from place_safe.exceptions import CalibrationError
from place_safe.geometry import Plane
from place_safe.recovery.estimator import PlaneEstimate, Uncertainty
from place_safe.recovery.points import plane_covariance


def test_jsonl_line_keeps_the_interface_keys_and_adds_extras():
    cov = np.diag([1e-6, 2e-6, 3e-8])
    e = PlaneEstimate(Plane(np.array([0, 0, 1.0]), 0.1), albedo=1.0, seconds=0.002, covariance=cov,
                      method_used="peak")
    line = e.to_json(3)
    assert list(line)[:5] == ["index", "normal", "offset", "albedo", "ms"]
    assert line["method_used"] == "peak"
    assert np.allclose(line["covariance"], cov)
    json.dumps(line)
    assert "covariance" not in PlaneEstimate(None, reason="no return").to_json(0)


def test_uncertainty_round_trip_and_defaults():
    u = Uncertainty(tilt_std=0.001, offset_std=1e-4, chi2_limit=4.0, tilt_range_std=1e-4, offset_rel=0.001, scale=1.2)
    assert Uncertainty.from_dict(json.loads(json.dumps(u.to_dict()))) == u
    assert Uncertainty.from_dict({"chi2_limit": None}).chi2_limit == math.inf
    c = Uncertainty(consistency_limit=16.27)
    assert Uncertainty.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    assert Uncertainty.from_dict({"consistency_limit": None}).consistency_limit == math.inf
    with pytest.raises(ValueError):
        Uncertainty(consistency_limit=0.0)
    assert Uncertainty.from_dict({"chi2_limit": 0.0}).chi2_limit == 0.0  # diff always falls back
    with pytest.raises(ValueError):
        Uncertainty(chi2_limit=-1.0)
    with pytest.raises(ValueError):
        Uncertainty(chi2_limit=math.nan)
    assert np.all(Uncertainty().apply(np.eye(3), 0.1) == np.eye(3))  # defaults add nothing
    with pytest.raises(ValueError):
        Uncertainty(tilt_std=-1.0)
    with pytest.raises(ValueError):
        Uncertainty.from_dict({"tilt": 1.0})


def test_calibration_files_keep_their_uncertainty_sections_byte_for_byte():
    """Every shipped calibration's uncertainty sections load and write back exactly (null limits, left-out keys)."""
    from place_safe.assets import sim_sensors_dir

    files = sorted(sim_sensors_dir().glob("calibration*.json"))
    sections = [s for f in files for s in json.loads(f.read_text())["uncertainty"].values()]
    assert sections
    for sec in sections:
        assert json.dumps(Uncertainty.from_dict(sec).to_dict(), indent=2) == json.dumps(sec, indent=2)


@pytest.mark.parametrize("bad, words", [
    ({"tilt": 1.0}, "uncertainty: tilt: unknown key"),
    ({"scale": 0}, "uncertainty: scale: Input should be greater than or equal to 0.1"),  # MIN_SCALE
    ({"chi2_limit": -1.0}, "uncertainty: chi2_limit: Input should be greater than or equal to 0"),
    ({"tilt_std": "0.1"}, "uncertainty: tilt_std: Input should be a valid number"),
    ({"near_depths": [0.1, 0.2], "near_range_std": [0.01]}, "uncertainty: near_depths and near_range_std need"),
    ({"near_depths": [0.2, 0.1], "near_range_std": [0.01, 0.0]}, "uncertainty: near_depths must increase"),
    ({"near_depths": [0.1, 0.2], "near_range_std": [0.01, 0.06]}, "uncertainty: near_range_std.1: Input should be "
                                                                  "less than or equal to 0.05"),
    ([0.1], "uncertainty must be a JSON object, got a list"),
])
def test_uncertainty_errors_are_one_line_naming_the_field(bad, words):
    with pytest.raises(CalibrationError) as exc:
        Uncertainty.from_dict(bad)
    assert str(exc.value).startswith(words) and "\n" not in str(exc.value)


@pytest.mark.parametrize("name", ["tilt_std", "offset_std", "tilt_range_std", "offset_rel", "scale"])
def test_an_uncertainty_that_loads_gives_a_finite_covariance(name):
    """Property (hypothesis): a floor or scale a file may hold keeps every covariance finite. ``tilt_std`` 1e308 in a
    calibration overflowed squaring it and cost every plane of peak and diff ("numerical failure: (34, 'Numerical
    result out of range')"); such a value is refused when the file is read, with one line naming the field."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=100, deadline=None)
    @given(value=st.floats(1e-12, 1e308), offset=st.floats(1e-3, 10.0), tilt=st.floats(0.0, 1.5))
    def check(value, offset, tilt):
        try:
            u = Uncertainty.from_dict({name: value})
        except CalibrationError as exc:
            assert str(exc).startswith(f"uncertainty: {name}:") and "\n" not in str(exc)
            return
        n = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
        assert np.all(np.isfinite(u.apply(np.eye(3) * 1e-6, offset, n)))

    check()
    with pytest.raises(CalibrationError, match=name):
        Uncertainty.from_dict({name: 1e308})


def test_tilt_term_and_preference_round_trip_and_default_to_none():
    u = Uncertainty(tilt_rel=0.05, prefer_ratio=2.0)
    assert Uncertainty.from_dict(json.loads(json.dumps(u.to_dict()))) == u
    old = Uncertainty().to_dict()
    assert "tilt_rel" not in old and "prefer_ratio" not in old  # files older versions read
    assert Uncertainty.from_dict({}).tilt_rel == 0.0 and Uncertainty.from_dict({"prefer_ratio": None}).prefer_ratio == math.inf
    for bad in ({"tilt_rel": -0.1}, {"tilt_rel": 2.0}, {"prefer_ratio": 0.0}, {"tilt_rel": math.nan}):
        with pytest.raises(ValueError):
            Uncertainty(**bad)


def test_blend_round_trips_is_left_out_when_off_and_goes_with_the_fallback():
    """``blend`` is written when on, left out when off (files older versions read, which never blended), refused
    unless true or false, and off in the copy that measures diff's own plane."""
    u = Uncertainty(chi2_limit=3.0, blend=True)
    assert u.to_dict()["blend"] is True and Uncertainty.from_dict(json.loads(json.dumps(u.to_dict()))) == u
    assert "blend" not in Uncertainty().to_dict() and Uncertainty.from_dict({}).blend is False
    assert u.without_fallback().blend is False and u.without_fallback().chi2_limit == math.inf
    for bad in (1, "yes", None):
        with pytest.raises(ValueError):
            Uncertainty.from_dict({"blend": bad})


def test_tilt_term_is_zero_level_and_turns_the_plane_about_its_axis_crossing():
    u = Uncertainty(tilt_rel=0.05)
    level = np.array([0.0, 0.0, 1.0])
    assert np.all(u.tilt_floor(level, 0.2) == 0.0)
    assert np.all(u.apply(np.eye(3) * 1e-8, 0.2, level) == u.apply(np.eye(3) * 1e-8, 0.2))
    t = math.radians(20.0)
    n = np.array([math.sin(t), 0.0, math.cos(t)])
    c = u.tilt_floor(n, 0.2)
    assert c[0, 0] == pytest.approx((0.05 * math.tan(t)) ** 2) and c[1, 1] == pytest.approx(c[0, 0])
    # turning about (0, 0, z0): d = z0 n_z moves by -z0 n_x dn_x / n_z
    z0 = 0.2 / math.cos(t)
    assert c[2, 2] == pytest.approx(c[0, 0] * (z0 * math.tan(t)) ** 2)
    assert c[0, 2] == pytest.approx(-c[0, 0] * z0 * math.tan(t))


def test_tilt_pivot_and_offset_term():
    """Pivot 0: the plane turns about the sensor (d does not follow the tilt); the offset term is independent."""
    t = math.radians(20.0)
    n = np.array([math.sin(t), 0.0, math.cos(t)])
    z0 = 0.2 / math.cos(t)
    c = Uncertainty(tilt_rel=0.02, tilt_pivot=0.0, tilt_offset_rel=0.003).tilt_floor(n, 0.2)
    assert c[0, 0] == pytest.approx((0.02 * math.tan(t)) ** 2) and c[0, 2] == 0.0 and c[1, 2] == 0.0
    assert c[2, 2] == pytest.approx((0.003 * z0 * math.tan(t)) ** 2)
    half = Uncertainty(tilt_rel=0.02, tilt_pivot=0.5).tilt_floor(n, 0.2)
    assert half[0, 2] == pytest.approx(-0.5 * half[0, 0] * z0 * math.tan(t))
    only = Uncertainty(tilt_offset_rel=0.003)  # the offset term alone acts too
    assert only.apply(np.zeros((3, 3)), 0.2, n)[2, 2] == pytest.approx(c[2, 2])
    assert np.all(only.apply(np.zeros((3, 3)), 0.2, np.array([0.0, 0.0, 1.0])) == 0.0)
    u = Uncertainty(tilt_rel=0.01, tilt_pivot=0.0, tilt_offset_rel=0.002)
    assert Uncertainty.from_dict(json.loads(json.dumps(u.to_dict()))) == u
    assert "tilt_pivot" not in Uncertainty().to_dict() and "tilt_offset_rel" not in Uncertainty().to_dict()
    assert Uncertainty.from_dict({}).tilt_pivot == 1.0  # older files: peak's pivot about the axis crossing
    for bad in ({"tilt_pivot": -0.1}, {"tilt_pivot": 3.0}, {"tilt_offset_rel": 2.0}, {"tilt_offset_rel": math.nan}):
        with pytest.raises(ValueError):
            Uncertainty(**bad)


@settings(max_examples=60, deadline=None)
@given(st.floats(0.0, 1.0), st.floats(0.0, 1.5), st.floats(-math.pi, math.pi), st.floats(1e-3, 5.0),
       st.floats(0.0, 2.0), st.floats(0.0, 1.0))
def test_tilt_term_only_adds_uncertainty(rel, theta, phi, offset, pivot, offset_rel):
    """Safety invariant: the tilt term is a finite positive semi-definite covariance, so it never makes an
    estimate claim more certainty than without it."""
    n = np.array([math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)])
    c = Uncertainty(tilt_rel=rel, tilt_pivot=pivot, tilt_offset_rel=offset_rel).tilt_floor(n, offset)
    assert np.all(np.isfinite(c)) and np.allclose(c, c.T)
    assert np.linalg.eigvalsh(c).min() >= -1e-12 * max(1.0, np.abs(c).max())


def test_preference_compares_tilt_variances():
    plane = Plane(np.array([0.0, 0.0, 1.0]), 0.1)
    small = PlaneEstimate(plane, covariance=np.eye(3) * 1e-6)
    large = PlaneEstimate(plane, covariance=np.eye(3) * 4e-6)
    u = Uncertainty(prefer_ratio=1.0)
    assert u.prefers(small, large) and not u.prefers(large, small)
    assert Uncertainty(prefer_ratio=4.0).prefers(large, small)
    assert Uncertainty().prefers(large, small)  # no comparison by default
    assert u.prefers(PlaneEstimate(plane), small)  # no covariance: no claim to compare


def test_calibration_without_uncertainty_section_loads_with_defaults():
    cal = Calibration.from_dict({"format": "place_safe.calibration/1"})
    assert cal.uncertainty("diff") == Uncertainty()
    bad = Calibration.from_dict({"format": "place_safe.calibration/1", "uncertainty": {"peak": {"tilt_std": -1}}})
    with pytest.raises(CalibrationError, match="uncertainty"):  # a bad section fails when it is used
        bad.uncertainty("peak")


@settings(max_examples=15, deadline=None)
@given(st.floats(0.0, 0.4), st.floats(-3.0, 3.0), st.floats(0.03, 0.4), st.floats(1e-4, 2e-3))
def test_plane_covariance_matches_the_scatter_of_fitted_planes(theta, phi, z0, sigma):
    """The SVD fit's covariance predicts the spread of planes fitted to noisy points (Monte Carlo).

    The covariance is first order, so the property holds where errors are small: point noise up to 3 % of
    the distance (tilt std up to about 0.1 rad). Beyond, e.g. 2 mm of noise on points 3 cm away (tilt std
    0.18 rad), normalising the normal makes the spread about 28 % larger than first order predicts."""
    from hypothesis import assume

    from place_safe.geometry import fit_plane
    from place_safe.sensor.zones import ZONE_DIRECTIONS

    assume(sigma <= 0.03 * z0)

    rng = np.random.default_rng(0)
    truth = Plane.from_angles(theta, phi, z0)
    pts = truth.intersect(ZONE_DIRECTIONS)
    states, covs = [], []
    for _ in range(300):
        noisy = pts + rng.normal(0.0, sigma, pts.shape[0])[:, None] * truth.normal
        plane, _ = fit_plane(noisy)
        states.append([plane.normal[0], plane.normal[1], plane.offset])
        covs.append(plane_covariance(noisy, np.ones(9, dtype=bool), plane))
    emp = np.cov(np.array(states).T)
    pred = np.mean(covs, axis=0)
    assert np.trace(emp[:2, :2]) == pytest.approx(np.trace(pred[:2, :2]), rel=0.25)
    assert emp[2, 2] == pytest.approx(pred[2, 2], rel=0.25)


@pytest.mark.parametrize("z0, theta, zones", [(0.02, 0.0, range(9)), (0.05, 0.3, range(9)), (0.03, 0.1, (0, 1, 2, 3, 6))])
def test_plane_covariance_with_range_errors_is_the_scatter_of_fitted_planes(z0, theta, zones):
    """plane_covariance with a known range error (Monte Carlo of its own assumption: each zone's range off by
    an independent error along its direction, the SVD plane through the zones used). Each zone's variance is
    the larger of the fit's estimate and the known one, so the prediction is at least the scatter and not far
    above it; with zones missing it follows the points actually used."""
    from place_safe.geometry import fit_plane
    from place_safe.sensor.zones import ZONE_DIRECTIONS

    rng = np.random.default_rng(3)
    sigma = 2e-5
    truth = Plane.from_angles(theta, 0.7, z0)
    used = np.zeros(9, dtype=bool)
    used[list(zones)] = True
    r = truth.offset / (ZONE_DIRECTIONS @ truth.normal)
    states, covs = [], []
    for _ in range(2000):
        pts = (r + rng.normal(0.0, sigma, 9))[:, None] * ZONE_DIRECTIONS
        plane, _ = fit_plane(pts[used])
        states.append([plane.normal[0], plane.normal[1], plane.offset])
        covs.append(plane_covariance(pts, used, plane, np.full(9, sigma)))
    emp = np.diag(np.cov(np.array(states).T))
    pred = np.diag(np.mean(covs, axis=0))
    assert np.all(pred >= 0.9 * emp) and np.all(pred <= 1.6 * emp), (pred / emp)
    # without a known error: the fit's own estimate alone, as before
    plain = plane_covariance(pts, used, plane)
    assert np.allclose(plain, plane_covariance(pts, used, plane, 0.0))


def test_near_std_between_its_depths_held_before_and_none_from_the_last_on():
    u = Uncertainty(near_depths=[0.01, 0.03, 0.09], near_range_std=[2e-3, 1e-3, 0.0])
    np.testing.assert_allclose(u.near_std(np.array([0.005, 0.01, 0.02, 0.06, 0.09, 0.5, np.nan])),
                               [2e-3, 2e-3, 1.5e-3, 0.5e-3, 0.0, 0.0, 0.0])
    assert not Uncertainty().near_std(np.full(9, 0.01)).any()
    cov = np.eye(3) * 1e-8
    np.testing.assert_allclose(u.apply(cov, 0.02), cov + u.floor(0.02))  # the term acts in the fit, not here
    assert Uncertainty.from_dict(json.loads(json.dumps(u.to_dict()))) == u
    assert "near_depths" not in Uncertainty().to_dict()  # files older versions read
    assert "near_common_std" not in u.to_dict() and not u.near_common(np.full(9, 0.02)).any()
    shared = u.replace(near_common_std=[1e-3, 4e-4, 0.0])
    np.testing.assert_allclose(shared.near_common(np.array([0.005, 0.02, 0.09])), [1e-3, 7e-4, 0.0])
    assert Uncertainty.from_dict(json.loads(json.dumps(shared.to_dict()))) == shared
    for bad in ({"near_depths": [0.01], "near_range_std": [0.001]},
                {"near_depths": [0.01, 0.03], "near_range_std": [0.001, 0.0], "near_common_std": [0.001]},
                {"near_depths": [0.01, 0.03], "near_range_std": [0.001, 0.0], "near_common_std": [0.001, -1.0]},
                {"near_depths": [0.03, 0.01], "near_range_std": [0.001, 0.0]},
                {"near_depths": [0.01, 0.03], "near_range_std": [0.001]},
                {"near_depths": [0.01, 0.03], "near_range_std": [-0.001, 0.0]},
                {"near_depths": [0.01, 0.03], "near_range_std": [float("nan"), 0.0]},
                {"near_depths": [0.01, 0.03], "near_range_std": [1.0, 0.0]},
                {"near_depths": 0.01, "near_range_std": [0.001]},
                {"near_depths": [True, 2], "near_range_std": [0.001, 0.0]},
                {"near_depths": [0.01, 10 ** 400], "near_range_std": [0.001, 0.0]},
                {"tilt_std": 10 ** 400}):
        cal = Calibration.from_dict({"format": "place_safe.calibration/1", "uncertainty": {"peak": bad}})
        with pytest.raises(CalibrationError, match="section .uncertainty.: uncertainty.peak") as info:
            cal.uncertainty("peak")
        assert "\n" not in str(info.value)


def test_recovery_never_imports_the_calibration_package():
    # calibration depends on recovery (it fits its parameters), never the reverse: no import cycle
    import subprocess
    import sys

    code = ("import sys; from place_safe.recovery import make_estimator; make_estimator('peak'); "
            "make_estimator('proprietary'); print('place_safe.calibration' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout
    assert out.strip() == "False"


@settings(max_examples=40, deadline=None)
@given(depth=st.floats(0.02, 0.09), tilt=st.floats(-0.3, 0.3), indep=st.floats(1e-6, 2e-3),
       shared=st.floats(0.0, 2e-3), drop=st.integers(-1, 8))
def test_a_shared_zone_error_never_makes_the_plane_look_more_certain(depth, tilt, indep, shared, drop):
    """The near-range covariance with a range error the zones share is the one without it plus a positive
    semi-definite term (issue 26): adding the shared error can only widen what the estimate admits."""
    from place_safe.recovery.points import PeakParams, plane_through

    dirs = PeakParams.default_peak().directions()
    n = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    r = depth * n[2] / (dirs @ n)  # each zone's range to the tilted plane through (0, 0, depth)
    used = np.ones(9, dtype=bool)
    if drop >= 0:
        used[drop] = False
    pts = r[:, None] * dirs
    plane, _ = plane_through(pts, used)
    alone = plane_covariance(pts, used, plane, np.full(9, indep), replace_fit=True)
    both = plane_covariance(pts, used, plane, np.full(9, indep), replace_fit=True, common_std=np.full(9, shared))
    assert np.all(np.isfinite(both))
    assert np.linalg.eigvalsh(both - alone).min() >= -1e-12 * max(1.0, float(np.abs(alone).max()))


def test_the_tilt_term_counts_the_tilt_from_the_calibration_sweeps_own_plane():
    """With ``tilt_about`` (the calibration frames' mean slopes) a plane at that tilt gets no tilt term, one tilted from
    it gets the term of that tilt, whichever way; the default (level) is as before, and stays out of the file."""
    unc = Uncertainty(tilt_rel=0.1, tilt_offset_rel=0.01, tilt_pivot=0.0)
    about = unc.replace(tilt_about=[0.01, -0.005])
    at = Plane.from_slopes(0.01, -0.005, 0.2)
    assert np.array_equal(about.tilt_floor(at.normal, at.offset), np.zeros((3, 3)))
    for da, db in ((0.03, 0.0), (-0.03, 0.0), (0.0, 0.03), (0.018, -0.024)):  # 0.03 off the sweep's slopes, any way
        p = Plane.from_slopes(0.01 + da, -0.005 + db, 0.2)
        c = about.tilt_floor(p.normal, p.offset)
        z0 = p.offset / p.normal[2]
        assert np.isclose(c[0, 0], (0.1 * 0.03) ** 2, rtol=1e-9, atol=0) and np.isclose(c[1, 1], c[0, 0], rtol=0, atol=0)
        assert np.isclose(c[2, 2], (0.01 * z0 * 0.03) ** 2, rtol=1e-9, atol=0)
    level = Plane(np.array([0.0, 0.0, 1.0]), 0.2)
    assert np.array_equal(unc.tilt_floor(level.normal, 0.2), np.zeros((3, 3)))
    assert about.tilt_floor(level.normal, 0.2)[0, 0] > 0
    steepest = unc.tilt_floor(np.array([1.0, 0.0, 0.0]), 0.2)  # past 80 deg, or not a normal: the 80 deg cap either way
    for bad in (np.array([1.0, 0.0, 0.0]), np.array([math.nan, 0.0, 1.0])):
        assert np.isclose(about.tilt_floor(bad, 0.2)[0, 0], steepest[0, 0], rtol=1e-12, atol=0)
    assert "tilt_about" not in unc.to_dict() and about.to_dict()["tilt_about"] == [0.01, -0.005]
    assert Uncertainty.from_dict(about.to_dict()) == about
    with pytest.raises(CalibrationError, match="tilt_about"):
        Uncertainty.from_dict({**about.to_dict(), "tilt_about": [2.0, 0.0]})


def test_stacked_fits_give_each_fit_its_own_covariance():
    """known_error_covariance of many fits stacked (what the near-range law's fit tries hundreds of times) is
    plane_covariance of each: the zones used, the known and shared errors, the fit's own where none is known."""
    from place_safe.recovery.points import (PeakParams, PlaneFitGeometry, known_error_covariance, plane_fit_geometry,
                                            plane_through)

    rng = np.random.default_rng(3)
    dirs = PeakParams.default_peak().directions()
    fits, stds, commons, expected = [], [], [], []
    for k in range(24):
        n = np.array([rng.normal(0, 0.2), rng.normal(0, 0.2), 1.0])
        n /= np.linalg.norm(n)
        r = rng.uniform(0.02, 0.12) * n[2] / (dirs @ n) + rng.normal(0, 3e-4, 9)
        pts = r[:, None] * dirs
        used = rng.uniform(size=9) > 0.25
        used[:3] = True
        plane, _ = plane_through(pts, used)
        std = rng.uniform(0, 2e-3, 9) * (rng.uniform(size=9) > 0.3) * (k % 4 != 0)  # some fits: none known
        common = rng.uniform(0, 1e-3, 9) * (k % 3 == 0)
        fits.append(plane_fit_geometry(pts, used, plane))
        stds.append(std)
        commons.append(common)
        expected.append(plane_covariance(pts, used, plane, std, replace_fit=True, common_std=common))
    stacked = PlaneFitGeometry(*(np.stack(parts) for parts in zip(*fits)))
    got = known_error_covariance(stacked, np.array(stds), replace_fit=True, common_std=np.array(commons))
    assert got.shape == (24, 3, 3)
    for g, e in zip(got, expected):
        assert np.allclose(g, e, rtol=1e-12, atol=1e-30)


@pytest.mark.parametrize("options", [5, {"rays": 2}])
def test_estimator_arguments_of_the_wrong_type_are_refused_saying_what_was_expected(options):
    """``make_estimator("diff", cal, options=5)`` raised AttributeError ('int' object has no attribute 'rays'), and an
    estimator built with ``uncertainty=1`` was accepted and raised AttributeError out of every ``estimate``: library
    calls say what they expected (ArgumentTypeError, a TypeError), when they are made."""
    from place_safe.exceptions import ArgumentTypeError
    from place_safe.recovery import make_estimator
    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.recovery.peak import PeakEstimator
    from place_safe.recovery.proprietary import ProprietaryEstimator

    with pytest.raises(ArgumentTypeError, match="options") as exc:
        make_estimator("diff", None, options=options)
    assert "\n" not in str(exc.value)
    for build, arg in ((DifferentiableEstimator, "forward"), (DifferentiableEstimator, "peak"),
                       (DifferentiableEstimator, "correction"), (DifferentiableEstimator, "uncertainty"),
                       (DifferentiableEstimator, "peak_uncertainty"), (DifferentiableEstimator, "options"),
                       (PeakEstimator, "params"), (PeakEstimator, "uncertainty"), (ProprietaryEstimator, "params")):
        with pytest.raises(ArgumentTypeError, match=arg):
            build(**{arg: {"m": 1.0}})


def test_without_fallback_lifts_only_the_fallback_limits():
    from place_safe.recovery.estimator import Uncertainty

    unc = Uncertainty(tilt_std=1e-3, chi2_limit=2.0, consistency_limit=9.0, prefer_ratio=1.5, scale=1.3)
    own = unc.without_fallback()
    assert all(math.isinf(getattr(own, k)) for k in Uncertainty.FALLBACK_LIMITS)
    assert own.replace(**{k: getattr(unc, k) for k in Uncertainty.FALLBACK_LIMITS}) == unc  # nothing else moved


def test_an_uncertainty_entry_that_shrinks_every_covariance_is_refused_when_read():
    """A hand-edited file with ``scale`` 1e-12 (NEES 3e11 on the sweep) or every floor term 0 (a model without error:
    NEES 5.7) was accepted; each is now one CalibrationError line naming the entry. Some zero terms are fitted (the
    packaged mismatched calibration's peak has no tilt floor) and stay accepted, as do the defaults of a missing
    entry."""
    from place_safe.recovery.estimator import MIN_SCALE

    fmt = {"format": "place_safe.calibration/1"}
    for entry, words in (({"tilt_std": 3e-4, "scale": 1e-12}, "scale"), ({"tilt_std": 3e-4, "scale": 0.0}, "scale"),
                         ({"tilt_std": 0.0, "offset_std": 0.0, "scale": 0.95}, "states no model error"),
                         ({}, "states no model error")):
        cal = Calibration.from_dict({**fmt, "uncertainty": {"peak": entry}})
        with pytest.raises(CalibrationError, match=f"section .uncertainty.: uncertainty.peak: .*{words}") as info:
            cal.uncertainty("peak")
        assert "\n" not in str(info.value)
        with pytest.raises(CalibrationError):
            cal.check()
    with pytest.raises(CalibrationError):
        Uncertainty(scale=MIN_SCALE / 2)
    assert Uncertainty(scale=MIN_SCALE).scale == MIN_SCALE
    kept = Calibration.from_dict({**fmt, "uncertainty": {"peak": {"offset_std": 8e-6, "scale": 0.21}}})
    assert kept.uncertainty("peak").offset_std == 8e-6
    assert Calibration.from_dict(fmt).uncertainty("peak") == Uncertainty()  # no entry: the defaults
    # a calibration without diff's entry keeps none without its fallback (the defaults never fall back)
    assert Calibration().without_fallback().uncertainty("diff") == Uncertainty()
    assert kept.without_fallback().uncertainty("peak") == kept.uncertainty("peak")


def test_the_batch_entry_points_take_any_iterable_and_say_what_they_need_in_one_line(synthetic_frames):
    """A review's bad-input search: diff's ``estimate_batch([None])`` raised AttributeError from deep inside, its
    ``estimate_many`` took no generator, and every ``estimate_many(frame)`` raised "'Frame' object is not iterable".
    Now a non-frame gets its reason in place, any iterable is taken, and a single frame or an array is one
    ArgumentTypeError saying what to call instead; ``load_frames(None)`` and a two-component normal say what they
    need in one line too."""
    from place_safe import load_frames, make_estimator
    from place_safe.exceptions import ArgumentTypeError, FrameFileError
    from place_safe.geometry import Plane

    frame = synthetic_frames[0]
    for method in ("peak", "diff"):
        est = make_estimator(method)
        out = est.estimate_many(f for f in (frame, None))
        assert out[0].ok and out[1].plane is None and "expected a Frame" in out[1].reason
        for bad in (frame, np.zeros((2, 9, 128)), 3):
            with pytest.raises(ArgumentTypeError, match="expected an iterable of Frame objects"):
                est.estimate_many(bad)
    diff = make_estimator("diff")
    got = diff.estimate_batch([None, frame])
    assert got[0].plane is None and "expected a Frame" in got[0].reason and got[1].plane is not None
    with pytest.raises(FrameFileError, match="expected a file path"):
        load_frames(None)
    with pytest.raises(ValueError, match="a normal of 3 numbers"):
        Plane(np.array([0.0, 1.0]), 0.1)


def test_a_plane_beyond_the_sensors_range_is_no_plane(synthetic_frames):
    """A peak calibration whose ``b`` is -10000 (within its field's range) put every plane 140 m away, stated to
    millimetres, through peak and diff alike (session 82); a proprietary ``b`` of -10000 put planes 9-10 m away,
    within the 65.5 m the on-sensor field holds (the limit then) but beyond the TMF8820's 5 m (session 83). Beyond
    SENSOR_RANGE an estimate is no plane, with the reason; the same calibrations with their own ``b`` read as before."""
    from place_safe.recovery import make_estimator
    from place_safe.recovery.estimator import checked
    from place_safe.recovery.points import PeakParams
    from place_safe.sensor.frame import SENSOR_RANGE

    far = PeakParams.default_peak().replace(b=-10000.0)
    cal = Calibration({"peak": far.to_dict(), "proprietary": PeakParams.default_proprietary().replace(
        b=-10000.0).to_dict()})
    for method in ("peak", "diff", "proprietary"):
        for est in make_estimator(method, cal).estimate_many(synthetic_frames[:3]):
            assert est.plane is None and "m away, beyond the sensor's 5 m range: is the calibration this sensor's?" \
                in est.reason, (method, est.reason)
    near = Calibration({"peak": PeakParams.default_peak().to_dict(),
                        "proprietary": PeakParams.default_proprietary().to_dict()})
    for method in ("peak", "proprietary"):
        assert all(e.plane is not None for e in make_estimator(method, near).estimate_many(synthetic_frames[:3]))
    at_limit = PlaneEstimate(Plane([0.0, 0.0, 1.0], SENSOR_RANGE))
    assert checked(at_limit) is at_limit
    assert checked(PlaneEstimate(Plane([0.0, 0.0, 1.0], SENSOR_RANGE + 1e-3))).plane is None


def test_the_zones_scatter_is_a_bounded_length_left_out_of_the_file_where_it_is_not_stated():
    """``zone_std`` (m): 0 (files before it) is left out of the file, a stated one written and read back; a negative or a
    value beyond NEAR_MAX_STD is one line naming the field."""
    assert "zone_std" not in Uncertainty().to_dict()
    stated = Uncertainty(offset_std=1e-4, zone_std=1.04e-4)
    assert stated.to_dict()["zone_std"] == 1.04e-4
    assert Uncertainty.from_dict(stated.to_dict()) == stated
    for bad in (-1e-4, 0.06, "0.1"):
        with pytest.raises(CalibrationError) as exc:
            Uncertainty.from_dict({**stated.to_dict(), "zone_std": bad})
        assert str(exc.value).startswith("uncertainty: zone_std: ") and "\n" not in str(exc.value)
