"""Tests of place_safe.geometry: plane conventions, conversions, SVD plane fit, ground truth from poses."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from place_safe.exceptions import NoPlaneError
from place_safe.geometry import Plane, fit_plane, is_rotation, plane_from_pose, rotation_angle_between, transform_problem


def test_plane_normalises_and_orients_towards_plus_z():
    p = Plane(np.array([0.0, 0.0, -2.0]), -0.1)  # -2 z = -0.1, i.e. the plane z = 0.05
    np.testing.assert_allclose(p.normal, [0, 0, 1])
    assert p.offset == pytest.approx(0.05)
    q = Plane(np.array([3.0, 0.0, 4.0]), 1.0)  # |n| = 5: the same plane as n/5 . x = 0.2
    assert q.offset == pytest.approx(0.2)
    np.testing.assert_allclose(q.intersect(np.array([0.0, 0.0, 1.0])), [0, 0, 0.25])


@pytest.mark.parametrize("normal,offset", [([np.nan, 0, 1], 0.1), ([0, 0, 1], np.inf), ([0, 0, 0], 0.1),
                                           ([1, 0, 0], 0.1)])
def test_plane_rejects_unusable_planes(normal, offset):
    with pytest.raises(NoPlaneError):
        Plane(np.array(normal, dtype=float), offset)


@pytest.mark.parametrize("theta,phi,z0", [(0.0, 0.0, 0.05), (0.3, 1.0, 0.2), (np.deg2rad(45), -2.5, 0.4),
                                          (np.deg2rad(10), np.pi, 0.01)])
def test_angles_round_trip(theta, phi, z0):
    p = Plane.from_angles(theta, phi, z0)
    assert np.linalg.norm(p.normal) == pytest.approx(1.0)
    assert p.theta == pytest.approx(theta, abs=1e-12)
    if theta > 0:
        assert np.cos(p.phi - phi) == pytest.approx(1.0)
    assert p.z0 == pytest.approx(z0)
    assert p.offset == pytest.approx(z0 * np.cos(theta))
    # z0 is where the optical axis meets the plane
    np.testing.assert_allclose(p.intersect(np.array([0.0, 0.0, 1.0])), [0, 0, z0], atol=1e-12)


def test_slopes_round_trip_and_meaning():
    p = Plane.from_slopes(0.2, -0.1, 0.15)
    a, b, z0 = p.slopes
    assert (a, b, z0) == pytest.approx((0.2, -0.1, 0.15))
    # points of z = z0 - a x - b y lie on the plane
    x, y = 0.03, -0.02
    pt = np.array([x, y, 0.15 - 0.2 * x + 0.1 * y])
    assert p.normal @ pt == pytest.approx(p.offset)


def test_dict_round_trip():
    p = Plane.from_angles(0.2, 0.7, 0.12)
    q = Plane.from_dict(p.to_dict())
    np.testing.assert_allclose(q.normal, p.normal)
    assert q.offset == pytest.approx(p.offset)


def test_intersect_gives_nan_for_rays_that_miss():
    p = Plane(np.array([0.0, 0.0, 1.0]), 0.1)
    pts = p.intersect(np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]))
    np.testing.assert_allclose(pts[0], [0, 0, 0.1])
    assert np.all(np.isnan(pts[1:]))


def test_fit_plane_is_exact_on_noiseless_points():
    rng = np.random.default_rng(0)
    truth = Plane.from_angles(0.4, 2.0, 0.2)
    dirs = np.column_stack([rng.uniform(-0.3, 0.3, (50, 2)), np.ones(50)])
    pts = truth.intersect(dirs)
    plane, rms = fit_plane(pts)
    np.testing.assert_allclose(plane.normal, truth.normal, atol=1e-12)
    assert plane.offset == pytest.approx(truth.offset, abs=1e-12)
    assert rms < 1e-12


def test_fit_plane_weights_and_invalid_points():
    truth = Plane.from_angles(0.1, 0.3, 0.1)
    dirs = np.array([[0.1, 0.1, 1], [-0.1, 0.1, 1], [0.1, -0.1, 1], [-0.1, -0.1, 1], [0.0, 0.0, 1]], dtype=float)
    pts = truth.intersect(dirs)
    outlier = pts[4] + np.array([0.0, 0.0, 0.05])
    pts_bad = np.vstack([pts[:4], outlier, [np.nan, 0, 0]])
    plane, _ = fit_plane(pts_bad, weights=np.array([1, 1, 1, 1, 0, 1.0]))  # zero weight and NaN are ignored
    np.testing.assert_allclose(plane.normal, truth.normal, atol=1e-12)


def test_fit_plane_needs_three_non_collinear_points():
    with pytest.raises(NoPlaneError):
        fit_plane(np.array([[0, 0, 1.0], [0, 0, 2.0]]))
    with pytest.raises(NoPlaneError):
        fit_plane(np.array([[0, 0, 1.0], [0, 0, 2.0], [0, 0, 3.0]]))


def test_plane_from_pose_identity_and_tilt():
    p = plane_from_pose(np.eye(4), 0.2)
    np.testing.assert_allclose(p.normal, [0, 0, 1])
    assert p.offset == pytest.approx(0.2)
    # sensor looking down (flipped about x) and tilted by 20 deg about its x axis
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", 180 + 20, degrees=True).as_matrix()
    p = plane_from_pose(T, 0.1)
    assert np.degrees(p.theta) == pytest.approx(20.0)
    assert p.offset == pytest.approx(0.1)
    assert p.normal[2] > 0


def test_rotation_angle_between():
    assert rotation_angle_between([0, 0, 1], [0, 0, 1]) == pytest.approx(0.0)
    assert rotation_angle_between([0, 0, 1], [1, 0, 0]) == pytest.approx(np.pi / 2)
    small = np.array([np.sin(1e-7), 0.0, np.cos(1e-7)])
    assert rotation_angle_between([0, 0, 1], small) == pytest.approx(1e-7, rel=1e-6)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1))
def test_is_rotation_accepts_rotations_and_nothing_else(q):
    r = Rotation.from_quat(q).as_matrix()
    assert is_rotation(r)
    assert not is_rotation(-r)  # a reflection: orthonormal, determinant -1
    assert not is_rotation(r @ np.diag([1.0, 1.0, -1.0]))
    assert not is_rotation(1.01 * r) and is_rotation(1.0001 * r, tol=1e-3)
    assert not is_rotation(np.zeros((3, 3)))


@settings(max_examples=30, deadline=None)
@given(st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4).filter(lambda q: np.linalg.norm(q) > 0.1),
       st.lists(st.floats(-2.0, 2.0), min_size=3, max_size=3))
def test_transform_problem_names_what_breaks_a_rigid_transform(q, t):
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat(q).as_matrix()
    m[:3, 3] = t
    assert transform_problem(m) is None and transform_problem(m.tolist()) is None
    bad_row = m.copy()
    bad_row[3, 0] = 1e-6
    reflected = m.copy()
    reflected[:3, :3] *= -1.0
    with_nan = m.copy()
    with_nan[1, 3] = np.nan
    for bad, words in ((bad_row, "last row"), (reflected, "proper rotation"), (with_nan, "NaN"),
                       (m[:3], "shape (3, 4)"), ([["a"] * 4] * 4, "numbers"), ([[1.0, 2.0], [3.0]], "numbers")):
        why = transform_problem(bad)
        assert why is not None and words in why and "\n" not in why
