"""A bounded Levenberg-Marquardt solver that stops on a convergence test and says why.

Concept: minimise ``cost(x) = 0.5 * |r(x)|^2`` over a box ``lower <= x <= upper`` for residuals ``r`` that are
scaled to unit noise (Poisson-scaled histogram bins), given ``r`` and its exact Jacobian ``J``. Each
iteration solves the damped normal equations ``(J^T J + lambda D^2) dx = -J^T r`` on the free unknowns
(Marquardt's scaling ``D`` = the largest column norms of ``J`` seen so far, so the step does not depend on
units); unknowns at a bound whose gradient points out of the box are held there for the step. A step is
kept when it lowers the cost; ``lambda`` follows the gain ratio (actual / predicted decrease; Nielsen's
update).

Stopping (``Result.reason``):

``"converged: Gauss-Newton decrement"``
    The full Gauss-Newton step from the current point, kept in the box, would lower chi-square (``2 cost``) by
    less than
    ``decrement_tol`` times the reduced chi-square: the remaining step moves the unknowns by less than
    ``sqrt(decrement_tol)`` of their standard deviation (the Fisher metric ``J^T J`` scaled by the fit's
    reduced chi-square). The test of a minimum that a statistician would ask for.
``"converged: relative decrement"``
    That step would lower chi-square by less than ``relative_tol`` of itself (off by default), and the reduced
    chi-square is above :data:`RELATIVE_MIN_CHI2`. Where the model
    does not describe the data to their noise (a reduced chi-square of 9 on a real sensor), a tenth of a
    standard deviation of shot noise is far below what the model's own error moves the parameters: a fit that
    can still gain 0.01 % of its chi-square has nothing left that matters.
``"converged: cost change"``
    Three accepted steps in a row each lowered chi-square by less than ``decrement_tol`` times the
    reduced chi-square (or, above :data:`CRAWL_MIN_CHI2`, by less than ``relative_tol`` of chi-square: a fit
    whose predicted decrement stays large while its steps gain nothing, e.g. the real sweep crawling for 40
    iterations at an unchanged RMS) (the decrement test cannot pass where the cost has a kink, e.g. a pulse resampled
    by linear interpolation: the gradient does not vanish there, the cost no longer moves).
``"not converged: no step lowers the cost"``
    ``lambda`` exceeded ``1e12`` without a step that lowers the cost and the decrement test failed.
``"not converged: iteration limit"``
    ``max_iterations`` Jacobians were evaluated.

Units: those of ``x`` (the caller's fit coordinates, e.g. logs of positive quantities).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

#: Chi-square decrease (times the reduced chi-square) below which the fit is converged: 0.01, a step of a
#: tenth of a standard deviation.
DECREMENT_TOL = 0.01
#: Reduced chi-square above which the relative test (``relative_tol``) applies: residuals twice their noise (RMS
#: 2) mean a model that does not describe the data; below it the absolute test alone decides.
RELATIVE_MIN_CHI2 = 4.0
#: Reduced chi-square above which the "cost change" test also counts gains below ``relative_tol`` of chi-square as
#: small (a crawl): the mismatched simulated unit's level sweep (reduced chi-square 1.9) moved its RMS from 1.3735 to
#: 1.369 in 60 iterations without the decrement test passing. The decrement test keeps :data:`RELATIVE_MIN_CHI2`.
CRAWL_MIN_CHI2 = 1.5
#: Damping above which no step is tried any more (the trust region is a point).
MAX_DAMPING = 1e12


@dataclass
class Result:
    """Where :func:`solve` stopped: unknowns ``x``, residuals ``fun``, ``cost`` (0.5 |r|^2), whether it
    ``converged`` and the ``reason`` (see the module doc), Jacobians (``iterations``) and residual
    evaluations (``evaluations``) spent, and the last Gauss-Newton ``decrement`` (chi-square units)."""

    x: np.ndarray
    fun: np.ndarray
    jac: np.ndarray
    cost: float
    converged: bool
    reason: str
    iterations: int
    evaluations: int
    decrement: float
    history: list[float] = field(default_factory=list)


def _free(x: np.ndarray, g: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Unknowns that may move: not at a bound whose descent direction (-g) points out of the box."""
    span = np.where(np.isfinite(upper - lower), upper - lower, 1.0)
    eps = 1e-10 * np.maximum(span, 1.0)
    at_lo = (x <= lower + eps) & (g > 0)
    at_hi = (x >= upper - eps) & (g < 0)
    return ~(at_lo | at_hi)


def _box_step(x: np.ndarray, g: np.ndarray, jtj: np.ndarray, damp: np.ndarray, free: np.ndarray,
              lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """The damped Gauss-Newton step ``(J^T J + diag(damp)) dx = -g`` on the ``free`` unknowns, kept in the box: an
    unknown whose step would leave it moves to its bound and is held there while the others are solved again
    (a few rounds), so a bound does not cut the step short in a direction the model did not predict."""
    dx = np.zeros_like(x)
    held = ~free
    for _ in range(4):
        f = ~held
        if not f.any():
            break
        a = jtj[np.ix_(f, f)] + np.diag(damp[f])
        rhs = -g[f] - jtj[np.ix_(f, held)] @ dx[held]
        dx[f] = _solve_spd(a, rhs)
        target = x + dx
        out = f & ((target < lower) | (target > upper))
        if not out.any():
            break
        dx[out] = np.clip(target[out], lower[out], upper[out]) - x[out]
        held = held | out
    return dx


def _solve_spd(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    try:
        c = np.linalg.cholesky(a)
        return np.linalg.solve(c.T, np.linalg.solve(c, b))
    except np.linalg.LinAlgError:
        return np.linalg.lstsq(a, b, rcond=None)[0]


def solve(fun: Callable[[np.ndarray], np.ndarray], jac: Callable[[np.ndarray], np.ndarray], x0: np.ndarray,
          lower: np.ndarray, upper: np.ndarray, max_iterations: int = 60,
          decrement_tol: float = DECREMENT_TOL, damping: float = 1e-3, relative_tol: float = 0.0,
          log: Callable[[str], None] | None = None) -> Result:
    """Minimise ``0.5 |fun(x)|^2`` on ``[lower, upper]`` from ``x0`` (clipped into the box)."""
    lower = np.asarray(lower, dtype=float)
    upper = np.asarray(upper, dtype=float)
    x = np.clip(np.asarray(x0, dtype=float), lower, upper)
    r = fun(x)
    evals = 1
    cost = 0.5 * float(r @ r)
    if not math.isfinite(cost):
        raise ArithmeticError("the residuals at the start are not finite")
    dof = max(r.size - x.size, 1)
    scale = np.zeros(x.size)
    lam, nu = damping, 2.0
    small = 0
    history = [cost]
    decrement = math.inf
    reason = "not converged: iteration limit"
    converged = False
    J = None
    iterations = 0
    need_jac = True
    while iterations < max_iterations:
        if need_jac:
            J = jac(x)
            iterations += 1
            jtj = J.T @ J
            g = J.T @ r
            scale = np.maximum(scale, np.sqrt(np.maximum(np.diag(jtj), 0.0)))
            # an unknown the residuals do not depend on (a column of zeros) is damped as hard as the stiffest one,
            # so it stays where it is instead of making the system singular
            top = float(scale.max()) if scale.size else 1.0
            scale = np.where(scale > 1e-12 * top, scale, max(top, 1.0))
            need_jac = False
        free = _free(x, g, lower, upper)
        chi2_red = max(2.0 * cost / dof, 1.0)
        # chi-square decrease the quadratic model predicts for the full Gauss-Newton step kept in the box; far
        # from the minimum the box can turn that step into one the model does not see descend (<= 0): then the
        # decrease of the step on the free unknowns without the box, which is never smaller
        gn = _box_step(x, g, jtj, 1e-9 * scale ** 2, free, lower, upper)
        decrement = 2.0 * (-(g @ gn) - 0.5 * float(gn @ jtj @ gn))
        if not decrement > 0.0:
            a = jtj[np.ix_(free, free)]
            decrement = float(-g[free] @ _solve_spd(a + 1e-9 * np.diag(scale[free] ** 2), -g[free])) if free.any() else 0.0
        if log is not None:
            log(f"iteration {iterations}: cost {cost:.6g}, decrement {decrement:.4g}, damping {lam:.3g}, "
                f"held {np.flatnonzero(~free).tolist()}")
        if decrement < decrement_tol * chi2_red:
            converged, reason = True, "converged: Gauss-Newton decrement"
            break
        if chi2_red > RELATIVE_MIN_CHI2 and decrement < relative_tol * 2.0 * cost:
            converged, reason = True, "converged: relative decrement"
            break
        accepted = False
        while lam <= MAX_DAMPING:
            dx = _box_step(x, g, jtj, lam * scale ** 2, free, lower, upper)
            xn = np.clip(x + dx, lower, upper)
            dx = xn - x
            predicted = -(g @ dx) - 0.5 * float(dx @ jtj @ dx)
            rn = fun(xn)
            evals += 1
            cn = 0.5 * float(rn @ rn)
            if math.isfinite(cn) and cn < cost:
                rho = (cost - cn) / predicted if predicted > 0 else 0.0
                lam *= max(1.0 / 3.0, 1.0 - (2.0 * rho - 1.0) ** 3)
                nu = 2.0
                gain = 2.0 * (cost - cn)
                least = decrement_tol * chi2_red
                if chi2_red > CRAWL_MIN_CHI2:  # a model that does not fit to the noise: gains relative to chi-square
                    least = max(least, relative_tol * 2.0 * cost)
                small = small + 1 if gain < least else 0
                x, r, cost = xn, rn, cn
                history.append(cost)
                accepted = need_jac = True
                break
            lam *= nu
            nu *= 2.0
        if not accepted:
            reason = "not converged: no step lowers the cost"
            break
        if small >= 3:
            converged, reason = True, "converged: cost change"
            break
    if need_jac:  # the Jacobian at the returned point (for the covariance)
        J = jac(x)
    return Result(x=x, fun=r, jac=J, cost=cost, converged=converged, reason=reason, iterations=iterations,
                  evaluations=evals, decrement=decrement, history=history)


def covariance(J: np.ndarray, cost: float, n_params: int | None = None) -> np.ndarray:
    """Covariance of the unknowns at a solution: ``(J^T J)^-1`` scaled by the reduced chi-square (when above 1:
    residuals larger than their noise widen it). Unknowns the data do not determine get infinite variance
    (pseudo-inverse with eigenvalues below 1e-12 of the largest dropped, reported as inf)."""
    n = J.shape[1] if n_params is None else n_params
    dof = max(J.shape[0] - J.shape[1], 1)
    chi2_red = max(2.0 * cost / dof, 1.0)
    jtj = J.T @ J
    w, v = np.linalg.eigh(jtj)
    keep = w > 1e-12 * max(w[-1], 1e-300)
    inv = (v[:, keep] / w[keep]) @ v[:, keep].T
    cov = inv * chi2_red
    lost = (v[:, ~keep] ** 2).sum(axis=1) > 1e-6
    cov[lost, :] = np.inf
    cov[:, lost] = np.inf
    return cov[:n, :n]
