"""Metrics on known cases: tilt gives its angle, shifts give their distance."""

import numpy as np
import pytest

from place_safe.geometry import Plane
from place_safe.evaluation.metrics import (angular_error, angular_errors, grid_directions, linear_error, linear_errors,
                                point_error, point_errors, summarise)


def test_ten_degree_tilt_gives_ten_degrees():
    a = Plane.from_angles(0.0, 0.0, 0.2)
    b = Plane.from_angles(np.deg2rad(10.0), 0.7, 0.2)
    assert np.degrees(angular_error(b, a)) == pytest.approx(10.0, abs=1e-9)
    assert linear_error(b, a) == pytest.approx(0.0, abs=1e-12)


def test_one_millimetre_shift():
    a = Plane.from_angles(0.0, 0.0, 0.2)
    b = Plane.from_angles(0.0, 0.0, 0.201)
    assert linear_error(b, a) == pytest.approx(1e-3, abs=1e-12)
    # a fronto-parallel 1 mm shift moves each grid point by 1 mm / cos(ray angle): slightly over 1 mm
    e = point_error(b, a)
    assert 1e-3 < e < 1.1e-3
    assert angular_error(b, a) == pytest.approx(0.0, abs=1e-12)


def test_grid_spans_field_of_view():
    g = grid_directions()
    assert g.shape == (64, 3)
    xy = g[:, :2] / g[:, 2:]
    assert xy[:, 0].min() == pytest.approx(-0.294) and xy[:, 0].max() == pytest.approx(0.294)
    assert xy[:, 1].min() == pytest.approx(-0.291) and xy[:, 1].max() == pytest.approx(0.291)


def test_vectorised_matches_scalar():
    rng = np.random.default_rng(0)
    est = [Plane.from_angles(rng.uniform(0, 0.5), rng.uniform(-3, 3), rng.uniform(0.05, 0.3)) for _ in range(5)]
    tru = [Plane.from_angles(rng.uniform(0, 0.5), rng.uniform(-3, 3), rng.uniform(0.05, 0.3)) for _ in range(5)]
    ne, de = np.array([p.normal for p in est]), np.array([p.offset for p in est])
    nt, dt = np.array([p.normal for p in tru]), np.array([p.offset for p in tru])
    assert np.allclose(angular_errors(ne, nt), [angular_error(a, b) for a, b in zip(est, tru)])
    assert np.allclose(linear_errors(ne, de, nt, dt), [linear_error(a, b) for a, b in zip(est, tru)])
    assert np.allclose(point_errors(ne, de, nt, dt), [point_error(a, b) for a, b in zip(est, tru)])
    assert np.all(point_errors(nt, dt, nt, dt) == 0)


def test_summarise_ignores_nan():
    s = summarise([1.0, 2.0, 3.0, np.nan])
    assert s["mean"] == pytest.approx(2.0) and s["median"] == pytest.approx(2.0) and s["count"] == 3
    assert s["p95"] == pytest.approx(2.9)
    assert np.isnan(summarise([np.nan])["mean"])
