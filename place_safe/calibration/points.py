"""Zone readings to 3-D points and planes, and the calibration of that mapping.

Concept
-------
The ``peak`` and ``proprietary`` methods both turn one scalar *reading* per zone into a range and
put the point at that range along the zone's direction; a plane is fitted to the points by SVD.
The reading is the sub-bin histogram peak (bins) for ``peak`` and the on-sensor distance
(millimetres) for ``proprietary``. :class:`PeakParams` holds the mapping:

* range (m) of zone ``z``, from the reading ``x``::

      x' = x - s(x) - b - zone_offsets[z]
      r  solves  m g_z r + c(r) = x'       (fixed-point iteration; r = x' / (m g_z) without c)

  ``m`` in reading units per metre (bins/m or mm/m), ``g_z`` = ``zone_gains`` (dimensionless,
  mean 1), ``b`` and ``zone_offsets`` in reading units. ``s(x)`` (``phase_coeffs``, sine/cosine
  pairs of 2 pi k x) corrects the sub-bin bias of the spline peak, which pulls peaks towards
  whole bins (+-0.09 bin on the real sweep). ``c`` (``residual_coeffs``) is a smooth residual
  correction shared by all zones: a Chebyshev series in ``r`` over ``residual_domain`` (m),
  evaluated at ``r`` clipped to the domain, so it is constant outside the calibrated range; it
  absorbs the slow drift of the peak with distance (pulse shape changing with signal strength:
  a bow of +-3 mm over 5-40 cm on the real sweep). Per-zone gains take up what differs between
  zones with range (effective zone directions, signal level). Empty coefficient lists and unit
  gains are the paper's model.
* direction of zone ``z``: the zone-centre direction (:data:`place_safe.sensor.ZONE_DIRECTIONS`)
  with its angle from the optical axis multiplied by ``edge_scale`` (s_e, zones 2, 4, 6, 8) or
  ``corner_scale`` (s_c, zones 1, 3, 7, 9); azimuth kept, the centre zone stays on the axis.

Calibration (:func:`fit_peak`, :func:`fit_proprietary`) minimises the paper's point error over
frames with ground truth: Nelder-Mead over ``(m, b, s_e, s_c)`` as in the paper (``paper=True``),
then the full model by linear least squares (see :func:`fit_points`). The paper did not calibrate per-zone
offsets; on the real sweep zones differ by up to one bin (about 12 mm) at the same distance.
"""

from __future__ import annotations

import math
import sys
from dataclasses import asdict, dataclass, field
from typing import Any, Sequence

import numpy as np
from numpy.polynomial import chebyshev as cheb
from scipy.optimize import minimize

from ..config import check_keys
from ..exceptions import CalibrationError, NoPlaneError
from ..geometry import Plane
from ..sensor import CORNER, EDGE, N_ZONES, ZONE_DIRECTIONS, ZONE_KIND, Frame

#: The paper's calibrated peak method (their code): distance = (peak_bin - 13.155) / 72.073 m.
PAPER_PEAK_M = 72.073  # bins per metre
PAPER_PEAK_B = 13.155  # bins
PAPER_EDGE_SCALE = 0.9405
PAPER_CORNER_SCALE = 0.8916
#: Physical bin size of short-range high-accuracy mode (published forward model), m per bin.
BIN_SIZE = 0.014131
#: Bin offset of the published forward model: a target at range r gives a transient at bin
#: ``r / BIN_SIZE + FORWARD_BIN_OFFSET`` (before the laser pulse delays the peak).
FORWARD_BIN_OFFSET = 9.5235
#: Reference-pulse time scale of the published model: a reference bin is this many zone bins.
REF_TIME_SCALE = 0.27887
#: Millimetres per metre: the reading scale of on-sensor distances.
MM_PER_M = 1000.0
#: Fixed-point iterations inverting ``m r + c(r) = x`` (c changes by far less than m per metre).
RANGE_ITERATIONS = 3
#: Spread of ground-truth tilts (rad) from which the edge/corner scales are identifiable and fitted.
MIN_TILT_SPREAD = math.radians(5.0)
#: Frames whose true axis distance is below this are left out of calibration: the peak stops
#: moving with range there (pulse and target overlap), see the shared sweep below 25 mm.
MIN_CALIBRATION_RANGE = 0.03  # m


@dataclass
class PeakParams:
    """Reading-to-point mapping of the peak and on-sensor-distance methods (see module doc).

    ``m``: reading units per metre; ``b``, ``zone_offsets`` (9), ``residual_coeffs``: reading units;
    ``edge_scale``, ``corner_scale``: dimensionless; ``residual_domain``: (lo, hi) metres.
    """

    m: float
    b: float
    edge_scale: float = 1.0
    corner_scale: float = 1.0
    zone_offsets: list[float] = field(default_factory=lambda: [0.0] * N_ZONES)
    residual_coeffs: list[float] = field(default_factory=list)
    residual_domain: list[float] = field(default_factory=lambda: [0.0, 1.0])
    phase_coeffs: list[float] = field(default_factory=list)
    zone_gains: list[float] = field(default_factory=lambda: [1.0] * N_ZONES)

    def __post_init__(self) -> None:
        self.zone_offsets = [float(v) for v in self.zone_offsets]
        self.zone_gains = [float(v) for v in self.zone_gains]
        if len(self.zone_gains) != N_ZONES or min(self.zone_gains) <= 0:
            raise CalibrationError(f"zone_gains needs {N_ZONES} positive values")
        self.phase_coeffs = [float(v) for v in self.phase_coeffs]
        if len(self.phase_coeffs) % 2:
            raise CalibrationError("phase_coeffs needs (sin, cos) pairs, got an odd count")
        self.residual_coeffs = [float(v) for v in self.residual_coeffs]
        self.residual_domain = [float(v) for v in self.residual_domain]
        if len(self.zone_offsets) != N_ZONES:
            raise CalibrationError(f"zone_offsets needs {N_ZONES} values, got {len(self.zone_offsets)}")
        if len(self.residual_domain) != 2 or not self.residual_domain[0] < self.residual_domain[1]:
            raise CalibrationError(f"residual_domain must be [lo, hi] with lo < hi, got {self.residual_domain}")
        vals = [self.m, self.b, self.edge_scale, self.corner_scale, *self.zone_offsets, *self.residual_coeffs,
                *self.residual_domain, *self.phase_coeffs, *self.zone_gains]
        if not all(math.isfinite(float(v)) for v in vals):
            raise CalibrationError("peak parameters must all be finite")
        if self.m <= 0:
            raise CalibrationError(f"m (reading units per metre) must be > 0, got {self.m}")
        if not (0 < self.edge_scale < 3 and 0 < self.corner_scale < 3):
            raise CalibrationError("edge_scale and corner_scale must be in (0, 3)")

    # -- file form ---------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any) -> "PeakParams":
        check_keys(cls, d, "peak parameters", CalibrationError)
        missing = {"m", "b"} - set(d)
        if missing:
            raise CalibrationError(f"peak parameters lack {', '.join(sorted(missing))}")
        try:
            return cls(**d)
        except (TypeError, ValueError) as exc:
            raise CalibrationError(f"peak parameters are malformed: {exc}") from None

    # -- built-in sets -----------------------------------------------------------------------------
    @classmethod
    def default_peak(cls) -> "PeakParams":
        """The paper's published calibrated peak constants (their sensor)."""
        return cls(PAPER_PEAK_M, PAPER_PEAK_B, PAPER_EDGE_SCALE, PAPER_CORNER_SCALE)

    @classmethod
    def default_proprietary(cls) -> "PeakParams":
        """On-sensor distances as reported: mm to m, nominal zone directions."""
        return cls(MM_PER_M, 0.0)

    @classmethod
    def naive_peak(cls, reference_peak_bin: float | None = None) -> "PeakParams":
        """Physical constants: the published bin size and, for ``b``, the bin where a target at
        range 0 would peak: the forward model's bin offset plus the reference pulse's peak delay
        (reference-peak bin times the reference time scale). Without a reference, the typical
        reference peak of bin 14 is used (the TMF8820's reference pulse peaks near bin 14). Scales 1,
        no zone offsets.
        """
        ref_peak = 14.0 if reference_peak_bin is None else float(reference_peak_bin)
        return cls(1.0 / BIN_SIZE, FORWARD_BIN_OFFSET + ref_peak * REF_TIME_SCALE)

    # -- mapping -----------------------------------------------------------------------------------
    def directions(self) -> np.ndarray:
        """Unit direction (9, 3) of each zone with the edge/corner angle scales applied."""
        v = ZONE_DIRECTIONS
        theta = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
        phi = np.arctan2(v[:, 1], v[:, 0])
        scale = np.ones(N_ZONES)
        scale[ZONE_KIND == EDGE] = self.edge_scale
        scale[ZONE_KIND == CORNER] = self.corner_scale
        t = theta * scale
        return np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], axis=1)

    def correction(self, r0: np.ndarray) -> np.ndarray:
        """Residual correction c(r0) in reading units (0 without coefficients)."""
        r0 = np.asarray(r0, dtype=float)
        if not self.residual_coeffs:
            return np.zeros_like(r0)
        lo, hi = self.residual_domain
        u = (2.0 * np.clip(r0, lo, hi) - (lo + hi)) / (hi - lo)
        return cheb.chebval(u, self.residual_coeffs)

    def phase_correction(self, readings: np.ndarray) -> np.ndarray:
        """Sub-bin phase correction s(x) in reading units (0 without coefficients)."""
        x = np.asarray(readings, dtype=float)
        out = np.zeros_like(x)
        for k in range(len(self.phase_coeffs) // 2):
            w = 2.0 * np.pi * (k + 1) * x
            out = out + self.phase_coeffs[2 * k] * np.sin(w) + self.phase_coeffs[2 * k + 1] * np.cos(w)
        return out

    def ranges(self, readings: np.ndarray) -> np.ndarray:
        """Ranges (m) for readings (..., 9)."""
        x = np.asarray(readings, dtype=float)
        x = x - self.phase_correction(x) - self.b - np.asarray(self.zone_offsets)
        mz = self.m * np.asarray(self.zone_gains)
        r = x / mz
        if self.residual_coeffs:
            for _ in range(RANGE_ITERATIONS):  # solve m g r + c(r) = x by fixed-point iteration
                r = (x - self.correction(r)) / mz
        return r

    def points(self, readings: np.ndarray) -> np.ndarray:
        """Points (..., 9, 3) in the sensor frame for readings (..., 9)."""
        return self.ranges(readings)[..., None] * self.directions()

    def expected_readings(self, planes_n: np.ndarray, planes_d: np.ndarray) -> np.ndarray:
        """Ideal readings (F, 9) of planes (normals (F, 3), offsets (F,)) along the current directions,
        *without* the residual correction (used to fit offsets and correction linearly)."""
        dirs = self.directions()
        denom = planes_n @ dirs.T  # (F, 9)
        r = planes_d[:, None] / denom
        return self.m * np.asarray(self.zone_gains) * r + self.b + np.asarray(self.zone_offsets)


# ---------------------------------------------------------------------------------------------
# Batched plane fit
# ---------------------------------------------------------------------------------------------
def fit_planes(points: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares planes through point sets, batched: points (F, N, 3), valid (F, N) bool.

    Returns normals (F, 3) with n_z > 0, offsets (F,), RMS perpendicular residuals (F,) in metres
    and ``ok`` (F,) bool: at least 3 valid, non-collinear points and a plane not containing the
    optical axis. Entries with ``ok`` False are NaN. Same maths as :func:`place_safe.geometry.fit_plane`
    (SVD of the centred points), for many frames at once.
    """
    pts = np.asarray(points, dtype=float)
    w = (np.asarray(valid, dtype=bool) & np.all(np.isfinite(pts), axis=-1)).astype(float)
    count = w.sum(-1)
    safe_pts = np.where(w[..., None] > 0, pts, 0.0)
    cnt = np.maximum(count, 1.0)
    centroid = (w[..., None] * safe_pts).sum(-2) / cnt[..., None]
    centred = (safe_pts - centroid[..., None, :]) * w[..., None]
    _, s, vt = np.linalg.svd(centred, full_matrices=False)
    n = vt[..., -1, :]
    sign = np.where(n[..., 2] < 0, -1.0, 1.0)
    n = n * sign[..., None]
    d = (n * centroid).sum(-1)
    rms = s[..., -1] / np.sqrt(cnt)
    ok = (count >= 3) & (s[..., 1] > 1e-9 * np.maximum(s[..., 0], 1e-30)) & (n[..., 2] > 1e-6) & (d > 0)
    n = np.where(ok[..., None], n, np.nan)
    d = np.where(ok, d, np.nan)
    rms = np.where(ok, rms, np.nan)
    return n, d, rms, ok


# ---------------------------------------------------------------------------------------------
# Calibration
# ---------------------------------------------------------------------------------------------
def _truth_arrays(frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray]:
    n = np.array([f.truth.normal for f in frames])
    d = np.array([f.truth.offset for f in frames])
    return n, d


def _errors(params: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray) -> dict:
    from ..metrics import angular_errors, linear_errors, point_errors

    n, d, _, ok = fit_planes(params.points(readings), valid)
    out = {"failures": int((~ok).sum())}
    if ok.any():
        out["point"] = point_errors(n[ok], d[ok], tn[ok], td[ok])
        out["angular"] = angular_errors(n[ok], tn[ok])
        out["linear"] = linear_errors(n[ok], d[ok], tn[ok], td[ok])
    return out


def _summary(errs: dict) -> dict:
    out: dict[str, Any] = {"failures": errs["failures"]}
    for key, scale, unit in (("point", 1e3, "mm"), ("linear", 1e3, "mm"), ("angular", 180 / np.pi, "deg")):
        e = errs.get(key)
        if e is None or len(e) == 0:
            continue
        out[f"{key}_mean_{unit}"] = float(np.mean(e) * scale)
        out[f"{key}_median_{unit}"] = float(np.median(e) * scale)
    return out


def fit_linear(edge_scale: float, corner_scale: float, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray,
               td: np.ndarray, degree: int = 2, harmonics: int = 2, fit_offsets: bool = True,
               fit_gains: bool = True) -> PeakParams | None:
    """For fixed direction scales, the least-squares m, b, zone offsets, residual correction and phase
    correction: ``reading = m r + b + off_z + c(r) + s(reading)`` at the true ranges ``r`` along the
    scaled directions (reading units). Returns None when the data do not determine them."""
    dirs = PeakParams(1.0, 0.0, edge_scale, corner_scale).directions()
    with np.errstate(divide="ignore", invalid="ignore"):
        r = td[:, None] / (tn @ dirs.T)
    use = valid & np.isfinite(readings) & np.isfinite(r) & (r > 0)
    if use.sum() < 3:
        return None
    rows, zones = np.nonzero(use)
    y = readings[use]
    rr = r[use]
    lo, hi = float(rr.min()), float(rr.max())
    if hi - lo < 1e-3:
        degree, hi = 0, lo + 1e-3
    onehot = np.zeros((len(y), N_ZONES))
    onehot[np.arange(len(y)), zones] = 1.0
    seen = onehot.sum(0) > 0
    n_slope = N_ZONES if fit_gains else 1
    if fit_gains and not seen.all():
        return None  # a zone never seen cannot get its own gain
    cols = [rr[:, None] * onehot] if fit_gains else [rr[:, None]]
    if fit_offsets:
        if not seen.all():
            return None
        cols.append(onehot)
    else:
        cols.append(np.ones((len(y), 1)))
    if degree > 1:  # the constant and linear Chebyshev terms are b and m
        u = (2.0 * rr - (lo + hi)) / (hi - lo)
        cols.append(cheb.chebvander(u, degree)[:, 2:])
    for k in range(harmonics):
        w = 2.0 * np.pi * (k + 1) * y
        cols.append(np.stack([np.sin(w), np.cos(w)], axis=1))
    A = np.concatenate(cols, axis=1)
    if np.linalg.matrix_rank(A) < A.shape[1]:
        return None
    coef, *_ = np.linalg.lstsq(A, y, rcond=None)
    slopes = coef[:n_slope]
    m = float(slopes.mean())
    if not (m > 0 and np.all(slopes > 0)):
        return None
    gains = slopes / m if fit_gains else np.ones(N_ZONES)
    k = n_slope
    if fit_offsets:
        off = coef[k:k + N_ZONES]
        k += N_ZONES
        b = float(off.mean())
        offsets = off - b
    else:
        b = float(coef[k])
        k += 1
        offsets = np.zeros(N_ZONES)
    res_coeffs: list[float] = []
    if degree > 1:
        res_coeffs = [0.0, 0.0] + [float(v) for v in coef[k:k + degree - 1]]
        k += degree - 1
    phase = [float(v) for v in coef[k:k + 2 * harmonics]]
    try:
        return PeakParams(m, b, edge_scale, corner_scale, list(offsets), res_coeffs, [lo, hi], phase, list(gains))
    except CalibrationError:
        return None


def _mean_point_error(p: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray,
                      td: np.ndarray) -> float:
    from ..metrics import point_errors

    n, d, _, ok = fit_planes(p.points(readings), valid)
    e = np.full(len(td), 1.0)  # a failed fit costs 1 m
    if ok.any():
        e[ok] = point_errors(n[ok], d[ok], tn[ok], td[ok])
    return float(np.mean(e))


def _fit_scales(start: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray,
                bar: Any, max_iter: int, degree: int, harmonics: int, fit_offsets: bool,
                fit_gains: bool) -> PeakParams:
    """Nelder-Mead over (s_e, s_c) on the mean point error, the rest solved linearly inside."""

    def make(x: np.ndarray) -> PeakParams | None:
        if not (0 < x[0] < 3 and 0 < x[1] < 3):
            return None
        return fit_linear(float(x[0]), float(x[1]), readings, valid, tn, td, degree, harmonics, fit_offsets,
                          fit_gains)

    def cost(x: np.ndarray) -> float:
        p = make(x)
        return 1e3 if p is None else _mean_point_error(p, readings, valid, tn, td)

    x0 = np.array([start.edge_scale, start.corner_scale])
    res = minimize(cost, x0, method="Nelder-Mead",
                   options={"maxiter": max_iter, "xatol": 1e-6, "fatol": 1e-10,
                            "initial_simplex": np.array([x0, x0 + [0.05, 0], x0 + [0, 0.05]])},
                   callback=(lambda *_: bar.update(1)) if bar is not None else None)
    p = make(res.x)
    return p if p is not None else start


def _nelder_mead(params: PeakParams, readings: np.ndarray, valid: np.ndarray, tn: np.ndarray, td: np.ndarray,
                 bar: Any, max_iter: int) -> PeakParams:
    """Nelder-Mead over (m, b, s_e, s_c) on the mean point error, other fields fixed."""
    fixed = dict(zone_offsets=params.zone_offsets, residual_coeffs=params.residual_coeffs,
                 residual_domain=params.residual_domain, phase_coeffs=params.phase_coeffs)
    x0 = np.array([params.m, params.b, params.edge_scale, params.corner_scale])
    scale = np.array([params.m, 1.0, 1.0, 1.0])  # optimise m relative to its start

    def make(x: np.ndarray) -> PeakParams | None:
        m, b, se, sc = x * scale
        if not (m > 0 and 0 < se < 3 and 0 < sc < 3):
            return None
        return PeakParams(float(m), float(b), float(se), float(sc), **fixed)

    def cost(x: np.ndarray) -> float:
        p = make(x)
        return 1e3 if p is None else _mean_point_error(p, readings, valid, tn, td)

    res = minimize(cost, x0 / scale, method="Nelder-Mead",
                   options={"maxiter": max_iter, "xatol": 1e-7, "fatol": 1e-9,
                            "initial_simplex": _simplex(x0 / scale)},
                   callback=(lambda *_: bar.update(1)) if bar is not None else None)
    p = make(res.x)
    return p if p is not None else params


def _simplex(x0: np.ndarray) -> np.ndarray:
    steps = np.array([0.02, 0.3, 0.03, 0.03])  # relative m, bins, scale, scale
    return np.vstack([x0] + [x0 + np.eye(len(x0))[i] * steps[i] for i in range(len(x0))])


def fit_points(readings: np.ndarray, valid: np.ndarray, frames: Sequence[Frame], init: PeakParams,
               progress: bool = True, residual_degree: int = 3, harmonics: int = 2, fit_offsets: bool = True,
               fit_gains: bool = True, paper: bool = False, max_iter: int = 400,
               label: str = "calibrate") -> tuple[PeakParams, dict]:
    """Calibrate a reading-to-point mapping on readings (F, 9) with mask (F, 9) and the frames' truth.

    First the paper's procedure: Nelder-Mead over (m, b, s_e, s_c) on the mean point error from
    ``init`` (its result is returned when ``paper`` is True). Otherwise the full model is fitted
    from ``init``'s scales: m, b, per-zone offsets and gains, the residual correction (Chebyshev
    ``residual_degree``) and the sub-bin phase correction (``harmonics`` sine/cosine pairs) by linear
    least squares (:func:`fit_linear`); the scales s_e, s_c are refined by Nelder-Mead on the point
    error only when the ground-truth planes are tilted by :data:`MIN_TILT_SPREAD` or more between
    frames. Otherwise (e.g. a sweep towards a level table) the scales are not identifiable: they
    would only trade the fit's lever arm and are kept at ``init``'s values.
    """
    from tqdm import tqdm

    tn, td = _truth_arrays(frames)
    before = _summary(_errors(init, readings, valid, tn, td))
    tilt = np.arccos(np.clip(tn[:, 2], -1.0, 1.0))
    tilted = bool(np.ptp(tilt) >= MIN_TILT_SPREAD)
    bar = tqdm(total=max_iter * (2 if tilted and not paper else 1), desc=label, unit="it", disable=not progress,
               leave=False, file=sys.stderr)
    try:
        base = PeakParams(init.m, init.b, init.edge_scale, init.corner_scale)
        params = _nelder_mead(base, readings, valid, tn, td, bar, max_iter)
        paper_style = _summary(_errors(params, readings, valid, tn, td))
        if not paper:
            full = fit_linear(init.edge_scale, init.corner_scale, readings, valid, tn, td, residual_degree, harmonics,
                              fit_offsets, fit_gains)
            if full is None:
                raise CalibrationError("calibration data do not determine the per-zone parameters "
                                       "(every zone needs returns in several frames at different distances)")
            params = full
            if tilted:
                params = _fit_scales(params, readings, valid, tn, td, bar, max_iter, residual_degree, harmonics,
                                     fit_offsets, fit_gains)
    finally:
        bar.close()
    after = _summary(_errors(params, readings, valid, tn, td))
    report = {"frames": len(frames), "before": before, "paper_style_fit": paper_style, "after": after,
              "params": params.to_dict(), "residual_degree": residual_degree, "harmonics": harmonics,
              "fit_offsets": fit_offsets, "fit_gains": fit_gains, "scales_fitted": tilted or paper, "paper": paper}
    return params, report


def _calibration_frames(frames: Sequence[Frame], min_range: float) -> list[Frame]:
    use = [f for f in frames if f.truth is not None and f.truth.z0 >= min_range]
    if len(use) < 3:
        raise CalibrationError(f"calibration needs 3 or more frames with ground truth at >= {min_range * 1e3:.0f} mm, "
                               f"got {len(use)}")
    return use


def _initial_linear(readings: np.ndarray, valid: np.ndarray, frames: Sequence[Frame], like: PeakParams) -> PeakParams:
    """Start values for m, b from a straight-line fit of readings vs. true ranges (nominal directions)."""
    tn, td = _truth_arrays(frames)
    r = td[:, None] / (tn @ like.directions().T)
    use = valid & np.isfinite(readings)
    if use.sum() < 2 or np.ptp(r[use]) < 1e-3:
        return like
    m, b = np.polyfit(r[use], readings[use], 1)
    if not (m > 0 and np.isfinite(b)):
        return like
    return PeakParams(float(m), float(b), like.edge_scale, like.corner_scale)


def fit_peak(frames: Sequence[Frame], init: PeakParams | None = None, progress: bool = True,
             min_range: float = MIN_CALIBRATION_RANGE, residual_degree: int = 3, harmonics: int = 2,
             fit_offsets: bool = True, paper: bool = False) -> tuple[PeakParams, dict]:
    """Calibrate the peak method on frames with ground truth; returns the parameters and a report.

    Frames closer than ``min_range`` (m) and frames without a usable return are left out. With
    With ``paper=True`` this is the paper's calibration (Nelder-Mead over m, b, s_e, s_c only).
    """
    from ..estimators.peak import find_peaks

    use = _calibration_frames(frames, min_range)
    hists = np.array([np.asarray(f.hists, dtype=float) for f in use])
    readings, valid, _ = find_peaks(hists)
    return _fit_readings("peak", "returns", use, readings, valid, init, PeakParams.default_peak(), progress,
                         residual_degree, harmonics, fit_offsets, paper, min_range)


def _fit_readings(method: str, what: str, use: list[Frame], readings: np.ndarray, valid: np.ndarray,
                  init: PeakParams | None, default: PeakParams, progress: bool, residual_degree: int,
                  harmonics: int, fit_offsets: bool, paper: bool, min_range: float) -> tuple[PeakParams, dict]:
    """Fit readings (F, 9) of frames ``use`` for ``method``: frames with 3 or more valid zones, a
    straight-line start unless ``init`` is given, then :func:`fit_points`."""
    keep = valid.sum(1) >= 3
    if keep.sum() < 3:
        raise CalibrationError(f"fewer than 3 calibration frames have {what} in 3 or more zones")
    use = [f for f, k in zip(use, keep) if k]
    readings, valid = readings[keep], valid[keep]
    start = init if init is not None else _initial_linear(readings, valid, use, default)
    params, report = fit_points(readings, valid, use, start, progress, residual_degree, harmonics, fit_offsets,
                                fit_offsets, paper, label=f"calibrate {method}")
    report["method"] = method
    report["min_range_m"] = min_range
    return params, report


def proprietary_readings(frames: Sequence[Frame]) -> tuple[np.ndarray, np.ndarray]:
    """On-sensor distances in mm (F, 9) and validity (distance > 0, finite) of frames."""
    out = np.full((len(frames), N_ZONES), np.nan)
    for i, f in enumerate(frames):
        if f.distances is not None and np.shape(f.distances) == (N_ZONES,):
            out[i] = np.asarray(f.distances, dtype=float) * MM_PER_M
    valid = np.isfinite(out) & (out > 0)
    return out, valid


def fit_proprietary(frames: Sequence[Frame], init: PeakParams | None = None, progress: bool = True,
                    min_range: float = MIN_CALIBRATION_RANGE, residual_degree: int = 3, fit_offsets: bool = True,
                    paper: bool = False) -> tuple[PeakParams, dict]:
    """Calibrate the on-sensor distances (mm readings) on frames with ground truth (no phase
    correction: the readings are whole millimetres, not sub-bin peaks)."""
    use = _calibration_frames(frames, min_range)
    readings, valid = proprietary_readings(use)
    params, report = _fit_readings("proprietary", "on-sensor distances", use, readings, valid, init,
                                   PeakParams.default_proprietary(), progress, residual_degree, 0, fit_offsets,
                                   paper, min_range)
    return params, report


def plane_from_points(params: PeakParams, readings: np.ndarray, valid: np.ndarray) -> tuple[Plane, float]:
    """The plane of one frame's readings (9,) and mask (9,), and its RMS residual (m); raises NoPlaneError."""
    if valid.sum() < 3:
        raise NoPlaneError(f"only {int(valid.sum())} zones have a return; a plane needs 3 or more")
    n, d, rms, ok = fit_planes(params.points(readings)[None], valid[None])
    if not ok[0]:
        raise NoPlaneError("the zone points do not determine a plane in front of the sensor")
    return Plane(n[0], float(d[0])), float(rms[0])


__all__ = ["PeakParams", "fit_planes", "fit_points", "fit_peak", "fit_proprietary", "proprietary_readings",
           "plane_from_points", "MIN_CALIBRATION_RANGE"]
