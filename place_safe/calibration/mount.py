"""Hand-eye calibration of the sensor mount: ``flange_T_sensor`` (6 DoF) and the plane, from a capture.

Concept: a capture (:mod:`place_safe.calibration.capture`, or the shared real sweep) gives, per frame,
the flange pose ``base_T_flange_i`` (forward kinematics of the recorded joint angles, or the recorded
pose) and the plane the sensor saw, estimated from the histograms in the sensor frame ``(n_i, d_i)``.
One unknown plane ``n_b . x = d_b`` in the base frame and one unknown mount ``M = flange_T_sensor``
explain all frames: ``n_i = -(R_i R_M)^T n_b`` and ``d_i = -(d_b - n_b . (p_i + R_i t_M))``.
:func:`fit_mount` solves for ``M`` and the plane by nonlinear least squares (``scipy.optimize.least_squares``,
soft-L1 loss against outlier frames), after Sifferman et al., RA-L 2022.

Frames whose residual lies beyond :data:`OUTLIER_K` robust standard deviations (a wrong plane estimate)
are left out and the fit repeated. Uncertainty: the Gauss-Newton covariance ``(J^T J)^-1`` scaled by the
reduced chi-square. A first fit with a
moderate prior around the starting mount (5 cm, 0.2 rad) finds the directions the sweep does not observe
(parameter sigma above half the prior's); the final fit holds those at the start with that prior (and, refitted,
any it then states more loosely than :data:`MAX_SIGMA_ROTATION` / :data:`MAX_SIGMA_TRANSLATION`) and
leaves every other direction to the data (``prior_translation`` 1 m, ``prior_rotation`` 1 rad: a stronger
prior would pull weakly observed directions). Held directions -- e.g. the mount's x/y offset when the
sensor only moves straight down over a level table -- are listed in :attr:`MountFit.unobserved`.

Conventions: SI units inside (m, rad), mm and degrees in :meth:`MountFit.summary`. Rotations of the
mount are rotation vectors applied on the left of the starting rotation; ``rpy`` is fixed-axis x-y-z.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from typing import Any, Sequence

import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from place_safe.exceptions import CalibrationError
from place_safe.geometry import MAX_REACH, Plane, transform_problem
from place_safe.robot.kinematics import Kinematics

#: Fraction of the prior sigma above which a direction counts as not observed by the sweep.
UNOBSERVED = 0.5
#: Typical size of each parameter's change (rad, m, plane tilt, m): fixed, so that a direction the data does
#: not constrain is not stretched by a near-zero Jacobian column.
_X_SCALE = np.array([0.02, 0.02, 0.02, 0.005, 0.005, 0.005, 0.02, 0.02, 0.005])
#: Stage-1 prior (rad, m) around the starting mount, used to find unobserved directions and to hold them.
_STAGE1_ROT, _STAGE1_TRANS = 0.2, 0.05
#: Sigma (rad, m) that holds an unobserved direction at its starting value in the final fit.
_HOLD_ROT, _HOLD_TRANS = 1e-3, 1e-4
#: Floors of the noise weights (rad, m): of those taken from the residuals' robust scatter (exact data stays finite),
#: and the smallest per-frame noise :func:`fit_mount` (``calibrate-mount --sigma-angle`` / ``--sigma-mm``) takes to start
#: with: 1e-20 deg ended "mount fit did not converge", 1e-160 deg "array must not contain infs or NaNs" (the weighted
#: residuals overflowed), neither naming the option (session 82).
MIN_SIGMA_ANGLE, MIN_SIGMA_DISTANCE = 1e-5, 1e-6
#: Sigma (rad or m) of the rows that hold a known plane tilt or offset.
_KNOWN = 1e-7
#: Frames whose residual exceeds this many robust standard deviations are left out of the final fit.
OUTLIER_K = 4.0
#: rad, m: the largest residual RMS (normal angle; plane distance) of a fit good enough to use, e.g. to write
#: into a robot file (``calibrate-mount --write`` refuses beyond them): the per-frame noise the command assumes by
#: default (``--sigma-angle`` 1 deg, ``--sigma-mm`` 2 mm). A good fit stays well inside: 0.04 deg / 0.02 mm (diff
#: on a simulated capture), 0.32 deg / 0.18-0.34 mm (calibrated peak, simulated capture and the real sweep:
#: docs/results.md); planes of an uncalibrated estimator read 5.6-5.8 deg / 2.6-3.1 mm on the real sweep, and
#: flange poses that do not belong to the frames tens of degrees.
MAX_RMS_ANGLE, MAX_RMS_DISTANCE = math.radians(1.0), 0.002
#: rad, m: the largest 1-sigma of a mount direction the final fit leaves to the data, where its residuals are within
#: :data:`MAX_RMS_ANGLE` and :data:`MAX_RMS_DISTANCE`; one the capture determines only more loosely is held at the
#: start as well (listed in :attr:`MountFit.unobserved`). The stage-1 test (a sigma above half the prior's) keeps
#: directions observed to 0.1 rad or 25 mm: a straight-down sweep whose flange tilt wanders by
#: a few tenths of a degree, as the real sweep's does, then fitted the mount's tilt from it to 10.9 / 2.9 deg and its
#: height to 42 mm 1-sigma with ``--table-height`` alone, and moved the mount by 234 mm. Good fits state far less
#: (0.02 deg for the real sweep's tilt with ``--level``).
MAX_SIGMA_ROTATION, MAX_SIGMA_TRANSLATION = math.radians(1.0), 0.005
#: The mount's six parameters, in the order of the fit's rotation-vector and translation components: the names
#: :attr:`MountFit.unobserved` lists.
MOUNT_PARAMETERS = ("rotation about x", "rotation about y", "rotation about z", "translation x", "translation y",
                    "translation z")


@dataclass
class MountFit:
    """Result of :func:`fit_mount` (SI units)."""

    flange_T_sensor: np.ndarray  # 4x4
    plane_normal: np.ndarray  # base frame, up
    plane_offset: float  # m
    sigma_xyz: np.ndarray  # m, 1-sigma of the mount translation (NaN: held, see unobserved)
    sigma_rot: np.ndarray  # rad, 1-sigma of the mount rotation (rotation-vector components; NaN: held)
    rms_angle: float  # rad, RMS of the normal residuals
    rms_distance: float  # m, RMS of the offset residuals
    residuals_angle: np.ndarray  # rad per frame
    residuals_distance: np.ndarray  # m per frame
    frames: int
    unobserved: list[str] = field(default_factory=list)  # mount components the sweep did not determine
    start: np.ndarray | None = None  # the starting mount
    outliers: int = 0  # frames left out (residual beyond OUTLIER_K robust sigmas); residual arrays hold all

    @property
    def xyz(self) -> np.ndarray:
        return self.flange_T_sensor[:3, 3].copy()

    @property
    def rpy(self) -> np.ndarray:
        return Rotation.from_matrix(self.flange_T_sensor[:3, :3]).as_euler("xyz")

    def change(self) -> tuple[float, float]:
        """(m, rad) between the starting and the fitted mount."""
        if self.start is None:
            return math.nan, math.nan
        E = np.linalg.inv(self.start) @ self.flange_T_sensor
        return float(np.linalg.norm(self.flange_T_sensor[:3, 3] - self.start[:3, 3])), \
            float(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))

    def error_to(self, truth: np.ndarray) -> tuple[float, float]:
        """(m, rad) from the fitted mount to ``truth``."""
        E = np.linalg.inv(truth) @ self.flange_T_sensor
        return float(np.linalg.norm(self.flange_T_sensor[:3, 3] - truth[:3, 3])), \
            float(np.linalg.norm(Rotation.from_matrix(E[:3, :3]).as_rotvec()))

    def to_dict(self) -> dict[str, Any]:
        dt, dr = self.change()
        return {"flange_T_sensor": self.flange_T_sensor.tolist(), "xyz": self.xyz.tolist(), "rpy": self.rpy.tolist(),
                "sigma_xyz": [None if v != v else float(v) for v in self.sigma_xyz],
                "sigma_rot": [None if v != v else float(v) for v in self.sigma_rot],
                "plane_normal": self.plane_normal.tolist(), "plane_offset": self.plane_offset,
                "rms_angle": self.rms_angle, "rms_distance": self.rms_distance, "frames": self.frames,
                "unobserved": list(self.unobserved), "outliers": self.outliers, "change_translation": dt, "change_rotation": dr,
                "residuals_angle": self.residuals_angle.tolist(),
                "residuals_distance": self.residuals_distance.tolist()}

    @property
    def determines_nothing(self) -> bool:
        """Whether the sweep determined none of the mount's six parameters (all of :data:`MOUNT_PARAMETERS` held at
        the start): the fitted mount is the starting one, whatever its residuals."""
        return set(MOUNT_PARAMETERS) <= set(self.unobserved)

    def quality_problem(self) -> str | None:
        """Why the fit is too poor to use -- ``"residual RMS 28.32 deg (normal) > 1 deg"`` (its residuals beyond
        :data:`MAX_RMS_ANGLE` or :data:`MAX_RMS_DISTANCE`) -- or None."""
        over = []
        if not self.rms_angle <= MAX_RMS_ANGLE:  # NaN too
            over.append(f"{math.degrees(self.rms_angle):.2f} deg (normal) > {math.degrees(MAX_RMS_ANGLE):g} deg")
        if not self.rms_distance <= MAX_RMS_DISTANCE:
            over.append(f"{self.rms_distance * 1000:.2f} mm (distance) > {MAX_RMS_DISTANCE * 1000:g} mm")
        return "residual RMS " + " and ".join(over) if over else None

    def summary(self) -> str:
        mm, deg = 1000.0, math.degrees(1.0)
        dt, dr = self.change()
        lines = [f"mount fit on {self.frames} frames ({self.outliers} outliers left out): residual RMS {self.rms_angle * deg:.2f} deg (normal), "
                 f"{self.rms_distance * mm:.2f} mm (distance)",
                 "  flange_T_sensor xyz [mm]: " + ", ".join(f"{v * mm:8.2f} " + (f"+- {s * mm:.2f}" if s == s else "(held)")
                                                             for v, s in zip(self.xyz, self.sigma_xyz)),
                 "  flange_T_sensor rpy [deg]: " + ", ".join(f"{v * deg:7.2f}" for v in self.rpy)
                 + "  (rotation 1-sigma " + ", ".join(f"{s * deg:.2f}" if s == s else "held" for s in self.sigma_rot)
                 + " deg)",
                 f"  plane in base: normal {np.round(self.plane_normal, 4).tolist()}, offset {self.plane_offset * mm:.2f} mm",
                 f"  change from the starting mount: {dt * mm:.2f} mm, {dr * deg:.2f} deg"]
        if self.unobserved:
            lines.append("  not determined by this sweep (kept at the start value by the prior): "
                         + ", ".join(self.unobserved))
        return "\n".join(lines)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _plane_basis(n0: np.ndarray) -> np.ndarray:
    """Rotation whose third column is ``n0`` (parametrises plane normals as tilts around n0)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n0[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = _unit(np.cross(a, n0))
    return np.column_stack([e1, np.cross(n0, e1), n0])


def fit_mount(base_T_flange: Sequence[np.ndarray], planes: Sequence[Plane | None], start: np.ndarray, *,
              sigma_angle: float = math.radians(1.0), sigma_distance: float = 0.002,
              prior_translation: float = 1.0, prior_rotation: float = 1.0,
              loss: str = "soft_l1", level: bool = False, plane_offset: float | None = None) -> MountFit:
    """Fit ``flange_T_sensor`` and the plane (see module docstring).

    ``base_T_flange``: (N, 4, 4) flange poses. ``planes``: the estimated sensor-frame plane per frame
    (None for frames without one: skipped). ``start``: the starting mount (nominal or current).
    ``sigma_angle`` (rad) / ``sigma_distance`` (m): starting guesses of the per-frame noise of the plane
    estimates; after a first fit both kinds of residual are weighed by their robust scatter, and the
    reported uncertainty is rescaled by the fit's own chi-square. ``level``: the plane's normal is the
    base z axis (a level table); ``plane_offset``: its offset is known (m, e.g. a measured table height).
    A straight-down sweep needs both to observe the mount's tilt and height at all: without them a mount
    tilt looks like a plane tilt and a mount height like a plane height.
    """
    for name, value, floor, unit in (("sigma_angle", sigma_angle, MIN_SIGMA_ANGLE, "rad"),
                                     ("sigma_distance", sigma_distance, MIN_SIGMA_DISTANCE, "m")):
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not floor <= value < math.inf:
            raise CalibrationError(f"fit_mount: {name} must be a finite number of {unit} >= {floor:g} (the per-frame "
                                   f"noise the fit starts from), got {value!r}")
    F = np.asarray(base_T_flange, dtype=float)
    if F.ndim != 3 or F.shape[1:] != (4, 4) or len(F) != len(planes):
        raise CalibrationError(f"need one 4x4 flange pose per plane; got poses {F.shape} and {len(planes)} planes")
    keep = [i for i, p in enumerate(planes) if p is not None and np.all(np.isfinite(F[i]))]
    if len(keep) < 6:
        raise CalibrationError(f"a mount fit needs at least 6 frames with a plane; got {len(keep)}")
    F = F[keep]
    ns = np.array([planes[i].normal for i in keep])
    ds = np.array([planes[i].offset for i in keep])
    start = np.asarray(start, dtype=float)
    R0, t0 = start[:3, :3], start[:3, 3]
    # starting plane: every frame's plane moved to the base frame with the starting mount, averaged
    RS = F[:, :3, :3] @ R0
    pS = F[:, :3, 3] + F[:, :3, :3] @ t0
    nb = -np.einsum("nij,nj->ni", RS, ns)  # sensor-frame normal points away from the sensor: base "up" is -R n
    n0 = np.array([0.0, 0.0, 1.0]) if level else _unit(nb.mean(axis=0))
    d0 = float(np.mean(np.einsum("i,ni->n", n0, pS) - ds)) if plane_offset is None else float(plane_offset)
    B = _plane_basis(n0)

    def unpack(x: np.ndarray):
        Rm = Rotation.from_rotvec(x[:3]).as_matrix() @ R0
        tm = t0 + x[3:6]
        n = B @ _unit(np.array([x[6], x[7], 1.0]))
        return Rm, tm, n, x[8]

    def frame_residuals(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(normal residuals (N, 3), offset residuals (N,)) of every frame, SI units."""
        Rm, tm, n, d = unpack(x)
        R = F[:, :3, :3] @ Rm
        p = F[:, :3, 3] + F[:, :3, :3] @ tm
        n_pred = -np.einsum("nji,j->ni", R, n)  # -(R^T n)
        d_pred = -(d - p @ n)
        return n_pred - ns, d_pred - ds

    def residuals(x: np.ndarray, use: np.ndarray, prior: np.ndarray) -> np.ndarray:
        rn, rd = frame_residuals(x)
        known = []
        if level:
            known += [x[6] / _KNOWN, x[7] / _KNOWN]
        if plane_offset is not None:
            known.append((x[8] - plane_offset) / _KNOWN)
        return np.concatenate([(rn[use] / sigma_angle).ravel(), rd[use] / sigma_distance, x[:6] / prior, known])

    def solve(x0: np.ndarray, use: np.ndarray, prior: np.ndarray):
        for _ in range(3):  # fit, drop frames far off the robust spread of the residuals, refit
            sol = least_squares(lambda x: residuals(x, use, prior), x0, loss=loss, f_scale=3.0, x_scale=_X_SCALE,
                                max_nfev=1000)
            if sol.status <= 0:
                raise CalibrationError(f"mount fit did not converge: {sol.message}")
            rn_all, rd_all = frame_residuals(sol.x)
            ang_all = np.linalg.norm(rn_all, axis=1)
            ok = (ang_all <= max(OUTLIER_K * _robust_scale(ang_all[use]), sigma_angle)) & \
                (np.abs(rd_all) <= max(OUTLIER_K * _robust_scale(rd_all[use]), sigma_distance))
            if np.array_equal(ok, use) or ok.sum() < 6:
                break
            use, x0 = ok, sol.x
        return sol, use

    def info_sigma(x: np.ndarray, use: np.ndarray, prior: np.ndarray) -> np.ndarray:
        """1-sigma of each parameter from the plain (not loss-weighted) Jacobian, in units of the noise
        weights (prior rows included, so a direction no frame constrains gets the prior's sigma)."""
        h = 1e-6
        J = np.column_stack([(residuals(x + h * e, use, prior) - residuals(x - h * e, use, prior)) / (2 * h)
                             for e in np.eye(len(x))])
        return np.sqrt(np.clip(np.diag(np.linalg.pinv(J.T @ J)), 0.0, None))

    x0 = np.zeros(9)
    x0[8] = d0
    nf = len(keep)
    # stage 1: a moderate prior finds the directions the sweep does not observe; stage 2 lets the data
    # alone decide every other direction (a prior would pull weakly observed ones) and holds those
    prior1 = np.array([_STAGE1_ROT] * 3 + [_STAGE1_TRANS] * 3)
    sol, use = solve(x0, np.ones(nf, dtype=bool), prior1)
    # weigh the residuals by the data's own robust scatter (the given sigmas only start the fit)
    rn1, rd1 = frame_residuals(sol.x)
    sigma_angle = max(_robust_scale(rn1[use].ravel()), MIN_SIGMA_ANGLE)
    sigma_distance = max(_robust_scale(rd1[use]), MIN_SIGMA_DISTANCE)
    sol, use = solve(sol.x, use, prior1)
    null = info_sigma(sol.x, use, prior1)[:6] > UNOBSERVED * prior1
    x1, use1 = sol.x, use
    limit = np.array([MAX_SIGMA_ROTATION] * 3 + [MAX_SIGMA_TRANSLATION] * 3)
    while True:  # stage 2; a direction the data then state more loosely than the limits is held too, and refitted
        prior2 = np.where(null, np.array([_HOLD_ROT] * 3 + [_HOLD_TRANS] * 3),
                          np.array([prior_rotation] * 3 + [prior_translation] * 3))
        sol, use = solve(x1, use1, prior2)
        m = int(use.sum())
        r = residuals(sol.x, use, prior2)
        chi2 = float(np.sum(r[:4 * m] ** 2)) / max(4 * m - 9, 1)
        sig = info_sigma(sol.x, use, prior2) * math.sqrt(max(chi2, 1e-12))
        rn_all, rd_all = frame_residuals(sol.x)
        ang_all = np.linalg.norm(rn_all, axis=1)  # small-angle: |n_pred - n| ~ angle
        # only in a fit whose residuals are a good fit's: where the frames disagree (poses that are not the frames')
        # every sigma is large, and that is a poor fit, said by its residuals, not a capture that observes nothing
        rms_angle, rms_distance = (float(np.sqrt(np.mean(v[use] ** 2))) for v in (ang_all, rd_all))
        weak = ~null & (sig[:6] > limit) & (rms_angle <= MAX_RMS_ANGLE) & (rms_distance <= MAX_RMS_DISTANCE)
        if not weak.any():
            break
        null = null | weak
        x1 = np.where(np.concatenate([null, np.zeros(3, bool)]), 0.0, sol.x)  # held ones back at the start
    Rm, tm, n, d = unpack(sol.x)
    sig[:6][null] = math.nan  # held at the start: no uncertainty from this sweep
    unobserved = [name for name, held in zip(MOUNT_PARAMETERS, null) if held]
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = Rm, tm
    return MountFit(M, n, float(d), sig[3:6], sig[:3], rms_angle, rms_distance, ang_all, rd_all, m, unobserved,
                    start.copy(), outliers=int(nf - m))


def _robust_scale(v: np.ndarray) -> float:
    """1.4826 x the median absolute deviation from zero (residuals are centred on zero)."""
    return 1.4826 * float(np.median(np.abs(v))) if len(v) else 0.0


class FlangePoseError(CalibrationError):
    """A frame without a usable flange pose; ``kind`` says why in a few words (``"bad joint_angles"``, ``"bad pose"``,
    ``"no joint_angles or pose"``), for a caller that skips and counts such frames."""

    def __init__(self, message: str, kind: str) -> None:
        super().__init__(message)
        self.kind = kind


def flange_poses(frames: Sequence[Any], use_kinematics: bool = True, kinematics: Any = None) -> np.ndarray:
    """base_T_flange per frame: forward kinematics of ``joint_angles`` (default) or the recorded ``pose``;
    :class:`FlangePoseError` for the first frame without a usable one."""
    out = []
    kin = kinematics
    for i, f in enumerate(frames):
        extra = f.extra if hasattr(f, "extra") else f
        if use_kinematics and extra.get("joint_angles") is not None:
            if kin is None:
                kin = Kinematics()
            out.append(kin.base_T_flange(_joint_angles(extra["joint_angles"], i)))
        elif extra.get("pose") is not None:
            T = extra["pose"]
            if (why := transform_problem(T, reach=MAX_REACH)) is not None:
                raise FlangePoseError(f"frame {i}: pose {why}; expected the flange's rigid base-frame transform (m)",
                                      "bad pose")
            out.append(np.asarray(T, dtype=float))
        elif use_kinematics or extra.get("joint_angles") is None:
            raise FlangePoseError(f"frame {i} has neither joint_angles nor pose; the capture cannot fit a mount",
                                  "no joint_angles or pose")
        else:  # (it said "neither joint_angles nor pose" of a frame with joint angles: round 14)
            raise FlangePoseError(f"frame {i} has no recorded pose (its joint angles are read with poses from joints)",
                                  "no recorded pose (poses from joints would read their joint angles)")
    return np.array(out)


def _joint_angles(q: Any, i: int) -> np.ndarray:
    """Frame ``i``'s six joint angles (rad, each within +-2 pi: a UR5 joint's range); CalibrationError otherwise."""
    ok = isinstance(q, (list, tuple, np.ndarray)) and len(q) == 6 and all(
        isinstance(v, (int, float, np.number)) and not isinstance(v, bool) for v in q)
    a = np.asarray(q, dtype=float) if ok else None
    if a is None or not np.all(np.isfinite(a)) or np.abs(a).max() > 2 * math.pi + 1e-9:
        raise FlangePoseError(f"frame {i}: joint_angles must be 6 finite numbers within +-2 pi rad (the UR5's joint "
                              "range)", "bad joint_angles")
    return a


__all__ = ["MountFit", "FlangePoseError", "fit_mount", "flange_poses", "MAX_REACH", "MAX_RMS_ANGLE",
           "MAX_RMS_DISTANCE", "MAX_SIGMA_ROTATION", "MAX_SIGMA_TRANSLATION", "MIN_SIGMA_ANGLE", "MIN_SIGMA_DISTANCE",
           "MOUNT_PARAMETERS"]
