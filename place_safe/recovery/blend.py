"""Two estimates of one frame's plane blended by their tilt variances, with a covariance that holds whatever their
errors' correlation.

Concept
-------
``diff`` and ``peak`` read the same histograms in two ways: diff renders the forward model, peak finds each zone's
return. Where diff passes its fallback's gates (chi-square, consistency with peak, 5 cm and farther) the two planes
are both usable, and their errors are partly independent: on the real sweep's held-out frames their average beat
either one (docs/results.md, "Diff and peak blended"). Each plane is the state ``x = (n_x, n_y, d)``
(:data:`~place_safe.recovery.estimator.COVARIANCE_ORDER`) with a covariance ``C``. The blend is

    x = w x_a + (1 - w) x_b,   w = v_b / (v_a + v_b),

with ``v`` each estimate's tilt variance along its worst direction
(:meth:`~place_safe.recovery.estimator.PlaneEstimate.tilt_std`): one scalar weight, so the plane that reads the
slope better counts more, continuously (the fallback's ``prefer_ratio`` chose one of the two). On a tilted plane
peak's stated tilt term grows with ``tan(tilt)`` (:func:`~place_safe.calibration.uncertainty.peak_tilt_term`) and
the weight goes to diff (about 0.99 on the simulated units' 0-30 deg frames); on the real level table, where diff's
stated tilt variance is 2-3 times peak's, it is about 0.3.

The two errors are correlated (both read the same photons; about 0.7 on the real halves), and no frame says by how
much. So the covariance is a bound that holds for any correlation: for ``e = w e_a + (1 - w) e_b`` and any
``t > 0``, ``e e^T <= (1 + t) w^2 e_a e_a^T + (1 + 1/t) (1 - w)^2 e_b e_b^T`` (the cross term
``u v^T + v u^T <= t u u^T + v v^T / t``), so

    C = (1 + t) w^2 C_a + (1 + 1/t) (1 - w)^2 C_b,

with ``t`` the square root of the ratio of the two terms' tilt traces, which makes it exact for perfectly correlated
scalar errors (``(w s_a + (1 - w) s_b)^2``) and its tilt trace never larger than that of ``w C_a + (1 - w) C_b``
(the bound with ``t = (1 - w) / w``). The normal is made unit again from the blended ``(n_x, n_y)``. Units: rad and m,
as the states.
"""

from __future__ import annotations

import math

import numpy as np

from place_safe.geometry import Plane
from place_safe.recovery.estimator import PlaneEstimate, tilt_offset

#: Weights closer to 0 or 1 than this return the one estimate unchanged (a blend that would only add rounding).
_EDGE = 1e-9


def blend_weight(a: PlaneEstimate, b: PlaneEstimate) -> float | None:
    """``a``'s weight ``v_b / (v_a + v_b)`` from the two estimates' worst-axis tilt variances, or None when either
    has no usable covariance or both variances are 0."""
    sa, sb = a.tilt_std(), b.tilt_std()
    if sa is None or sb is None or not (sa > 0.0 or sb > 0.0):
        return None
    return sb * sb / (sa * sa + sb * sb)


def blended(a: PlaneEstimate, b: PlaneEstimate, method_used: str) -> PlaneEstimate | None:
    """The blend of ``a`` and ``b`` (module doc) as ``method_used``, with ``a``'s albedo and residual; ``a`` or ``b``
    itself (unchanged) where the weight is within 1e-9 of 1 or 0; None when the two cannot be blended (a plane or a
    usable covariance missing)."""
    if not (a.ok and b.ok) or a.covariance is None or b.covariance is None:
        return None
    w = blend_weight(a, b)
    if w is None:
        return None
    if w >= 1.0 - _EDGE:
        return a
    if w <= _EDGE:
        return PlaneEstimate(b.plane, albedo=a.albedo, residual=a.residual, covariance=b.covariance,
                             method_used=b.method_used)
    x = w * tilt_offset(a.plane) + (1.0 - w) * tilt_offset(b.plane)
    s = x[0] * x[0] + x[1] * x[1]
    if not s < 1.0 - 1e-12:  # no normal with n_z > 0 (two planes far off a level one)
        return None
    normal = np.array([x[0], x[1], math.sqrt(1.0 - s)])
    ca, cb = w * w * np.asarray(a.covariance, dtype=float), (1.0 - w) ** 2 * np.asarray(b.covariance, dtype=float)
    ta, tb = float(np.trace(ca[:2, :2])), float(np.trace(cb[:2, :2]))
    if not (ta > 0.0 and tb > 0.0):
        return None
    t = math.sqrt(tb / ta)
    cov = (1.0 + t) * ca + (1.0 + 1.0 / t) * cb
    return PlaneEstimate(Plane(normal, float(x[2])), albedo=a.albedo, residual=a.residual,
                         covariance=0.5 * (cov + cov.T), method_used=method_used)


__all__ = ["blended", "blend_weight"]
