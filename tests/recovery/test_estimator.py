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


def test_near_floor_is_the_scatter_of_planes_through_zones_with_independent_range_errors():
    """zone_error_covariance (Monte Carlo of its own assumption: a level surface, each zone's range off by an
    independent error along its direction, the SVD plane through the 9 points)."""
    from place_safe.geometry import fit_plane
    from place_safe.recovery.estimator import zone_error_covariance
    from place_safe.sensor.zones import ZONE_DIRECTIONS

    rng = np.random.default_rng(3)
    sigma = 2e-5
    for d in (0.02, 0.06):
        states = []
        for _ in range(3000):
            r = d / ZONE_DIRECTIONS[:, 2] + rng.normal(0.0, sigma, 9)
            plane, _ = fit_plane(r[:, None] * ZONE_DIRECTIONS)
            states.append([plane.normal[0], plane.normal[1], plane.offset])
        emp = np.cov(np.array(states).T)
        pred = sigma ** 2 * zone_error_covariance(d)
        np.testing.assert_allclose(np.diag(emp), np.diag(pred), rtol=0.1)
        assert abs(emp[0, 1]) < 0.1 * emp[0, 0]


def test_near_floor_between_its_depths_unscaled_and_none_from_the_last_on():
    from place_safe.recovery.estimator import zone_error_covariance

    u = Uncertainty(tilt_std=1e-3, scale=2.0, near_depths=[0.01, 0.03, 0.09], near_range_std=[2e-3, 1e-3, 0.0])
    np.testing.assert_allclose(u.near_floor(0.02), (1.5e-3) ** 2 * zone_error_covariance(0.02))
    np.testing.assert_allclose(u.near_floor(0.005), (2e-3) ** 2 * zone_error_covariance(0.005))  # held
    assert not u.near_floor(0.09).any() and not u.near_floor(0.5).any()
    cov = np.eye(3) * 1e-8
    np.testing.assert_allclose(u.apply(cov, 0.02), 2.0 * (cov + u.floor(0.02)) + u.near_floor(0.02))
    np.testing.assert_allclose(u.apply(cov, 0.2), 2.0 * (cov + u.floor(0.2)))
    assert Uncertainty.from_dict(json.loads(json.dumps(u.to_dict()))) == u
    assert "near_depths" not in Uncertainty().to_dict()  # files older versions read
    for bad in ({"near_depths": [0.01], "near_range_std": [0.001]},
                {"near_depths": [0.03, 0.01], "near_range_std": [0.001, 0.0]},
                {"near_depths": [0.01, 0.03], "near_range_std": [0.001]},
                {"near_depths": [0.01, 0.03], "near_range_std": [-0.001, 0.0]},
                {"near_depths": [0.01, 0.03], "near_range_std": [float("nan"), 0.0]},
                {"near_depths": [0.01, 0.03], "near_range_std": [1.0, 0.0]},
                {"near_depths": 0.01, "near_range_std": [0.001]}):
        cal = Calibration.from_dict({"format": "place_safe.calibration/1", "uncertainty": {"peak": bad}})
        with pytest.raises(CalibrationError, match="uncertainty section") as info:
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
