"""Two estimates of one frame's plane blended by their variances, with a covariance that holds whatever their
errors' correlation.

Concept
-------
``diff`` and ``peak`` read the same histograms in two ways: diff renders the forward model, peak finds each zone's
return. Where diff passes its fallback's gates (chi-square, consistency with peak, 5 cm and farther) the two planes
are both usable, and their errors are partly independent: on the real sweep's held-out frames their blend beat
either one (docs/results.md, "Diff and peak blended"). Each plane is the state ``x = (n_x, n_y, d)``
(:data:`~place_safe.recovery.estimator.COVARIANCE_ORDER`) with a covariance ``C``. The blend is

    x = W x_a + (I - W) x_b,   W = diag(w, w, w_d),
    w = v_b / (v_a + v_b),     w_d = C_b[d, d] / (C_a[d, d] + C_b[d, d]),

with ``v`` each estimate's tilt variance along its worst direction
(:meth:`~place_safe.recovery.estimator.PlaneEstimate.tilt_std`): the plane that reads the slope better counts more
in the tilt, the one that reads the distance better in the offset, continuously (the fallback's ``prefer_ratio``
chose one plane whole). On a tilted plane peak's stated tilt term grows with ``tan(tilt)``
(:func:`~place_safe.calibration.uncertainty.peak_tilt_term`) and the weights go to diff (about 0.99 on the simulated
units' 0-30 deg frames); on the real level table, where diff's stated tilt variance is 2-3 times peak's, ``w`` is
about 0.3. (One weight for all three, tried first, let peak's wide offset variance on tilted planes into the blend's
covariance: NEES per dof 0.17 against 0.24 on a simulated unit's tilted frames, 0.82 against 0.99 on the real odd
half; its offsets read 0.109 mm there against 0.088.)

The two errors are correlated (both read the same photons; about 0.7 on the real halves), and no frame says by how
much. So the covariance is a bound that holds for any correlation: for ``e = u + v`` (``u = W e_a``,
``v = (I - W) e_b``) and any ``t > 0``, ``e e^T <= (1 + t) u u^T + (1 + 1/t) v v^T`` (the cross term
``u v^T + v u^T <= t u u^T + v v^T / t``), so

    C = (1 + t) W C_a W + (1 + 1/t) (I - W) C_b (I - W),

with ``t = sqrt(B / A)``, ``A`` and ``B`` each term's share of the two terms' variances summed over the three
components (unit-free; it minimises that sum of the bound's shares, and for one component it makes the bound exact for
perfectly correlated errors, ``(w s_a + (1 - w) s_b)^2``). (``t`` from the tilt traces alone, tried first, blew the
offset's variance up by 1e11 where one plane's tilt was known far better and the offsets alike.) The normal is made
unit again from the blended ``(n_x, n_y)``. Units: rad and m, as the states.
"""

from __future__ import annotations

import math

import numpy as np

from place_safe.geometry import Plane
from place_safe.recovery.estimator import PlaneEstimate, is_covariance, tilt_offset

#: Weights closer to 0 or 1 than this return the one estimate unchanged (a blend that would only add rounding).
_EDGE = 1e-9


def blend_weights(a: PlaneEstimate, b: PlaneEstimate) -> tuple[float, float] | None:
    """``a``'s weights ``(w, w_d)`` in the tilt and in the offset (module doc), or None when either estimate has no
    usable covariance or both variances of a pair are 0."""
    sa, sb = a.tilt_std(), b.tilt_std()
    if sa is None or sb is None or not (sa > 0.0 or sb > 0.0):
        return None
    da, db = float(np.asarray(a.covariance)[2, 2]), float(np.asarray(b.covariance)[2, 2])
    if not (da >= 0.0 and db >= 0.0 and da + db > 0.0):
        return None
    return sb * sb / (sa * sa + sb * sb), db / (da + db)


def _ratio(ca: np.ndarray, cb: np.ndarray) -> float:
    """``t`` of the bound (module doc): ``sqrt(B / A)``, which minimises ``(1 + t) A + (1 + 1/t) B``, with ``A`` and
    ``B`` each term's share of the two terms' variance summed over the three components (a sum without units, in
    which a component neither term holds does not count); 1 where one term holds nothing."""
    da, db = np.diag(ca), np.diag(cb)
    total = da + db
    held = total > 0.0
    sa, sb = float(np.sum(da[held] / total[held])), float(np.sum(db[held] / total[held]))
    return math.sqrt(sb / sa) if sa > 0.0 and sb > 0.0 else 1.0


def blended(a: PlaneEstimate, b: PlaneEstimate, method_used: str) -> PlaneEstimate | None:
    """The blend of ``a`` and ``b`` (module doc) as ``method_used``, with ``a``'s albedo and residual; ``a`` or ``b``'s
    plane and covariance (unchanged) where both weights are within 1e-9 of 1 or of 0; None when the two cannot be
    blended (a plane missing, a covariance missing or not a covariance, or a blended covariance that is not positive
    definite)."""
    if not (a.ok and b.ok and is_covariance(a.covariance) and is_covariance(b.covariance)):
        return None
    weights = blend_weights(a, b)
    if weights is None:
        return None
    if min(weights) >= 1.0 - _EDGE:
        return a
    if max(weights) <= _EDGE:
        return PlaneEstimate(b.plane, albedo=a.albedo, residual=a.residual, covariance=b.covariance,
                             method_used=b.method_used)
    wa = np.array([weights[0], weights[0], weights[1]])
    x = wa * tilt_offset(a.plane) + (1.0 - wa) * tilt_offset(b.plane)
    s = x[0] * x[0] + x[1] * x[1]
    if not s < 1.0 - 1e-12:  # no normal with n_z > 0 (two planes far off a level one)
        return None
    normal = np.array([x[0], x[1], math.sqrt(1.0 - s)])
    ca = wa[:, None] * np.asarray(a.covariance, dtype=float) * wa[None, :]
    cb = (1.0 - wa)[:, None] * np.asarray(b.covariance, dtype=float) * (1.0 - wa)[None, :]
    t = _ratio(ca, cb)
    cov = 0.5 * (ca + ca.T) * (1.0 + t) + 0.5 * (cb + cb.T) * (1.0 + 1.0 / t)
    if not is_covariance(cov, definite=True):  # a weight that zeroes a direction both leave open: no claim to make
        return None
    return PlaneEstimate(Plane(normal, float(x[2])), albedo=a.albedo, residual=a.residual,
                         covariance=cov, method_used=method_used)


__all__ = ["blended", "blend_weights"]
