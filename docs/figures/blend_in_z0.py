"""Diff as returned (the blend of diff's and peak's planes) with the blend made in other coordinates.

    python docs/figures/blend_in_z0.py s1:s1_cal.json:s1_tilt.json A:A_cal.json:A_tilt.json [--mode d z zw]

For each ``NAME:CALIBRATION:FRAMES`` the mean angle (deg), axis-crossing error ``|z0 - z0_true|`` (mm), point error (mm)
and NEES per dof of what ``diff`` returns, with :func:`place_safe.recovery.blend.blended` as it is (``zw``: the state
``(n_x, n_y, z0)``, weights from the ``(n_x, n_y, d)`` covariances) or replaced by the first version's blend of
``(n_x, n_y, d)`` (``d``) or by a blend of ``(n_x, n_y, z0)`` with weights from the covariances carried there
(``z``). Frames closer than 5 cm are left out of real files (``real`` in NAME). docs/results.md, "Each frame's own
crosstalk".
"""
from __future__ import annotations

import argparse
import math

import numpy as np

import place_safe.recovery.blend as blend
import place_safe.recovery.differentiable as differentiable
from place_safe.calibration import Calibration
from place_safe.evaluation.metrics import angular_error, linear_error, point_error
from place_safe.geometry import Plane
from place_safe.io.frame_file import iter_frames
from place_safe.recovery import make_estimator
from place_safe.recovery.estimator import PlaneEstimate, is_covariance, tilt_offset


def _in_z0(e: PlaneEstimate) -> tuple[np.ndarray, np.ndarray]:
    """``e``'s state ``(n_x, n_y, z0)`` and its covariance carried there (:func:`~place_safe.recovery.blend.axis_state`)."""
    x, j = blend.axis_state(e.plane)
    return x, j @ np.asarray(e.covariance) @ j.T


def blend_in_d(a: PlaneEstimate, b: PlaneEstimate, method_used: str) -> PlaneEstimate | None:
    """The first version of the blend: ``(n_x, n_y, d)`` combined with the same weights, its bound taken there."""
    if not (a.ok and b.ok and is_covariance(a.covariance) and is_covariance(b.covariance)):
        return None
    ws = blend.blend_weights(a, b)
    if ws is None:
        return None
    w = np.array([ws[0], ws[0], ws[1]])
    x = w * tilt_offset(a.plane) + (1.0 - w) * tilt_offset(b.plane)
    s = x[0] * x[0] + x[1] * x[1]
    if not s < 1.0 - 1e-12:
        return None
    ua = w[:, None] * np.asarray(a.covariance) * w[None, :]
    ub = (1.0 - w)[:, None] * np.asarray(b.covariance) * (1.0 - w)[None, :]
    t = blend._ratio(ua, ub)
    cov = 0.5 * (ua + ua.T) * (1.0 + t) + 0.5 * (ub + ub.T) * (1.0 + 1.0 / t)
    if not is_covariance(cov, definite=True):
        return None
    return PlaneEstimate(Plane(np.array([x[0], x[1], math.sqrt(1.0 - s)]), float(x[2])), albedo=a.albedo,
                         residual=a.residual, covariance=cov, method_used=method_used)


def blend_in_z0_own_weights(a: PlaneEstimate, b: PlaneEstimate, method_used: str) -> PlaneEstimate | None:
    """The blend of ``(n_x, n_y, z0)`` as :func:`~place_safe.recovery.blend.blended` makes it, but with weights from the
    covariances carried into those coordinates."""
    if not (a.ok and b.ok and is_covariance(a.covariance) and is_covariance(b.covariance)):
        return None
    xa, ca = _in_z0(a)
    xb, cb = _in_z0(b)
    sa2, sb2 = (max(float(np.linalg.eigvalsh(c[:2, :2]).max()), 0.0) for c in (ca, cb))
    if not (sa2 + sb2 > 0.0 and ca[2, 2] + cb[2, 2] > 0.0):
        return None
    w = np.array([sb2 / (sa2 + sb2)] * 2 + [cb[2, 2] / (ca[2, 2] + cb[2, 2])])
    x = w * xa + (1.0 - w) * xb
    s = x[0] * x[0] + x[1] * x[1]
    if not s < 1.0 - 1e-12:
        return None
    nz = math.sqrt(1.0 - s)
    plane = Plane(np.array([x[0], x[1], nz]), float(x[2] * nz))
    ua = w[:, None] * ca * w[None, :]
    ub = (1.0 - w)[:, None] * cb * (1.0 - w)[None, :]
    t = blend._ratio(ua, ub)
    cz = 0.5 * (ua + ua.T) * (1.0 + t) + 0.5 * (ub + ub.T) * (1.0 + 1.0 / t)
    back = np.linalg.inv(blend.axis_state(plane)[1])
    cov = back @ cz @ back.T
    if not is_covariance(cov, definite=True):
        return None
    return PlaneEstimate(plane, albedo=a.albedo, residual=a.residual, covariance=cov, method_used=method_used)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("units", nargs="+", metavar="NAME:CALIBRATION:FRAMES")
    ap.add_argument("--mode", nargs="+", choices=("d", "z", "zw"), default=["d", "zw"],
                    help="d: the first version's blend of (n_x, n_y, d); z: of (n_x, n_y, z0) with weights from the z0 "
                         "covariances; zw: the blend as it is")
    args = ap.parse_args()
    as_is = differentiable.blended
    for mode in args.mode:
        differentiable.blended = {"zw": as_is, "d": blend_in_d, "z": blend_in_z0_own_weights}[mode]
        for item in args.units:
            name, cal, path = item.split(":")
            frames = [f for f in iter_frames(path) if f.truth is not None
                      and ("real" not in name or f.truth.offset >= 0.05)]
            est = make_estimator("diff", Calibration.load(cal)).estimate_many(frames)
            ang = np.degrees([angular_error(e.plane, f.truth) for e, f in zip(est, frames)])
            z0 = np.array([linear_error(e.plane, f.truth) for e, f in zip(est, frames)]) * 1e3
            pt = np.array([point_error(e.plane, f.truth) for e, f in zip(est, frames)]) * 1e3
            nees = []
            for e, f in zip(est, frames):
                r = tilt_offset(e.plane) - tilt_offset(f.truth)
                nees.append(float(r @ np.linalg.solve(e.covariance, r)) / 3)
            print(f"{mode:2s} {name:10s} {ang.mean():.3f} deg   z0 {z0.mean():.3f} mm   point {pt.mean():.3f} mm   "
                  f"NEES/dof {np.mean(nees):.2f}", flush=True)


if __name__ == "__main__":
    main()
