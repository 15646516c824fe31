"""The bounded Levenberg-Marquardt solver: it stops on its convergence test, says why, and stays in its box."""

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.calibration import gauss_newton


def _rosenbrock():
    def fun(x):
        return np.array([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])

    def jac(x):
        return np.array([[-20.0 * x[0], 10.0], [-1.0, 0.0]])

    return fun, jac


def test_converges_on_a_curved_valley_by_the_decrement_test():
    fun, jac = _rosenbrock()
    # residuals of unit noise would make 1e-4 a ten-thousandth of a standard deviation: ask for that
    res = gauss_newton.solve(fun, jac, np.array([-1.2, 1.0]), np.full(2, -np.inf), np.full(2, np.inf),
                             decrement_tol=1e-16)
    assert res.converged and res.reason == "converged: Gauss-Newton decrement"
    np.testing.assert_allclose(res.x, [1.0, 1.0], atol=1e-4)
    assert res.history == sorted(res.history, reverse=True)  # every kept step lowered the cost


def test_a_minimum_outside_the_box_is_found_on_its_bound():
    fun, jac = _rosenbrock()
    res = gauss_newton.solve(fun, jac, np.array([0.0, 0.0]), np.array([-2.0, -2.0]), np.array([0.5, 2.0]),
                             decrement_tol=1e-16)
    assert res.converged
    assert res.x[0] == pytest.approx(0.5)
    assert res.x[1] == pytest.approx(0.25, abs=1e-4)


def test_the_iteration_limit_is_reported_as_not_converged():
    fun, jac = _rosenbrock()
    res = gauss_newton.solve(fun, jac, np.array([-1.2, 1.0]), np.full(2, -np.inf), np.full(2, np.inf),
                             max_iterations=2)
    assert not res.converged and res.reason == "not converged: iteration limit"
    assert res.iterations == 2


def test_linear_problem_solved_with_its_covariance():
    rng = np.random.default_rng(0)
    A = rng.normal(size=(200, 3))
    x_true = np.array([1.0, -2.0, 0.5])
    y = A @ x_true + rng.normal(size=200) * 3.0  # residuals 3x their unit noise: covariance widened by chi2
    res = gauss_newton.solve(lambda x: A @ x - y, lambda x: A, np.zeros(3), np.full(3, -np.inf), np.full(3, np.inf))
    assert res.converged
    cov = gauss_newton.covariance(res.jac, res.cost)
    # stopped within a tenth of a standard deviation of the least-squares solution (the decrement test)
    off = res.x - np.linalg.lstsq(A, y, rcond=None)[0]
    assert off @ np.linalg.solve(cov, off) <= 0.1 ** 2
    chi2_red = 2 * res.cost / (200 - 3)
    np.testing.assert_allclose(cov, np.linalg.inv(A.T @ A) * chi2_red, rtol=1e-6)


def test_an_unknown_the_data_do_not_inform_has_infinite_spread():
    A = np.zeros((10, 2))
    A[:, 0] = 1.0
    cov = gauss_newton.covariance(A, 5.0)
    assert math.isfinite(cov[0, 0]) and math.isinf(cov[1, 1])


def test_non_finite_residuals_at_the_start_are_an_error():
    with pytest.raises(ArithmeticError):
        gauss_newton.solve(lambda x: np.array([np.nan]), lambda x: np.ones((1, 1)), np.zeros(1),
                           np.full(1, -1.0), np.full(1, 1.0))


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 10_000), st.floats(-3.0, 3.0), st.floats(0.1, 3.0))
def test_never_leaves_its_box_nor_raises_the_cost(seed, centre, half):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(12, 3))
    y = rng.normal(size=12) * 5.0
    lower, upper = np.full(3, centre - half), np.full(3, centre + half)
    x0 = rng.uniform(lower, upper)
    res = gauss_newton.solve(lambda x: A @ x - y, lambda x: A, x0, lower, upper)
    assert np.all(res.x >= lower) and np.all(res.x <= upper)
    assert res.cost <= 0.5 * float(((A @ x0 - y) ** 2).sum()) + 1e-9


def test_a_relative_decrement_test_stops_where_the_absolute_one_would_go_on():
    """With residuals far above their noise (chi-square of 1e6), a step that gains a millionth of it is not worth
    taking: the relative test says converged, the absolute one alone keeps going."""
    rng = np.random.default_rng(1)
    A = rng.normal(size=(100, 2))
    y = rng.normal(size=100) * 100.0

    def fun(x):
        return A @ np.array([x[0], x[1] ** 3]) - y

    def jac(x):
        return np.column_stack([A[:, 0], A[:, 1] * 3 * x[1] ** 2])

    lo, hi = np.full(2, -10.0), np.full(2, 10.0)
    rel = gauss_newton.solve(fun, jac, np.array([0.0, 2.0]), lo, hi, relative_tol=1e-3)
    assert rel.converged and rel.reason in ("converged: relative decrement", "converged: Gauss-Newton decrement")
    assert rel.decrement < 1e-3 * 2 * rel.cost
