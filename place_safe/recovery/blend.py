"""Two estimates of one frame's plane blended by their variances, with a covariance that holds whatever their
errors' correlation.

Concept
-------
``diff`` and ``peak`` read the same histograms in two ways: diff renders the forward model, peak finds each zone's
return. Where diff passes its fallback's gates (chi-square, consistency with peak, 5 cm and farther) the two planes
are both usable, and their errors are partly independent: on the real sweep's held-out frames their blend beat
either one (docs/results.md, "Diff and peak blended"). Each plane has a covariance ``C`` of ``(n_x, n_y, d)``
(:data:`~place_safe.recovery.estimator.COVARIANCE_ORDER`). The blend combines the states ``x = (n_x, n_y, z0)``, where
each plane meets the optical axis (``z0 = d / n_z``, :func:`axis_state`; the covariances carried there through the
Jacobian), and carries the result back to ``(n_x, n_y, d)`` at the blended plane:

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

(Blending ``d`` instead, as the first version did, mixes on a steep plane each plane's ``d`` with its own tilt: ``d``
moves by about ``z0 sin(tilt)`` times a tilt error. On the generator's tilted frames after a level sweep diff's own
``z0`` read 0.04-0.06 mm and the blend of ``d`` 0.17-0.25 mm; blended at ``z0`` it reads 0.04 mm; level planes, where
``n_z`` is 1, are the same to 1e-3 mm: docs/results.md, "Each frame's own crosstalk". The weights stay those of the
``(n_x, n_y, d)`` covariances: taken from the ``z0`` covariances they let peak's ``z0``, stated tight on tilted planes
where it errs by millimetres, into the blend.)

The two errors are correlated (both read the same photons; about 0.7 on the real halves), and no frame says by how
much. So the covariance is a bound that holds for any correlation: for ``e = u + v`` (``u = W J_a e_a``,
``v = (I - W) J_b e_b``) and any ``t > 0``, ``e e^T <= (1 + t) u u^T + (1 + 1/t) v v^T`` (the cross term
``u v^T + v u^T <= t u u^T + v v^T / t``), so

    C_x = (1 + t) W J_a C_a J_a^T W + (1 + 1/t) (I - W) J_b C_b J_b^T (I - W),

(``J`` each plane's Jacobian of :func:`axis_state`; ``C_x`` is carried back to ``(n_x, n_y, d)`` through the inverse
of the blended plane's), with ``t = sqrt(B / A)``, ``A`` and ``B`` each term's share of the two terms' variances summed over the three
components (unit-free; it minimises that sum of the bound's shares, and for one component it makes the bound exact for
perfectly correlated errors, ``(w s_a + (1 - w) s_b)^2``). (``t`` from the tilt traces alone, tried first, blew the
offset's variance up by 1e11 where one plane's tilt was known far better and the offsets alike.) The normal is made
unit again from the blended ``(n_x, n_y)``. Units: rad and m, as the states.
"""

from __future__ import annotations

import math

import numpy as np

from place_safe.geometry import Plane
from place_safe.recovery.estimator import PlaneEstimate, is_covariance

#: Weights closer to 0 or 1 than this return the one estimate unchanged (a blend that would only add rounding).
_EDGE = 1e-9


def axis_state(plane: Plane) -> tuple[np.ndarray, np.ndarray]:
    """The state the blend combines, ``(n_x, n_y, z0)`` (``z0 = d / n_z``: where the plane meets the optical axis), of
    ``plane``, and the Jacobian ``d (n_x, n_y, z0) / d (n_x, n_y, d)`` there (3, 3), which carries a covariance of
    :data:`~place_safe.recovery.estimator.COVARIANCE_ORDER` into it."""
    nx, ny, nz = (float(v) for v in plane.normal)
    d = float(plane.offset)
    jac = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [d * nx / nz ** 3, d * ny / nz ** 3, 1.0 / nz]])
    return np.array([nx, ny, d / nz]), jac


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
    (xa, ja), (xb, jb) = axis_state(a.plane), axis_state(b.plane)
    x = wa * xa + (1.0 - wa) * xb
    s = x[0] * x[0] + x[1] * x[1]
    if not s < 1.0 - 1e-12:  # no normal with n_z > 0 (two planes far off a level one)
        return None
    nz = math.sqrt(1.0 - s)
    plane = Plane(np.array([x[0], x[1], nz]), float(x[2] * nz))
    ca = wa[:, None] * (ja @ np.asarray(a.covariance, dtype=float) @ ja.T) * wa[None, :]
    cb = (1.0 - wa)[:, None] * (jb @ np.asarray(b.covariance, dtype=float) @ jb.T) * (1.0 - wa)[None, :]
    t = _ratio(ca, cb)
    bound = 0.5 * (ca + ca.T) * (1.0 + t) + 0.5 * (cb + cb.T) * (1.0 + 1.0 / t)
    back = np.linalg.inv(axis_state(plane)[1])  # (n_x, n_y, z0) -> (n_x, n_y, d) at the blended plane
    cov = back @ bound @ back.T
    cov = 0.5 * (cov + cov.T)
    if not is_covariance(cov, definite=True):  # a weight that zeroes a direction both leave open: no claim to make
        return None
    return PlaneEstimate(plane, albedo=a.albedo, residual=a.residual, covariance=cov, method_used=method_used)


__all__ = ["blended", "blend_weights", "axis_state"]
