"""The estimator protocol: a frame in, a plane in the sensor frame (or a reason why not) out.

Every estimator returns a :class:`PlaneEstimate`; none raises on bad frames. A frame from which
no plane can be recovered gives ``plane=None`` and a one-line ``reason``. ``residual`` is the
method's own fit-quality measure (documented per method; smaller is better).

Uncertainty: ``covariance`` is the 3 x 3 covariance of the estimate's *tilt components and offset*
``(n_x, n_y, d)``: the x and y components of the unit normal in the sensor frame (for a plane tilted
by a small angle these are the tilt angles about -y and x, in radians) and the offset ``d`` in metres
(units rad^2, rad m, m^2). Each method linearises its own fit at the solution (``diff``: the
Jacobian of the histogram residuals; ``peak``: of the zone points' distances from the plane) and
scales it by the fit's residual, then adds the calibrated model-error floor of :class:`Uncertainty`
(independent of the frame). ``method_used`` names what produced the plane (``diff`` may fall back to
``peak`` when its residual fails the chi-square test, see :class:`Uncertainty`).
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, ClassVar

import numpy as np

from pydantic import Field, model_validator

from place_safe.config import ParamModel, vector
from place_safe.exceptions import ArgumentTypeError, CalibrationError, FrameError, NoPlaneError
from place_safe.geometry import Plane
from place_safe.sensor.frame import SENSOR_RANGE, Frame


#: cos(80 deg): the largest tilt the tilt terms grow with (the tilt term here, the zones' tilt scatter in peak).
COS_MAX_TILT = math.cos(math.radians(80.0))
_TAN2_MAX_TILT = math.tan(math.radians(80.0)) ** 2

#: Order of the covariance entries: the normal's x and y components (rad) and the offset (m).
COVARIANCE_ORDER = ("n_x", "n_y", "d")


#: m: largest zone range error the near-range term may hold.
NEAR_MAX_STD = 0.05

#: The largest ``Uncertainty.scale`` (calibration keeps its fit within :data:`MIN_SCALE` .. this).
MAX_SCALE = 10.0
#: The smallest ``Uncertainty.scale`` a calibration states (:func:`~place_safe.calibration.uncertainty.fit_floor` clips
#: its fit here) and a file may hold (below it, e.g. a hand-edited 1e-12, the file is refused): a covariance shrunk
#: tenfold makes every plane three times as certain as its own fit says (the real sweep's calibrations: 0.2-1.1).
MIN_SCALE = 0.1


class Uncertainty(ParamModel):
    """Calibrated trust in one method (a calibration file's ``uncertainty`` section, one per method).

    A model-error floor, added to each estimate's covariance as variances: what the method gets wrong
    beyond its fit's own noise, chosen at calibration by maximum likelihood of the calibration frames'
    errors. On each tilt component the variance ``tilt_std^2 + (tilt_range_std / d)^2`` (a range
    error of ``tilt_range_std`` between zones tilts a plane at distance ``d`` by about that over
    ``d``), on the offset ``offset_std^2 + (offset_rel d)^2``. Units and the values calibration gives
    (each field's ``Field`` holds its accepted range, wider: at most a right angle, 1 m, 10 m and 1, so a covariance
    stays finite): ``tilt_std`` rad (0 .. 0.1), ``tilt_range_std`` m (0 .. 0.01), ``offset_std`` m (0 .. 0.01), ``offset_rel`` dimensionless (0 .. 0.05). ``chi2_limit`` (reduced chi-square, >= 0; ``inf`` =
    never): ``diff`` falls back to the peak estimate of a frame whose residual chi-square per bin
    (Poisson and calibrated model error, :func:`~place_safe.recovery.forward.residual_weights`) is
    above it; 0: always, without solving (calibration found the model no better than peak on this sensor).
    The fallbacks act in the ``fast`` solver; ``paper`` mode reports its own fit. ``scale`` (dimensionless,
    0.1 .. :data:`MAX_SCALE`) multiplies the whole covariance (the fit's and the
    floor) so the calibration frames' mean NEES per degree of freedom is 1. ``consistency_limit``
    (squared Mahalanobis distance, > 0; ``inf`` = never): ``diff`` also falls back to the peak estimate
    when the two estimates of ``(n_x, n_y, d)`` differ by more than that under their summed covariances
    (a solution the chi-square passed but the independent peak estimate contradicts). ``near_depths``
    (m, increasing, in (0, 10]) and ``near_range_std`` (m, one per depth, 0 .. :data:`NEAR_MAX_STD`): the
    zones' range errors where the sensor is close (:meth:`near_std`; empty: none), cross-validated at
    calibration (:func:`place_safe.calibration.near_range.near_range_std`); the peak method fits its plane's
    covariance with each zone's error at least that large
    (:func:`~place_safe.recovery.points.plane_covariance`). ``near_common_std`` (m, empty or one per depth, 0 ..
    :data:`NEAR_MAX_STD`): a range error that all zones of a frame share besides (one error along every zone's ray
    at once: it moves the plane's offset more than its tilt; :meth:`near_common`); empty: the zones err
    independently. ``zone_std`` (m, 0 .. :data:`NEAR_MAX_STD`; 0 in files before it: none stated, though a
    calibrated entry's partial fits on tilted planes still state the tilt part): the zones' own scatter about the
    plane, the RMS residual of the calibration frames' full-grid fits pooled
    (:func:`~place_safe.calibration.uncertainty.pooled_zone_std`); a fit through fewer zones than the grid, whose own
    residual says less (nothing with three zones), states the larger of its residual variance and ``zone_std^2`` with a
    tilted plane's scatter added (:func:`~place_safe.recovery.peak.partial_zone_variance`). ``far_common_rel`` and
    ``far_zone_rel`` (dimensionless, 0 .. 1; 0 in files before them: none stated): beyond the far end ``hi`` of the
    mapping's calibrated domain, a zone reading range ``r`` errs by a standard deviation of ``far_common_rel (r - hi)``
    shared by the frame's zones and ``far_zone_rel (r - hi)`` of its own, added to the peak method's covariance
    outside ``scale`` (:func:`~place_safe.recovery.peak.far_covariance`;
    :mod:`place_safe.calibration.far_range` reads both on the sweep).

    ``tilt_rel`` (dimensionless, 0 .. 1): what a tilted plane adds that a level sweep cannot show, each tilt
    component's standard deviation per unit ``tan(tilt)`` of the estimated plane, added (outside ``scale``)
    as the variance ``(tilt_rel tan(tilt))^2`` on both tilt components, the plane turning about the point
    ``tilt_pivot z0`` along the optical axis (dimensionless, 0 .. 2; 1: its optical-axis crossing ``z0``, 0: about
    the sensor, so ``d`` does not move), and ``tilt_offset_rel`` (dimensionless, 0 .. 1) adds the variance
    ``(tilt_offset_rel z0 tan(tilt))^2`` on the offset, independent of the tilt components (:meth:`tilt_floor`).
    ``tilt_about`` (the slopes ``(n_x / n_z, n_y / n_z)`` of the calibration frames' mean plane, each -1 .. 1): the tilt
    these terms grow with is counted from there (a sweep whose table sat half a degree off the sensor's axis read planes
    at that tilt as it was calibrated on them); ``(0, 0)``, level, the default.
    ``prefer_ratio``
    (> 0; ``inf`` = no comparison): ``diff`` keeps its own plane only where its tilt variance (worst axis of
    the (n_x, n_y) block) is at most ``prefer_ratio`` times the peak estimate's, so it falls back where its
    covariance says peak reads the slope better (:meth:`prefers`). ``blend`` (``diff`` only; true or false): where
    diff passes its chi-square, consistency and near-range gates it returns its plane blended with peak's by their
    variances (:mod:`place_safe.recovery.blend`, ``method_used = "diff+peak"``) instead of choosing one by
    ``prefer_ratio`` (calibration writes ``prefer_ratio`` null with it). The defaults (no floor, no fallback,
    scale 1, no tilt term, no comparison) are the behaviour of a missing section.

    File form (:meth:`to_dict`, as files have always had it): an infinite ``chi2_limit``, ``consistency_limit`` or
    ``prefer_ratio`` is ``null``; the near-range fields are left out when empty, and ``tilt_rel``, ``prefer_ratio``,
    ``tilt_pivot``, ``tilt_offset_rel`` and ``blend`` at their defaults (older files), ``near_common_std`` when empty.
    Problems are one :class:`~place_safe.exceptions.CalibrationError` line naming the field.
    """

    tilt_std: float = Field(0.0, ge=0.0, le=math.pi / 2, description="rad")
    offset_std: float = Field(0.0, ge=0.0, le=10.0, description="m")
    chi2_limit: float = Field(math.inf, ge=0.0, allow_inf_nan=True,
                              description="(reduced chi-square)")
    tilt_range_std: float = Field(0.0, ge=0.0, le=1.0, description="m")
    offset_rel: float = Field(0.0, ge=0.0, le=1.0, description="(dimensionless)")
    scale: float = Field(1.0, ge=MIN_SCALE, le=MAX_SCALE, description="(dimensionless)")
    consistency_limit: float = Field(math.inf, gt=0.0, allow_inf_nan=True,
                                     description="(squared Mahalanobis distance)")
    near_depths: vector(gt=0.0, le=10.0) = Field(default_factory=list, description="m")
    near_range_std: vector(ge=0.0, le=NEAR_MAX_STD) = Field(default_factory=list, description="m")
    tilt_rel: float = Field(0.0, ge=0.0, le=1.0, description="(dimensionless)")
    prefer_ratio: float = Field(math.inf, gt=0.0, allow_inf_nan=True,
                                description="(dimensionless)")
    tilt_pivot: float = Field(1.0, ge=0.0, le=2.0, description="(of z0)")
    tilt_offset_rel: float = Field(0.0, ge=0.0, le=1.0, description="(dimensionless)")
    tilt_about: vector(2, ge=-1.0, le=1.0) = Field(default_factory=lambda: [0.0, 0.0], description="(slopes)")
    near_common_std: vector(ge=0.0, le=NEAR_MAX_STD) = Field(default_factory=list, description="m")
    blend: bool = Field(False, description="(diff: blend its plane with peak's where its gates pass)")
    zone_std: float = Field(0.0, ge=0.0, le=NEAR_MAX_STD, description="m")
    far_common_rel: float = Field(0.0, ge=0.0, le=1.0, description="(dimensionless)")
    far_zone_rel: float = Field(0.0, ge=0.0, le=1.0, description="(dimensionless)")

    what: ClassVar[str] = "uncertainty"
    error: ClassVar[type[Exception]] = CalibrationError

    @model_validator(mode="after")
    def _near_law(self) -> "Uncertainty":
        k = len(self.near_depths)
        if k == 1 or len(self.near_range_std) != k:
            raise ValueError(f"near_depths and near_range_std need 0 or 2 or more values each, as many of one as "
                             f"of the other (got {k} and {len(self.near_range_std)})")
        if not all(b > a for a, b in zip(self.near_depths, self.near_depths[1:])):
            raise ValueError("near_depths must increase")
        if self.near_common_std and len(self.near_common_std) != k:
            raise ValueError(f"near_common_std needs none or one value per near_depths value (got "
                             f"{len(self.near_common_std)} for {k})")
        return self

    def consistent(self, est: "PlaneEstimate", other: "PlaneEstimate") -> bool:
        """Whether ``est`` agrees with ``other`` within ``consistency_limit`` (True without both covariances)."""
        if math.isinf(self.consistency_limit) or not (est.ok and other.ok):
            return True
        if est.covariance is None or other.covariance is None:
            return True
        dx = tilt_offset(est.plane) - tilt_offset(other.plane)
        try:
            m2 = float(dx @ np.linalg.solve(np.asarray(est.covariance) + np.asarray(other.covariance), dx))
        except np.linalg.LinAlgError:
            return True
        return not (m2 > self.consistency_limit)

    def prefers(self, est: "PlaneEstimate", other: "PlaneEstimate") -> bool:
        """Whether ``est``'s tilt variance is at most ``prefer_ratio`` times ``other``'s (True when
        ``prefer_ratio`` is ``inf`` or a covariance is missing)."""
        if math.isinf(self.prefer_ratio):
            return True
        mine, theirs = est.tilt_std(), other.tilt_std()
        if mine is None or theirs is None:
            return True
        return bool(mine * mine <= self.prefer_ratio * theirs * theirs)

    def apply(self, covariance: np.ndarray, offset: float, normal=None) -> np.ndarray:
        """The reported covariance of an estimate at ``offset`` (m) with unit ``normal`` (None: level; for the tilt
        term) whose fit gave ``covariance`` (3, 3): ``scale (covariance + floor(offset)) + tilt_floor(normal,
        offset)``. Scalar arithmetic, entry by entry in that order (it is on the peak method's per-frame path)."""
        c = np.asarray(covariance, dtype=float)
        if c.shape != (3, 3):
            raise ValueError(f"covariance must be 3 x 3, got shape {c.shape}")
        (c00, c01, c02), (c10, c11, c12), (c20, c21, c22) = c.tolist()
        tilt, off = self._floor_terms(offset)
        s = self.scale
        out = [[s * (c00 + tilt), s * (c01 + 0.0), s * (c02 + 0.0)],
               [s * (c10 + 0.0), s * (c11 + tilt), s * (c12 + 0.0)],
               [s * (c20 + 0.0), s * (c21 + 0.0), s * (c22 + off)]]
        if not (normal is None or (self.tilt_rel == 0.0 and self.tilt_offset_rel == 0.0)):
            v, vx, vy, vd = self._tilt_terms(normal, offset)
            t = ((v, 0.0, vx), (0.0, v, vy), (vx, vy, vd))
            out = [[a + b for a, b in zip(row, trow)] for row, trow in zip(out, t)]
        return np.array(out)

    def tilt_floor(self, normal, offset: float) -> np.ndarray:
        """The covariance (3, 3) of ``(n_x, n_y, d)`` a plane with unit ``normal`` at ``offset`` (m) adds:
        variance ``(tilt_rel tan(tilt))^2`` on each tilt component (tilt capped at 80 deg), the plane turning
        about the point ``tilt_pivot z0`` on the optical axis (``z0 = d / n_z``), so ``d`` moves by
        ``-tilt_pivot z0 (n_x dn_x + n_y dn_y) / n_z``, and ``(tilt_offset_rel z0 tan(tilt))^2`` on ``d`` alone; the tilt
        counted from ``tilt_about``."""
        v, vx, vy, vd = self._tilt_terms(normal, offset)
        return np.array([[v, 0.0, vx], [0.0, v, vy], [vx, vy, vd]])

    def _tilt_terms(self, normal, offset: float) -> tuple[float, float, float, float]:
        """:meth:`tilt_floor`'s entries: the tilt components' variance, their covariances with ``d`` and ``d``'s
        variance (scalar arithmetic: it is on the peak method's per-frame path)."""
        nx, ny, nz = _plane_floats(normal) or (float(v) for v in normal)
        if not (math.isfinite(nx) and math.isfinite(ny) and math.isfinite(nz) and math.isfinite(offset)):
            nx, ny, nz, offset = 0.0, 0.0, COS_MAX_TILT, 0.0
        steep = nz <= COS_MAX_TILT  # (and a normal that is not a number: the fallback above)
        nz = min(max(nz, COS_MAX_TILT), 1.0)
        a0, b0 = self.tilt_about
        if a0 == 0.0 and b0 == 0.0:
            tan2 = max(1.0 - nz * nz, 0.0) / (nz * nz)
        elif steep:
            tan2 = _TAN2_MAX_TILT
        else:  # the tilt from the calibration frames' mean plane: the difference of the slopes (at most 80 deg)
            tan2 = min((nx / nz - a0) ** 2 + (ny / nz - b0) ** 2, _TAN2_MAX_TILT)
        v = self.tilt_rel * self.tilt_rel * tan2  # (tilt_rel tan(tilt))^2
        k = -self.tilt_pivot * float(offset) / (nz * nz)  # -tilt_pivot z0 / n_z
        jx, jy = k * nx, k * ny
        vd = (self.tilt_offset_rel * float(offset) / nz) ** 2 * tan2  # (tilt_offset_rel z0 tan(tilt))^2
        return v, v * jx, v * jy, v * (jx * jx + jy * jy) + vd

    def floor(self, offset: float) -> np.ndarray:
        """The model-error covariance (3, 3) added to an estimate at distance ``offset`` (m)."""
        tilt, off = self._floor_terms(offset)
        return np.array([[tilt, 0.0, 0.0], [0.0, tilt, 0.0], [0.0, 0.0, off]])  # (np.diag's overhead is a frame's 4 us)

    def _floor_terms(self, offset: float) -> tuple[float, float]:
        """:meth:`floor`'s variances: each tilt component's and the offset's."""
        d = max(float(offset), 1e-3)
        return self.tilt_std ** 2 + (self.tilt_range_std / d) ** 2, self.offset_std ** 2 + (self.offset_rel * d) ** 2

    def near_std(self, depth: np.ndarray) -> np.ndarray:
        """The zones' range error (m, a standard deviation) at ``depth`` (m, along the optical axis; any shape):
        ``near_range_std``, linear between ``near_depths``, the first value before the first, 0 from the last on,
        everywhere without them, and where the depth is not a number."""
        return self._near_table(depth, self.near_range_std)

    def near_common(self, depth: np.ndarray) -> np.ndarray:
        """The zones' shared range error (m, a standard deviation) at ``depth`` (m, any shape): ``near_common_std``
        read as :meth:`near_std` reads ``near_range_std``; 0 without it."""
        return self._near_table(depth, self.near_common_std)

    def near_stds(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(:meth:`near_std`, :meth:`near_common`) at ``depth`` (m, any shape), the depths sorted out once."""
        return self._near_table(depth, self.near_range_std, self.near_common_std)

    def _near_table(self, depth: np.ndarray, *values: list[float]) -> np.ndarray | tuple[np.ndarray, ...]:
        """Each of ``values`` (lists of one value per ``near_depths``) at ``depth``: linear between the depths, the
        first value before the first, 0 from the last on, everywhere without values, and where the depth is not a
        number. One list: its array; more: a tuple of them."""
        depth = np.asarray(depth, dtype=float)
        if self.near_depths:
            with np.errstate(invalid="ignore"):
                near = depth < self.near_depths[-1]
            inside = np.where(near, depth, 0.0)
        out = [np.where(near, np.interp(inside, self.near_depths, v), 0.0) if self.near_depths and v
               else np.zeros_like(depth) for v in values]
        return out[0] if len(out) == 1 else tuple(out)

    #: the limits at which ``diff`` returns peak's plane instead of its own (``inf``: never)
    FALLBACK_LIMITS: ClassVar[tuple[str, ...]] = ("chi2_limit", "consistency_limit", "prefer_ratio")
    #: fields written as JSON null when infinite
    _INF_AS_NULL: ClassVar[tuple[str, ...]] = FALLBACK_LIMITS
    #: fields left out of the file at these values (the defaults of files older versions read)
    _OMITTED_AT: ClassVar[tuple[tuple[str, Any], ...]] = (("tilt_rel", 0.0), ("prefer_ratio", None),
                                                           ("tilt_pivot", 1.0), ("tilt_offset_rel", 0.0),
                                                           ("blend", False), ("tilt_about", [0.0, 0.0]),
                                                           ("zone_std", 0.0), ("far_common_rel", 0.0),
                                                           ("far_zone_rel", 0.0))

    #: the model-error floor's terms (:meth:`floor`); a calibrated entry states some (:meth:`states_no_floor`)
    FLOOR_TERMS: ClassVar[tuple[str, ...]] = ("tilt_std", "tilt_range_std", "offset_std", "offset_rel")

    def states_no_floor(self) -> bool:
        """Whether every term of the model-error floor (:data:`FLOOR_TERMS`) is 0: the defaults (no section), but never
        what a calibration writes (the real sweep's peak floor: 0.3 mrad and 0.04 mm; some terms may be 0, not all;
        where its frames want none, :func:`~place_safe.calibration.uncertainty.fit_floor` states a 1 um offset), so a
        file's entry that says so claims a model without error and is refused when read
        (:meth:`place_safe.calibration.Calibration.uncertainty`); on the real sweep it made peak's NEES per dof 5.7."""
        return not any(getattr(self, k) for k in self.FLOOR_TERMS)

    def without_fallback(self) -> "Uncertainty":
        """This uncertainty with every :data:`FALLBACK_LIMITS` at ``inf``: ``diff`` returns its own plane wherever it
        solves one (how its own accuracy is measured), with the same covariance."""
        return self.replace(blend=False, **{k: math.inf for k in self.FALLBACK_LIMITS})

    def to_dict(self) -> dict:
        """The JSON form: ``inf`` limits as null; without the near-range fields when there are none and without
        the tilt terms and ``prefer_ratio`` at their defaults (files older versions read)."""
        d = super().to_dict()
        for key in self._INF_AS_NULL:
            d[key] = None if math.isinf(self.__dict__[key]) else float(self.__dict__[key])
        if not self.near_depths:
            del d["near_depths"], d["near_range_std"]
        if not self.near_common_std:
            del d["near_common_std"]
        for key, default in self._OMITTED_AT:
            if d[key] == default:
                del d[key]
        return d

    @classmethod
    def from_dict(cls, d: Any, what: str | None = None) -> "Uncertainty":
        """An instance from the JSON form (a null or missing limit is ``inf``); one-line :attr:`error` otherwise."""
        if isinstance(d, dict):
            d = {**d, **{k: math.inf for k in cls._INF_AS_NULL if k in d and d[k] is None}}
        return super().from_dict(d, what)


#: rad, the largest tilt error a calibration's reference may state (:class:`Reference`, the plane filter's
#: ``reference_tilt_std``): beyond it the capture's plane says nothing about the sensor's pointing.
MAX_REFERENCE_TILT = 0.1


def reference_tilt_problem(value: Any) -> str | None:
    """Why ``value`` is not a reference tilt error (a number of radians in 0 .. :data:`MAX_REFERENCE_TILT`);
    None when it is."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
            math.isfinite(value) and 0.0 <= value <= MAX_REFERENCE_TILT):
        return f"must be 0..{MAX_REFERENCE_TILT:g} rad, got {describe(value)}"
    return None


class Reference(ParamModel):
    """How far the ground truth a method's calibration was fitted to is itself off (an entry of a calibration file's
    ``reference`` section, one per method family; absent: exact, as in a rig or a file whose truth came with no error).

    A calibration learns the sensor's pointing (peak's zone mapping, the forward model's mount) so that its
    frames read the planes they were captured against. When that reference plane is off, for instance a table
    the arm touched at three points (:func:`place_safe.calibration.capture.touched_reference`), the calibration
    learns the error with the pointing, and every plane the sensor reads afterwards is turned by about the same
    rotation. The frames' own covariances cannot show it (their floor is fitted against the same reference),
    and fusing frames does not average it away: :class:`~place_safe.fusion.plane_filter.PlaneFilter` adds it
    once to the fused tilt's standard error (``reference_tilt_std``), and an estimate's ``covariance`` leaves it
    out. ``tilt_std`` (rad, 0 .. :data:`MAX_REFERENCE_TILT`): the reference normal's standard deviation along its
    worst direction, what placements use; ``offset_std`` (m, 0 .. 0.01; informational: a tenth of a millimetre is far
    inside the release clearance): its offset's, at the touch points' centroid; ``points`` (0: not from touches) and
    ``height_std`` (m): what the touches were and the error taken for each contact's height."""

    tilt_std: float = Field(0.0, ge=0.0, le=MAX_REFERENCE_TILT, description="rad")
    offset_std: float = Field(0.0, ge=0.0, le=0.01, description="m")
    points: int = Field(0, ge=0, le=1000, description="(touch points)")
    height_std: float = Field(0.0, ge=0.0, le=0.01, description="m")

    what: ClassVar[str] = "reference"
    error: ClassVar[type[Exception]] = CalibrationError


def is_covariance(c, definite: bool = False) -> bool:
    """Whether ``c`` is a finite 3 x 3 covariance: its symmetric part's largest eigenvalue above 0 and its smallest
    at least -1e-12 of it (positive semi-definite up to rounding), or with ``definite`` above 1e-12 of it (positive
    definite: a plane the fit pinned down). None is none."""
    if c is None:
        return False
    m = np.asarray(c, dtype=float)
    if m.shape != (3, 3) or not np.all(np.isfinite(m)):
        return False
    w = np.linalg.eigvalsh(0.5 * m + 0.5 * m.T)  # (halved first: a 1e308 entry does not overflow)
    if not w[-1] > 0.0:
        return False
    return bool(w[0] > 1e-12 * w[-1]) if definite else bool(w[0] >= -1e-12 * w[-1])


def tilt_offset(plane: Plane) -> np.ndarray:
    """The state ``(n_x, n_y, d)`` of a plane, in the order of :data:`COVARIANCE_ORDER`."""
    return np.array([plane.normal[0], plane.normal[1], plane.offset])


def frames_of(frames: Any) -> list:
    """``frames`` (a list, tuple, generator or any iterable of frames) as a list; an ArgumentTypeError (a TypeError)
    saying what to call instead for one frame, a histogram array or anything not iterable."""
    if isinstance(frames, (Frame, np.ndarray, dict, str, bytes)) or not hasattr(frames, "__iter__"):
        raise ArgumentTypeError(f"expected an iterable of Frame objects, got {type(frames).__name__} (for one frame "
                                "call estimate(frame); a file: place_safe.load_frames(path))")
    return list(frames)


@dataclass
class PlaneEstimate:
    """Result of one recovery. ``plane`` is None exactly when ``reason`` says why.

    ``covariance``: (3, 3) of ``(n_x, n_y, d)`` (see the module doc) or None when the method gives
    none; ``method_used``: the method that produced ``plane`` (None: the estimator's own).
    """

    plane: Plane | None
    albedo: float | None = None
    residual: float | None = None
    reason: str | None = None
    seconds: float = 0.0
    covariance: np.ndarray | None = None
    method_used: str | None = None

    def tilt_std(self) -> float | None:
        """Standard deviation (rad) of the tilt along its worst direction (largest eigenvalue of the
        symmetric part of the (n_x, n_y) block); None without a covariance, or with one that is not a real,
        symmetric (to 1e-9 of its largest entry) covariance (:func:`is_covariance`: a negative or an all-zero
        variance, a complex or a lopsided matrix state no uncertainty, as NaN does)."""
        if self.covariance is None:
            return None
        try:
            raw = np.asarray(self.covariance)
            if np.iscomplexobj(raw):
                return None
            C = np.asarray(raw, dtype=float)
        except (TypeError, ValueError, OverflowError):
            return None
        if C.shape != (3, 3) or not np.all(np.isfinite(C)) or not is_covariance(C):
            return None
        if float(np.abs(C - C.T).max()) > 1e-9 * float(np.abs(C).max()):
            return None
        B = C[:2, :2]
        v = float(np.linalg.eigvalsh(0.5 * B + 0.5 * B.T).max())  # (halved first: a 1e308 block does not overflow)
        return math.sqrt(v) if v >= 0 and math.isfinite(v) else None

    @property
    def ok(self) -> bool:
        return self.plane is not None

    def to_json(self, index: int) -> dict:
        """The ``recover --jsonl`` line of docs/interfaces.md."""
        out: dict = {"index": index}
        if self.plane is not None:
            out["normal"] = [float(v) for v in self.plane.normal]
            out["offset"] = float(self.plane.offset)
        else:
            out["normal"] = None
            out["offset"] = None
        out["albedo"] = None if self.albedo is None or not np.isfinite(self.albedo) else float(self.albedo)
        out["ms"] = round(self.seconds * 1e3, 4)
        if self.residual is not None and np.isfinite(self.residual):
            out["residual"] = float(self.residual)
        if self.reason is not None:
            out["reason"] = self.reason
        if self.method_used is not None:
            out["method_used"] = self.method_used
        if self.covariance is not None and np.isfinite(self.covariance).all():
            out["covariance"] = [[float(f"{v:.6g}") for v in row] for row in self.covariance]
        return out


def _plane_floats(normal) -> list[float] | None:
    """A :class:`~place_safe.geometry.Plane`'s own ``normal`` (a float64 array of 3) as its three Python floats (read
    thus, a microsecond less on every frame); None for anything else, which callers read as before."""
    if type(normal) is np.ndarray and normal.dtype == np.float64 and normal.shape == (3,):
        return normal.tolist()
    return None


def _finite(normal) -> bool:
    """Whether every component of a plane's ``normal`` is finite (a Plane's own by its Python floats)."""
    xyz = _plane_floats(normal)
    return all(map(math.isfinite, xyz)) if xyz is not None else bool(np.isfinite(normal).all())


def checked(est: PlaneEstimate) -> PlaneEstimate:
    """``est`` unless its plane is not finite, lies behind the sensor or beyond the sensor's range
    (:data:`~place_safe.sensor.frame.SENSOR_RANGE`, 5 m) (then no plane, with the reason). A peak calibration's ``b``
    of -10000 (within its field's range) put every plane 140 m away, stated with a covariance of millimetres (session
    82: then held to the 65.5 m the on-sensor field can hold); a proprietary ``b`` of -10000 put planes 9-10 m away,
    which no TMF8820 measures (session 83)."""
    p = est.plane
    if p is not None and not (_finite(p.normal) and np.isfinite(p.offset) and p.offset > 0):
        return PlaneEstimate(None, reason=f"recovered plane is not in front of the sensor (offset {p.offset:.4g} m)",
                             seconds=est.seconds)
    if p is not None and p.offset > SENSOR_RANGE:
        return PlaneEstimate(None, reason=f"recovered plane is {p.offset:.4g} m away, beyond the sensor's "
                                          f"{SENSOR_RANGE:g} m range: is the calibration this sensor's?",
                             seconds=est.seconds)
    if est.albedo is not None and not np.isfinite(est.albedo):
        est.albedo = None
    return est


def describe(value: Any) -> str:
    """A wrong argument as an error line names it: its type, and for a string or number its value (80 characters)."""
    return f"{type(value).__name__} {value!r}"[:80] if isinstance(value, (str, int, float)) else type(value).__name__


def check_arguments(owner: str, **given: tuple[Any, type]) -> None:
    """Raise :class:`~place_safe.exceptions.ArgumentTypeError` (one line: the argument, what it must be, what it got)
    unless each ``name=(value, cls)`` has a value that is None or a ``cls``: an estimator's constructor checks its
    parameter sets so a wrong one fails there, not as an AttributeError out of every :meth:`Estimator.estimate`."""
    for name, (value, cls) in given.items():
        if value is not None and not isinstance(value, cls):
            raise ArgumentTypeError(f"{owner}: {name} must be a {cls.__name__} or None; got {describe(value)}")


class Estimator(ABC):
    """Base class: subclasses implement :meth:`_estimate`; :meth:`estimate` adds checks and timing."""

    #: CLI name of the method (``peak``, ``diff``, ...).
    name: str = "base"
    #: Whether the method needs the histograms (False: only the on-sensor distances).
    needs_histograms: bool = True
    #: rad, the standard deviation of the tilt error every estimate shares through the calibration's reference
    #: (:class:`Reference`; :func:`~place_safe.recovery.make_estimator` sets it): not in any estimate's covariance.
    reference_tilt_std: float = 0.0

    def estimate(self, frame: Frame) -> PlaneEstimate:
        """Recover the plane of one frame; never raises for bad data, never returns a NaN plane or a
        plane behind the sensor (``offset <= 0``): such frames get ``plane=None`` and a reason."""
        t0 = time.perf_counter()
        try:
            if not isinstance(frame, Frame):
                raise FrameError(f"expected a Frame, got {type(frame).__name__}")
            if self.needs_histograms:
                frame.validate()
            est = checked(self._estimate(frame))
        except (FrameError, NoPlaneError) as exc:
            est = PlaneEstimate(None, reason=str(exc))
        except (ArithmeticError, np.linalg.LinAlgError) as exc:
            est = PlaneEstimate(None, reason=f"numerical failure: {exc}")
        except (ValueError, TypeError, IndexError, RuntimeError) as exc:  # data no check above foresaw
            est = PlaneEstimate(None, reason=f"unusable data: {type(exc).__name__}: {str(exc)[:200]}")
        est.seconds = time.perf_counter() - t0
        return est

    def estimate_many(self, frames: list[Frame]) -> list[PlaneEstimate]:
        """Recover many frames (any iterable of them; subclasses may batch)."""
        return [self.estimate(f) for f in frames_of(frames)]

    @abstractmethod
    def _estimate(self, frame: Frame) -> PlaneEstimate:
        """Recover one validated frame; may raise FrameError or NoPlaneError."""
