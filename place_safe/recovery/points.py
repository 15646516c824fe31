"""Zone readings -> 3-D points -> a plane: the mapping shared by the ``peak`` and ``proprietary`` methods.

The reading is the sub-bin histogram peak (bins) for ``peak`` and the on-sensor distance
(millimetres) for ``proprietary``. :class:`PeakParams` holds the mapping:

* range (m) of zone ``z``, from the reading ``x``::

      x' = x - s(x) - b - zone_offsets[z]
      r  solves  m g_z r + c(r) = x'       (fixed-point iteration; r = x' / (m g_z) without c)

  ``m`` in reading units per metre (bins/m or mm/m), ``g_z`` = ``zone_gains`` (dimensionless,
  mean 1), ``b`` and ``zone_offsets`` in reading units. ``s(x)`` (``phase_coeffs``, sine/cosine
  pairs of 2 pi k x) corrects what is left of the sub-bin estimator's bias with a period of one bin
  (:attr:`PeakParams.subbin`: large for the spline's maximum, small for the centroid). ``c`` (``residual_coeffs``) is a
  smooth residual correction shared by all zones: a Chebyshev series in ``r`` over
  ``residual_domain`` (m), evaluated at ``r`` clipped to the domain. Empty coefficient lists and unit
  gains are the paper's model.
* beyond the residual domain's far end ``hi`` (a range farther than the calibration read), each zone's
  mapping goes on as a straight line from its value at ``hi`` with its mean slope over the domain's last
  :data:`FAR_SECANT` (:meth:`PeakParams.far_extension`): time of flight is linear in range there, and the
  corrections' slope at the far end is the sweep's best word on it. (Until 2026-12-05 the corrections were
  held at their value at ``hi``, which dropped their slope: a calibration on the real sweep to 20 cm read
  21-40 cm 0.6-7 mm short, 3.7 mm on average; with the slope carried on, 0.7 mm.)
* near range (histogram readings only): ``r -= e_z(r u_z)``, the calibrated error of zone ``z`` at the depth
  (m, along the optical axis) of its first-pass point, from a per-zone table over depth (``near_depths``,
  ``near_errors``: shape-preserving PCHIP between the knots, the first knot's value before it, none from
  the last knot on, where every zone's error is 0). There the emitter beside the receiver lights each
  zone's footprint only in part, so a zone's return comes from a point off its nominal direction and its
  timing no longer follows the far-range model; the table is fitted on a calibration sweep
  (:mod:`place_safe.calibration.near_range`). In a frame with any zone closer than the table's end,
  zones whose return is below ``near_min_fraction`` of the frame's highest are dropped: so little light
  comes from the edge of the lit spot or from other zones.
* direction of zone ``z``: the zone-centre direction (:data:`place_safe.sensor.zones.ZONE_DIRECTIONS`)
  with its angle from the optical axis multiplied by ``edge_scale`` (zones 2, 4, 6, 8) or
  ``corner_scale`` (zones 1, 3, 7, 9); azimuth kept, the centre zone stays on the axis.

The parameters are fitted from data by :mod:`place_safe.calibration.points`.
"""

from __future__ import annotations

import math
from typing import ClassVar, NamedTuple

from pydantic import Field, PrivateAttr, model_validator

import numpy as np
from numpy.polynomial import chebyshev as cheb
from scipy.linalg import lapack

from place_safe.config import ParamModel, vector
from place_safe.exceptions import CalibrationError, NoPlaneError
from place_safe.geometry import Plane
from place_safe.sensor.histogram import CENTROID_HALF_WIDTH, CENTROID_HALF_WIDTHS, SUBBIN_METHODS, find_peaks, find_returns
from place_safe.sensor.zones import CORNER, EDGE, N_ZONES, ZONE_DIRECTIONS, ZONE_KIND

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
#: m: closest two knots of the near-range table may lie (closer ones make its interpolant's slopes overflow).
NEAR_MIN_SPACING = 1e-6
#: Fixed-point iterations inverting ``m r + c(r) = x`` (c changes by far less than m per metre). Against 10
#: iterations, 2 leave at most 0.002 mm on the real sweep's calibration (3: 0.0001 mm, 1: 0.05 mm).
RANGE_ITERATIONS = 2
#: Spacing (m) of each zone's tabulated inverse of the mapping with its own terms in the inverse range
#: (:meth:`PeakParams._inverse_mapping`), and the bounds on its number of points (the real sweep's 0.37 m domain: 3700).
INVERSE_TABLE_SPACING = 1e-4
INVERSE_TABLE_POINTS = (2048, 20000)
#: m: the most each zone's own terms may move a range anywhere in the domain (:meth:`PeakParams.inverse_problem`; as
#: a range correction, more than 5 cm is not a correction: the real sweep's peak fits move ranges by at most 9-10 mm,
#: the odd half's on-sensor distances by 23 mm).
INVERSE_MAX_SHIFT = 0.05
#: The least slope, per unit of the linear part's ``m g``, of the mapping with the terms over the domain: it must
#: keep rising with range for a reading to have one range (the real peak fits: 0.84 and more; the odd half's
#: on-sensor distances 0.58), and its inverse is then tabulated to well under a micrometre.
INVERSE_MIN_SLOPE = 0.5
#: Share of the residual domain, at its far end, over which each zone's mapping's slope is measured for its straight
#: continuation beyond the domain (:meth:`PeakParams.far_extension`): a secant, steadier than the series' slope at its
#: very end. Calibrations of the real sweep cut at 13, 15, 20, 25 and 30 cm read the frames beyond at 2.6 / 2.2 /
#: 0.7 / 0.2 / 0.6 mm offset error (held: 11.4 / 7.2 / 3.7 / 0.2 / 0.7; the end slope: 2.4 / 2.8 / 1.0 / 0.2 / 0.8).
FAR_SECANT = 0.25
#: The most that slope may differ from the linear part's (a fraction of ``m g``): a mapping whose corrections turn
#: more steeply at the domain's end is continued at this slope (the real sweep's cut calibrations: 0.3-3 %).
FAR_SLOPE_MAX = 0.1
#: m: the narrowest ``residual_domain`` (``hi - lo``). The series in ``u = (2 r - lo - hi) / (hi - lo)`` and the
#: inverse-range table divide by the width; a narrower domain loses the series' argument to rounding (and at 0 divides
#: by zero). Calibration widens a sweep narrower than this to it (:func:`~place_safe.calibration.points.fit_linear`).
MIN_DOMAIN_WIDTH = 1e-3
#: m: the most a zone's calibrated offset may move its range (``PeakParams.zone_offsets`` over ``m``). Calibrations of
#: the real sweep and the simulated units hold 8-12 mm; an offset of a histogram's length (accepted before, in
#: reading units) read a level table 80 deg off as a calibrated plane (an adversarial review, session 89).
MAX_ZONE_OFFSET = 0.05
#: m: largest zone residual a mapping may state (PeakParams.zone_residual, .common_residual); the real sweep's on-sensor
#: distances leave 0.5-0.9 mm.
MAX_ZONE_RESIDUAL = 0.1


class PeakParams(ParamModel):
    """Reading-to-point mapping of the peak and on-sensor-distance methods (see module doc).

    ``m``: reading units per metre; ``b``, ``zone_offsets`` (9), ``residual_coeffs``: reading units;
    ``edge_scale``, ``corner_scale``: dimensionless; ``residual_domain``: (lo, hi) metres;
    ``pileup``: 1/counts, the SPAD pile-up undone before the peak is found
    (:func:`place_safe.sensor.histogram.undo_pileup`; 0: none, and always 0 for on-sensor distances).
    ``subbin``, ``subbin_half_width`` (bins): the sub-bin estimator the readings come from
    (:data:`place_safe.sensor.histogram.SUBBIN_METHODS`); the other fields were fitted to its readings.
    Files without them are ``"spline"`` (the estimator before the windowed centroid); calibration
    writes ``"centroid"``. ``near_depths`` (K knots, m, increasing), ``near_errors`` (K x 9, m, knot-major,
    the last knot's all 0), ``near_min_fraction``: the near-range table (module doc; empty: none).
    ``zone_residual``, ``common_residual`` (m, 0 .. :data:`MAX_ZONE_RESIDUAL`; 0: not known): what the mapping
    leaves of the zones' range errors on its calibration frames, the part each zone has on its own (RMS about its
    frame's mean error) and the part a frame's zones share (the frame means' spread less the own part's share);
    :func:`~place_safe.calibration.points.fit_proprietary` writes them and the ``proprietary`` method states its
    covariance from them (:mod:`place_safe.recovery.proprietary`). ``zone_inverse`` (reading units, 9 a power,
    power-major; empty: none): each zone's own terms in the inverse range (:meth:`inverse_correction`), which the
    peak calibration fits where held-out frames ask for them (:func:`~place_safe.calibration.points.select_inverse`).

    The ranges (reading units: bins for ``peak``, mm for ``proprietary``) are wide enough for either reading,
    narrow enough that no accepted value can put a point behind the sensor or overflow: the calibrated sweep
    sits far inside.
    """

    m: float = Field(..., ge=1.0, le=1e5, description="reading units per metre")
    b: float = Field(..., ge=-1e4, le=1e4, description="reading units")
    edge_scale: float = Field(1.0, gt=0.0, lt=3.0, description="(of the nominal zone angle)")
    corner_scale: float = Field(1.0, gt=0.0, lt=3.0, description="(of the nominal zone angle)")
    zone_offsets: vector(N_ZONES, ge=-1e3, le=1e3) = Field(default_factory=lambda: [0.0] * N_ZONES,
                                                           description="reading units")
    residual_coeffs: vector(ge=-1e3, le=1e3) = Field(default_factory=list, description="reading units")
    residual_domain: vector(2, ge=0.0, le=10.0) = Field(default_factory=lambda: [0.0, 1.0], description="m")
    phase_coeffs: vector(ge=-10.0, le=10.0) = Field(default_factory=list, description="reading units")
    zone_gains: vector(N_ZONES, gt=0.0, le=10.0) = Field(default_factory=lambda: [1.0] * N_ZONES,
                                                         description="(relative, mean 1)")
    pileup: float = Field(0.0, ge=0.0, le=1e-3, description="1/counts")
    subbin: str = "spline"
    subbin_half_width: float = Field(CENTROID_HALF_WIDTH, ge=CENTROID_HALF_WIDTHS[0], le=CENTROID_HALF_WIDTHS[1],
                                     description="bins")
    near_depths: vector(ge=0.0, le=10.0) = Field(default_factory=list, description="m")
    near_errors: vector(ge=-0.1, le=0.1) = Field(default_factory=list, description="m")
    near_min_fraction: float = Field(0.0, ge=0.0, lt=1.0, description="(of the frame's highest return)")
    zone_residual: float = Field(0.0, ge=0.0, le=MAX_ZONE_RESIDUAL, description="m")
    common_residual: float = Field(0.0, ge=0.0, le=MAX_ZONE_RESIDUAL, description="m")
    zone_inverse: vector(ge=-1e3, le=1e3) = Field(default_factory=list, description="reading units")

    what: ClassVar[str] = "peak parameters"
    error: ClassVar[type[Exception]] = CalibrationError
    _cache: dict = PrivateAttr(default_factory=dict)  # values computed from the fields (see _memo)

    @model_validator(mode="after")
    def _consistent(self) -> "PeakParams":
        if self.subbin not in SUBBIN_METHODS:
            raise ValueError(f"subbin must be one of {', '.join(SUBBIN_METHODS)}, got {self.subbin!r}")
        if (worst := max(abs(v) for v in self.zone_offsets)) > MAX_ZONE_OFFSET * self.m:
            raise ValueError(f"zone_offsets must move no zone's range more than {MAX_ZONE_OFFSET * 1e3:g} mm "
                             f"({MAX_ZONE_OFFSET * self.m:.4g} reading units at m = {self.m:.4g} per metre), got "
                             f"{worst:.4g}")
        if len(self.zone_inverse) % N_ZONES:
            raise ValueError(f"zone_inverse needs {N_ZONES} values per power of the inverse range, "
                             f"got {len(self.zone_inverse)}")
        lo, hi = self.residual_domain  # first: the checks below map the domain onto [-1, 1] (divide by hi - lo)
        if not hi - lo >= MIN_DOMAIN_WIDTH * (1.0 - 1e-9):  # (lo + 1 mm - lo rounds either way)
            raise ValueError(f"residual_domain must be [lo, hi] (m) with hi at least {MIN_DOMAIN_WIDTH * 1e3:g} mm "
                             f"above lo, got {self.residual_domain}")
        if self.zone_inverse and (why := self.inverse_problem()) is not None:
            raise ValueError(why)
        if len(self.phase_coeffs) % 2:
            raise ValueError("phase_coeffs needs (sin, cos) pairs, got an odd count")
        k = len(self.near_depths)
        if k == 1 or (k and not all(b - a >= NEAR_MIN_SPACING for a, b in zip(self.near_depths, self.near_depths[1:]))):
            raise ValueError("near_depths must be empty or 2 or more increasing depths (m), "
                             f"{NEAR_MIN_SPACING * 1e6:g} um apart or more, got {self.near_depths}")
        if len(self.near_errors) != N_ZONES * k:
            raise ValueError(f"near_errors needs {N_ZONES} values per near depth ({N_ZONES * k}), "
                             f"got {len(self.near_errors)}")
        if k and any(self.near_errors[-N_ZONES:]):
            raise ValueError("near_errors of the last near depth must be 0 (the table ends there)")
        return self

    # -- file form ---------------------------------------------------------------------------------
    def to_dict(self) -> dict:
        """The JSON form; without the near-range fields when there is no table and without the residuals when
        they are not known (files older versions read)."""
        d = super().to_dict()
        if not self.near_depths and not self.near_min_fraction:
            for key in ("near_depths", "near_errors", "near_min_fraction"):
                d.pop(key)
        for key in ("zone_residual", "common_residual", "zone_inverse"):
            if not d[key]:
                d.pop(key)
        return d

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
        """Unit direction (9, 3) of each zone with the edge/corner angle scales applied (read-only; kept
        for the scales it was computed with)."""
        return self._memo("_directions", (self.edge_scale, self.corner_scale), self._scaled_directions)

    def _memo(self, name: str, key: tuple, compute):
        """``compute()``, kept under ``name`` for as long as the fields it depends on (``key``) do not change."""
        cache = self.__pydantic_private__["_cache"]  # directly: pydantic's own lookup of a private name is slow
        cached = cache.get(name)
        if cached is None or cached[0] != key:
            cached = (key, compute())
            cache[name] = cached
        return cached[1]

    def _scaled_directions(self) -> np.ndarray:
        """The directions, computed (read-only: they are shared through :meth:`directions`)."""
        v = ZONE_DIRECTIONS
        theta = np.arccos(np.clip(v[:, 2], -1.0, 1.0))
        phi = np.arctan2(v[:, 1], v[:, 0])
        scale = np.ones(N_ZONES)
        scale[ZONE_KIND == EDGE] = self.edge_scale
        scale[ZONE_KIND == CORNER] = self.corner_scale
        t = theta * scale
        out = np.stack([np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)], axis=1)
        out.setflags(write=False)
        return out

    def correction(self, r0: np.ndarray) -> np.ndarray:
        """Residual correction c(r0) in reading units (0 without coefficients)."""
        r0 = np.asarray(r0, dtype=float)
        if not self.residual_coeffs:
            return np.zeros_like(r0)
        return self._correction(r0)

    def _correction(self, r: np.ndarray) -> np.ndarray:
        """c(r) for an array ``r`` (m), with coefficients: Horner on the series' power form in ``u``."""
        lo, hi = self.residual_domain
        scale, shift, coeffs = self._power_coeffs()
        u = np.minimum(np.maximum(r, lo), hi)
        u *= scale
        u += shift  # u = (2 r - lo - hi) / (hi - lo)
        out = np.full_like(u, coeffs[0])
        for c in coeffs[1:]:
            out *= u
            out += c
        return out

    def _power_coeffs(self) -> tuple[float, float, tuple[float, ...]]:
        """(scale, shift, coefficients): ``u = scale r + shift`` maps ``residual_domain`` to [-1, 1], and
        ``residual_coeffs`` (Chebyshev in ``u``) as power-series coefficients in ``u``, highest first (cached;
        the power form in ``u``, not in ``r``, which is ill-conditioned for a narrow domain far from 0)."""
        def compute() -> tuple[float, float, tuple[float, ...]]:
            lo, hi = self.residual_domain
            return (2.0 / (hi - lo), -(lo + hi) / (hi - lo),
                    tuple(float(v) for v in cheb.cheb2poly(self.residual_coeffs)[::-1]))

        return self._memo("_power", (tuple(self.residual_coeffs), tuple(self.residual_domain)), compute)

    def inverse_correction(self, r: np.ndarray) -> np.ndarray:
        """Each zone's own term in the inverse range, in reading units ((..., 9) for ranges ``r`` (..., 9), m):
        ``sum_k zone_inverse[k, z] (lo / r)^k`` for the powers ``k = 1, 2, ..`` (``zone_inverse`` power-major, 9 a
        power), ``r`` held within ``residual_domain`` ``[lo, hi]`` (a value at its nearer end outside it, as the
        residual correction's; closer than ``lo`` the near-range table takes over). 0 without coefficients.

        What it is for: a zone's peak that reads long or short by an amount that falls with range and differs
        from zone to zone, which per-zone offsets and gains cannot follow and a level table reads as a tilt that
        grows as the plane comes closer (the real sweep: 0.5-0.7 deg at 6-8 cm). On the real sweep it is there
        on both halves (terms of 9-10 mm); the independent generator's sweeps and the MuJoCo captures choose none,
        the mismatched simulator's level sweeps small ones (0.3-1 mm) that change nothing on its tilted frames.
        Likely sources: the emitter's offset from the receiver, whose parallax moves
        each zone's spot within its footprint as the range changes, or the return's strength (a timing walk),
        which on one surface also falls as a power of the range, and which a calibration on one surface cannot
        tell apart from it."""
        r = np.asarray(r, dtype=float)
        return self._inverse_terms(r) if self.zone_inverse else np.zeros_like(r)

    def _inverse_terms(self, r) -> np.ndarray:
        """:meth:`inverse_correction` at ``r`` (..., 9) (m) for a mapping with terms."""
        r = np.asarray(r, dtype=float)
        lo, hi, coeffs = self._inverse_coeffs()
        with np.errstate(invalid="ignore", divide="ignore"):
            q = lo / np.minimum(np.maximum(r, lo), hi)
            out = coeffs[-1] * q
            for k in range(len(coeffs) - 2, -1, -1):  # Horner in q: ((c_K q + c_{K-1}) q + ..) q
                out += coeffs[k]
                out *= q
        return out

    def inverse_problem(self) -> str | None:
        """Why :attr:`zone_inverse` cannot be this mapping's (None: it can): a residual domain from 0 (the terms are in
        ``lo / r``), terms that move a range by more than :data:`INVERSE_MAX_SHIFT` somewhere in the domain, or a
        mapping that rises with range by less than :data:`INVERSE_MIN_SLOPE` of its linear part somewhere (a reading
        would have more than one range, or one that moves by much more than the reading)."""
        lo, hi = (float(v) for v in self.residual_domain)
        if not lo > 0.0:
            return f"zone_inverse needs a residual_domain from above 0 m (its terms are in lo / r), got {[lo, hi]}"
        mapping = self._inverse_mapping()
        if not mapping["reach"] <= INVERSE_MAX_SHIFT:
            return (f"zone_inverse moves a range by {mapping['reach'] * 1e3:.1f} mm in its domain, more than the "
                    f"{INVERSE_MAX_SHIFT * 1e3:g} mm a correction may")
        if not mapping["min_slope"] >= INVERSE_MIN_SLOPE:
            return (f"with zone_inverse the mapping rises with range at {mapping['min_slope']:.2f} of its linear part "
                    f"somewhere in its domain (at least {INVERSE_MIN_SLOPE:g} needed: a reading must have one range)")
        return None

    def _inverse_mapping(self) -> dict:
        """The mapping with each zone's own terms, evaluated once over the residual domain (cached): on ranges ``r``
        every :data:`INVERSE_TABLE_SPACING` / 2, ``y = r + (c(r) + i_z(r)) / (m g_z)`` and from it

        - ``"reach"`` (m): the most the terms alone move a range, ``max |i_z| / (m g_z)``;
        - ``"min_slope"``: the least ``dy / dr`` between neighbours;
        - ``"screen"`` (9,), m: the most the residual correction and the terms together take off a range (the larger
          of 0 and the largest ``(c + i_z) / (m g_z)``; held beyond the domain), what a screen on the linear part of
          the mapping must allow for;
        - ``"table"``: the inverse, each zone's range at evenly spaced values of ``y`` (:data:`INVERSE_TABLE_SPACING`),
          with the end values of ``(c + i_z) / (m g_z)`` (outside the domain both are held, so there ``r = y -`` that
          value exactly), as :func:`_tabulated` reads it. Where the mapping rises at :data:`INVERSE_MIN_SLOPE` or
          more (:meth:`inverse_problem`) linear interpolation in it is within a micrometre of the exact inverse (0.2
          um on the real sweep's calibrations, 0.03 um from 5 cm on); it is built in a few milliseconds, and
          :meth:`ranges` with it takes less time than the residual correction's fixed-point iterations without the
          terms."""
        def compute() -> dict:
            lo, hi = (float(v) for v in self.residual_domain)
            n = int(np.clip(np.ceil((hi - lo) / INVERSE_TABLE_SPACING), *INVERSE_TABLE_POINTS))
            r = np.linspace(lo, hi, 2 * n)
            mz = self.m * np.asarray(self.zone_gains, dtype=float)
            terms = self._inverse_terms(np.repeat(r[:, None], N_ZONES, axis=1))  # reading units
            shift = (self.correction(r)[:, None] + terms) / mz
            y = r[:, None] + shift
            y0, y1 = y[0], y[-1]
            grid = y0 + (y1 - y0) * np.linspace(0.0, 1.0, n)[:, None]
            tab = np.stack([np.interp(grid[:, z], y[:, z], r) for z in range(N_ZONES)])  # (9, n)
            return {"reach": float((np.abs(terms) / mz).max()),
                    "min_slope": float((np.diff(y, axis=0) / np.diff(r)[:, None]).min()),
                    "screen": np.maximum(shift.max(axis=0), 0.0),
                    "table": (y0, (n - 1) / (y1 - y0), tab.ravel(), np.arange(N_ZONES) * n, shift[0], shift[-1],
                              float(n - 1), hi, 1.0 + self.far_extension()[2])}

        key = self._corrections_key()
        return self._memo("_inverse_mapping", key, compute)

    def _inverse_table(self) -> tuple:
        """The mapping's tabulated inverse with each zone's own terms (:meth:`_inverse_mapping`'s ``"table"``)."""
        return self._inverse_mapping()["table"]

    def inverse_screen_shift(self) -> np.ndarray:
        """Per zone (9,), m: the most the residual correction and the zone's own terms together take off a range
        anywhere (:meth:`_inverse_mapping`'s ``"screen"``), what a screen on the linear part of the mapping must allow
        for (:func:`~place_safe.recovery.too_close.may_be_close`). Zeros without the terms."""
        return self._inverse_mapping()["screen"] if self.zone_inverse else np.zeros(N_ZONES)

    def _inverse_coeffs(self) -> tuple[float, float, np.ndarray]:
        """(lo, hi, coefficients (powers, 9)): :attr:`zone_inverse` as an array (cached)."""
        def compute():
            c = np.asarray(self.zone_inverse, dtype=float).reshape(-1, N_ZONES)
            lo, hi = self.residual_domain
            return float(lo), float(hi), c

        return self._memo("_zone_inverse", (tuple(self.zone_inverse), tuple(self.residual_domain)), compute)

    def phase_correction(self, readings: np.ndarray) -> np.ndarray:
        """Sub-bin phase correction s(x) in reading units (0 without coefficients)."""
        x = np.asarray(readings, dtype=float)
        if not self.phase_coeffs:
            return np.zeros_like(x)
        freqs, sin_coeffs, cos_coeffs = self._memo("_phase", tuple(self.phase_coeffs), lambda: (
            2.0 * np.pi * np.arange(1, len(self.phase_coeffs) // 2 + 1),
            np.asarray(self.phase_coeffs[0::2]), np.asarray(self.phase_coeffs[1::2])))
        w = x[..., None] * freqs  # (..., 9, harmonics)
        return np.sin(w) @ sin_coeffs + np.cos(w) @ cos_coeffs

    def _near_table(self):
        """The near-range table as one PCHIP over depth with the 9 zones as columns (cached)."""
        return self._memo("_near", (tuple(self.near_depths), tuple(self.near_errors)), lambda: near_table(
            self.near_depths, np.asarray(self.near_errors).reshape(len(self.near_depths), N_ZONES)))

    def near_correction(self, r0: np.ndarray) -> np.ndarray:
        """The near-range table's error e_z (m, (..., 9)) at first-pass ranges ``r0`` (..., 9): 0 without a
        table and from its last depth on."""
        r0 = np.asarray(r0, dtype=float)
        errors = self._near_errors(r0) if self.near_depths else None
        return np.zeros_like(r0) if errors is None else errors

    def far_extension(self) -> tuple[float, np.ndarray, np.ndarray]:
        """(``hi``, shift (9,), slope (9,)): how each zone's mapping goes on beyond the residual domain's far end
        ``hi`` (m). In linear range ``y = x' / (m g_z) = r + s_z(r)``, ``s_z = (c + i_z) / (m g_z)`` (m), a range ``r``
        beyond ``hi`` reads ``y = hi + s_z(hi) + (1 + slope_z) (r - hi)``: the shift at ``hi`` and the secant slope of
        ``s_z`` over the domain's last :data:`FAR_SECANT` (within +-:data:`FAR_SLOPE_MAX`). Zeros without corrections
        (cached)."""
        def compute() -> tuple[float, np.ndarray, np.ndarray]:
            lo, hi = (float(v) for v in self.residual_domain)
            if not (self.residual_coeffs or self.zone_inverse):
                return hi, np.zeros(N_ZONES), np.zeros(N_ZONES)
            w = FAR_SECANT * (hi - lo)
            r = np.repeat(np.array([[hi], [hi - w]]), N_ZONES, axis=1)
            s = self.correction(r) + self.inverse_correction(r)
            s = s / (self.m * np.asarray(self.zone_gains, dtype=float))
            return hi, s[0], np.clip((s[0] - s[1]) / w, -FAR_SLOPE_MAX, FAR_SLOPE_MAX)

        key = self._corrections_key()
        return self._memo("_far_extension", key, compute)

    def _corrections_key(self) -> tuple:
        """What the inverse table and the far continuation depend on (their cache key): the linear scale and gains,
        the residual series, its domain and each zone's inverse-range terms."""
        return (self.m, tuple(self.zone_gains), tuple(self.residual_coeffs), tuple(self.residual_domain),
                tuple(self.zone_inverse))

    def far_screen(self) -> float:
        """m: the depth (along the optical axis) beyond which a zone's range may lie past the residual domain's far end:
        that end times the least depth per unit range of the zones' directions (cached; a frame whose zones all lie
        closer has no range past it)."""
        hi = self.residual_domain[1]
        return self._memo("_far_screen", (self.edge_scale, self.corner_scale, hi),
                          lambda: float(hi * self.directions()[:, 2].min()))

    def ranges(self, readings: np.ndarray) -> np.ndarray:
        """Ranges (m) for readings (..., 9): see the module doc."""
        x = np.asarray(readings, dtype=float)
        shift, mz = self._memo("_linear", (self.m, self.b, tuple(self.zone_offsets), tuple(self.zone_gains)), lambda: (
            self.b + np.asarray(self.zone_offsets), self.m * np.asarray(self.zone_gains)))
        x = x - self.phase_correction(x) - shift
        r = x / mz
        if self.zone_inverse:  # m g r + c(r) + i_z(r) = x, by the mapping's inverse tabulated once (_inverse_table)
            r = _tabulated(r, *self._inverse_table())
        elif self.residual_coeffs:
            y = r
            for _ in range(RANGE_ITERATIONS):  # solve m g r + c(r) = x by fixed-point iteration
                r = (x - self._correction(r)) / mz
            if np.fmax.reduce(r, axis=None, initial=-np.inf) > self.residual_domain[1]:  # beyond the domain: a line
                hi, shift_hi, slope = self.far_extension()
                r = np.where(r > hi, _past_end(y, hi, shift_hi, 1.0 + slope), r)
        if self.near_depths and (errors := self._near_errors(r)) is not None:
            r = r - errors
        return r

    def _near_errors(self, r: np.ndarray) -> np.ndarray | None:
        """:meth:`near_correction` of a mapping with a near-range table at ranges ``r`` (..., 9; m), or None where no
        zone lies closer than the table's last depth (NaN: none), whose errors are all 0 there: the usual frame."""
        depth = r * self.directions()[:, 2]
        if not np.fmin.reduce(depth, axis=None, initial=np.inf) < self.near_depths[-1]:
            return None
        return near_table_errors(self._near_table(), self.near_depths, depth)

    def without_near_table(self) -> "PeakParams":
        """A copy without the near-range table (no depths, errors or weak-return fraction): the far-range mapping."""
        return self.replace(near_depths=[], near_errors=[], near_min_fraction=0.0)

    @property
    def drops_weak(self) -> bool:
        """Whether the near-range rule drops weak zones (a table and a fraction above 0)."""
        return bool(self.near_depths) and self.near_min_fraction > 0.0

    def drop_weak(self, readings: np.ndarray, valid: np.ndarray, heights: np.ndarray) -> np.ndarray:
        """The return mask (..., 9) without the zones that the near-range rule drops: in frames with a zone closer
        than the table's last depth, returns below ``near_min_fraction`` of the frame's highest (module doc)."""
        if not self.drops_weak:
            return valid
        top = np.where(valid, heights, 0.0).max(axis=-1, keepdims=True)
        weak = valid & (heights < self.near_min_fraction * top)
        if not weak.any():  # the usual frame: no ranges needed
            return valid
        depth = self.ranges(np.where(valid, readings, np.nan)) * self.directions()[:, 2]
        with np.errstate(invalid="ignore"):
            near = (valid & (depth < self.near_depths[-1])).any(axis=-1, keepdims=True)
        return valid & ~(near & weak)

    def peaks(self, hists: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Readings (..., 9) in bins of histograms (..., 9, 128) with this mapping's pile-up and sub-bin
        estimator, the return mask and the saturation mask (:func:`~place_safe.sensor.histogram.find_peaks`),
        without the zones the near-range rule drops (:meth:`drop_weak`)."""
        if not self.drops_weak:
            return find_peaks(hists, self.pileup, self.subbin, self.subbin_half_width)
        pos, _, valid, saturated = self.returns(hists)
        return pos, valid, saturated

    def returns(self, hists: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`peaks` with each zone's maximum from the same pass (readings, maxima, return mask, saturation
        mask; :func:`~place_safe.sensor.histogram.find_returns`)."""
        if not self.drops_weak:
            return find_returns(hists, self.pileup, self.subbin, self.subbin_half_width)
        pos, top, valid, saturated, heights = find_returns(hists, self.pileup, self.subbin, self.subbin_half_width,
                                                           heights=True)
        keep = self.drop_weak(pos, valid, heights)
        return np.where(keep, pos, np.nan), np.where(keep, top, np.nan), keep, saturated

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


def _tabulated(y: np.ndarray, y0: np.ndarray, inv_dy: np.ndarray, tab: np.ndarray, base: np.ndarray,
               shift_lo: np.ndarray, shift_hi: np.ndarray, last: float, hi: float, rise: np.ndarray) -> np.ndarray:
    """Ranges (m, (..., 9)) at linear ranges ``y`` (..., 9) from :meth:`PeakParams._inverse_table`'s table: linear
    interpolation inside it; before it ``y`` less the held end value (the near-range table takes over there), beyond
    it the straight continuation from the domain's far end ``hi`` (m) rising ``rise`` (9,) per m of range
    (:meth:`PeakParams.far_extension`); NaN stays NaN."""
    t = (y - y0) * inv_dy
    if t.size and t.min() >= 0.0 and t.max() <= last - 1e-9:  # every reading inside the table, none NaN: usual
        k = t.astype(np.intp)
        idx = k + base
        a = tab[idx]
        return a + (t - k) * (tab[idx + 1] - a)
    tc = np.fmin(np.fmax(t, 0.0), last - 1e-9)  # (fmax / fmin: a NaN becomes a finite index, put back below)
    k = tc.astype(np.intp)
    f = tc - k
    idx = k + base
    a = tab[idx]
    r = a + f * (tab[idx + 1] - a)
    r = np.where(t < 0.0, y - shift_lo, np.where(t > last, _past_end(y, hi, shift_hi, rise), r))
    r += y * 0.0  # NaN readings give NaN ranges
    return r


def _past_end(y: np.ndarray, hi: float, shift_hi: np.ndarray, rise: np.ndarray) -> np.ndarray:
    """Ranges (m) at linear ranges ``y`` (..., 9) on the mapping's straight continuation past its domain's far end
    ``hi`` (m), where each zone's linear range is ``hi + shift_hi`` (9,) and rises ``rise`` (9,) per m of range
    (:meth:`PeakParams.far_extension`); NaN stays NaN."""
    with np.errstate(invalid="ignore"):
        return hi + (y - hi - shift_hi) / rise


# ---------------------------------------------------------------------------------------------
# Batched plane fit
# ---------------------------------------------------------------------------------------------
def near_table(depths, errors: np.ndarray):
    """Near-range table(s) (:attr:`PeakParams.near_depths`, ``near_errors``) as one PCHIP over depth: ``errors``
    (K, ..., 9), m, at the K ``depths`` (m); the zones (and any tables between, e.g. several candidates of a
    calibration) are its columns."""
    from scipy.interpolate import PchipInterpolator

    return PchipInterpolator(np.asarray(depths, dtype=float), np.asarray(errors, dtype=float), axis=0)


def near_table_errors(table, depths, depth: np.ndarray) -> np.ndarray:
    """Each zone's range error e_z (m) by the table(s) ``table`` (:func:`near_table` over ``depths``) at that zone's
    depth ``depth`` (..., 9), m: (..., [tables,] 9); held at the first depth's error closer than it, 0 from the last
    depth on (and at NaN depths)."""
    depth = np.asarray(depth, dtype=float)
    lo, hi = depths[0], depths[-1]
    with np.errstate(invalid="ignore"):
        near = depth < hi
    e = table(np.minimum(np.maximum(depth, lo), hi))  # (..., 9 depths, [tables,] 9 zones)
    extra = e.ndim - depth.ndim - 1  # the tables' axes
    if extra:
        near = near.reshape(depth.shape[:-1] + (1,) * extra + depth.shape[-1:])
    # each zone's own error: the diagonal of depths and zones, which comes last (..., [tables,] 9)
    return np.where(near, e.diagonal(axis1=depth.ndim - 1, axis2=-1), 0.0)


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
    ok = (count >= 3) & _determines_plane(s, n, d)
    if (part := ok & (count < pts.shape[-2])).any():  # fewer zones than all: their rays may lie in one plane
        ok[part] = _rays_span(safe_pts[part], w[part] > 0)
    n = np.where(ok[..., None], n, np.nan)
    d = np.where(ok, d, np.nan)
    rms = np.where(ok, rms, np.nan)
    return n, d, rms, ok



#: A plane fit's points are collinear where their second singular value is at most this fraction of the first.
COLLINEAR_FRACTION = 1e-9
#: The zones' rays lie in one plane through the sensor (a row, a column or a diagonal of the 3x3 grid: the tilt about the
#: line where that plane meets the surface is not determined) where the smallest singular value of the used points'
#: unit directions is at most this fraction of the largest. Such points lie in that plane of rays whatever their
#: ranges, so a range error moves them off their line within it: an edge column alone read a level table 9 deg off
#: with a covariance of the floor's 0.5 deg (calibrated), 68 deg off with none (uncalibrated; an adversarial review,
#: session 89). The grid's lines read 0.000-0.005 (the lens's distortion bends the edge rows and columns), every
#: other set of 3 or more zones 0.037 or more (calibrated and nominal directions alike). A line has 3 zones, so only
#: fits of fewer than 9 points are tested.
COPLANAR_RAYS = 0.015
#: A plane fit's normal lies in the sensor's x-y plane (the plane holds the optical axis) where ``n_z`` is at most this.
MIN_NORMAL_Z = 1e-6


def _rays_span(points: np.ndarray, used: np.ndarray) -> np.ndarray:
    """Whether the rays to the ``used`` points (..., N, 3; mask (..., N)) do not lie in one plane through the sensor
    (:data:`COPLANAR_RAYS`)."""
    with np.errstate(invalid="ignore", divide="ignore"):
        u = points / np.linalg.norm(points, axis=-1, keepdims=True)
    u = np.where(used[..., None] & np.isfinite(u), u, 0.0)
    sv = np.linalg.svd(u, compute_uv=False)
    return sv[..., 2] > COPLANAR_RAYS * np.maximum(sv[..., 0], 1e-30)


def _determines_plane(s: np.ndarray, n: np.ndarray, d) -> np.ndarray:
    """Whether a least-squares fit with singular values ``s`` (..., 3) of its centred points, normal ``n``
    (..., 3) and offset ``d`` (...) is a plane: the points not collinear, the normal off the sensor's
    x-y plane and the plane in front of the sensor."""
    return (s[..., 1] > COLLINEAR_FRACTION * np.maximum(s[..., 0], 1e-30)) & (n[..., 2] > MIN_NORMAL_Z) & (d > 0)


def plane_covariance(points: np.ndarray, valid: np.ndarray, plane: Plane, range_std: float | np.ndarray = 0.0,
                     replace_fit: bool = False, common_std: float | np.ndarray = 0.0) -> np.ndarray:
    """Covariance (3, 3) of ``(n_x, n_y, d)`` of a least-squares plane through points (N, 3) with mask (N,).

    The perpendicular residuals ``n . p - d`` are linearised in the normal's x and y components (``n_z``
    follows from unit length) and the offset; their variance is estimated from the fit itself
    (sum of squares over ``N - 3``; zero with exactly 3 points, which fit any plane). ``range_std`` (m, one
    value or one per point): a known error of each point's range (along its direction from the origin; the
    peak method's zone errors at near range, :meth:`~place_safe.recovery.estimator.Uncertainty.near_std`).
    Each point's residual variance is then the larger of the fit's and that error's share off the plane,
    carried through the fit point by point (the points actually used, along their own directions).
    ``replace_fit``: each point with a known error takes that error's share alone, not the larger of it and the
    fit's (a calibrated error that already holds what the residual would say; points without one keep the fit's).
    ``common_std`` (m, one value or one per point; with ``replace_fit``): a range error the points share besides,
    one error along all their rays at once (each point's ``range_std`` is then its independent part).
    The two steps are :func:`plane_fit_geometry` (the fit's own part) and :func:`known_error_covariance` (the known
    errors carried through it), which a caller holding many fits and trying many errors calls apart.
    """
    if np.ndim(range_std) == 0 and not range_std > 0.0:  # the usual call: no known error
        _, _, sigma2, inverse = _fit(points, valid, plane)
        return sigma2 * inverse
    return known_error_covariance(plane_fit_geometry(points, valid, plane), range_std, replace_fit, common_std)


class PlaneFitGeometry(NamedTuple):
    """What the covariance of a least-squares plane takes from its fit alone (:func:`plane_fit_geometry`), for
    N points; the arrays may carry leading axes (many fits, stacked: :func:`known_error_covariance` takes either)."""

    inverse: np.ndarray  #: (3, 3) the inverse of the residuals' normal matrix in (n_x, n_y, d)
    gain: np.ndarray  #: (3, N) each point's residual carried to (n_x, n_y, d): ``inverse @ jac^T``; 0 for a point not used
    off_plane: np.ndarray  #: (N,) the cosine of each point's ray with the normal (0 for a point not used)
    sigma2: np.ndarray  #: () the fit's residual variance (m^2; 0 with exactly 3 points)
    used: np.ndarray  #: (N,) bool, the points the fit used


def plane_fit_geometry(points: np.ndarray, valid: np.ndarray, plane: Plane) -> PlaneFitGeometry:
    """The fit's own part of :func:`plane_covariance` of ``plane`` through ``points`` (N, 3) with mask ``valid`` (N,)."""
    used = np.asarray(valid, dtype=bool)
    p, jac, sigma2, inverse = _fit(points, used, plane)
    gain = np.zeros((3, used.size))
    gain[:, used] = inverse @ jac.T
    off_plane = np.zeros(used.size)
    with np.errstate(invalid="ignore", divide="ignore"):
        off_plane[used] = (p @ plane.normal) / np.sqrt(np.einsum("ij,ij->i", p, p))
    return PlaneFitGeometry(inverse, gain, off_plane, np.float64(sigma2), used)


def _fit(points: np.ndarray, valid: np.ndarray, plane: Plane) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """The points used (k, 3), the residuals' Jacobian in (n_x, n_y, d) (k, 3), their variance from the fit and the
    inverse (3, 3) of their normal matrix: :func:`plane_covariance`'s linearisation."""
    p = np.asarray(points, dtype=float)[np.asarray(valid, dtype=bool)]
    n = plane.normal
    jac = p - p[:, 2:] * (n / n[2])  # columns: d(res)/d(n_x), d(res)/d(n_y); the third is replaced next
    jac[:, 2] = -1.0
    res = p @ n - plane.offset
    dof = len(p) - 3
    sigma2 = float(res @ res) / dof if dof > 0 else 0.0
    inverse = _inverse(jac.T @ jac)
    inverse = 0.5 * (inverse + inverse.T)  # LU's inverse of a symmetric matrix is symmetric only to rounding
    return p, jac, sigma2, inverse


def known_error_covariance(geometry: PlaneFitGeometry, range_std: np.ndarray, replace_fit: bool = False,
                           common_std: np.ndarray | float = 0.0) -> np.ndarray:
    """:func:`plane_covariance` (..., 3, 3) of fits' ``geometry`` (:func:`plane_fit_geometry`; stacked along leading
    axes, or one) with each point's known range error ``range_std`` (..., N, or one value; m) and the error the points
    share ``common_std`` (..., N, or one value; m): see there. Where no point used has a known error above 0, the fit's
    own covariance ``sigma2 inverse`` (the shared error then unused)."""
    g = geometry
    std = np.asarray(range_std, dtype=float)
    shared_std = np.asarray(common_std, dtype=float)
    with np.errstate(invalid="ignore"):
        known = (std * g.off_plane) ** 2  # (a fresh array: NaN set to 0 in place, as np.nan_to_num would, faster)
        any_known = ((std > 0.0) & g.used).any(axis=-1)
    known[np.isnan(known)] = 0.0
    sigma2 = np.asarray(g.sigma2)[..., None]
    var = np.where(known > 0.0, known, sigma2) if replace_fit else np.maximum(sigma2, known)
    gain_t = g.gain.swapaxes(-1, -2)  # (the method: a frame's microsecond less than np.swapaxes)
    cov = (g.gain * var[..., None, :]) @ gain_t
    if replace_fit and (shared_std > 0.0).any():  # (a fit without a shared error gets 0 from it)
        common = shared_std * g.off_plane
        common[np.isnan(common)] = 0.0
        shared = (common[..., None, :] @ gain_t)[..., 0, :]  # the state's response to the shared error
        cov = cov + shared[..., :, None] * shared[..., None, :]
    cov = 0.5 * (cov + cov.swapaxes(-1, -2))  # (the sandwich's products leave 1e-20 of asymmetry)
    return np.where(any_known[..., None, None], cov, np.asarray(g.sigma2)[..., None, None] * g.inverse)


def _inverse(a: np.ndarray) -> np.ndarray:
    """The inverse of a small square matrix by LAPACK's LU (getrf, getri through SciPy: 1.4 against numpy's
    5 us for 3 x 3, a frame's share of peak's budget), the pseudo-inverse where it is singular."""
    lu, piv, info = lapack.dgetrf(a)
    if info == 0:
        inverse, info = lapack.dgetri(lu, piv)
        if info == 0:
            return inverse
    return np.linalg.pinv(a)


def _svd(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Singular values and right singular vectors (rows) of a small matrix: LAPACK's gesdd through SciPy, the
    routine numpy.linalg.svd calls, with the same results and a quarter of its overhead (3.5 against 12 us
    for 9 x 3)."""
    _, s, vt, info = lapack.dgesdd(a, compute_uv=1, full_matrices=0)
    if info != 0:
        _, s, vt = np.linalg.svd(a, full_matrices=False)  # raises LinAlgError where gesdd did not converge
    return s, vt


def plane_through(points: np.ndarray, valid: np.ndarray) -> tuple[Plane, float]:
    """The least-squares plane of one frame's zone points (9, 3) with mask (9,), and its RMS residual (m);
    raises NoPlaneError. The maths and the conditions of :func:`fit_planes`, for one frame without the
    batch's masking (a frame's estimate comes from here on every frame the sensor sends)."""
    pts = np.asarray(points, dtype=float)
    valid = np.asarray(valid, dtype=bool)
    if (used := np.count_nonzero(valid)) < 3:
        raise NoPlaneError(f"only {used} zones have a return; a plane needs 3 or more")
    keep = valid & np.isfinite(pts).all(axis=-1)
    count = np.count_nonzero(keep)
    if count < 3:
        raise NoPlaneError("the zone points do not determine a plane in front of the sensor")
    p = pts[keep]
    centroid = p.sum(axis=0) / count  # as p.mean, without its overhead
    s, vt = _svd(p - centroid)
    n = vt[-1] if vt[-1, 2] >= 0 else -vt[-1]
    d = float(n @ centroid)
    s0, s1, s2 = s.tolist()
    if count < keep.size and not _rays_span(p, np.ones(count, dtype=bool)):  # fit_planes' test, said first
        raise NoPlaneError(f"the zone points do not determine a plane in front of the sensor (the {count} zones with a "
                           "return lie along one line of the grid: the tilt about it is not determined)")
    if not (s1 > COLLINEAR_FRACTION * max(s0, 1e-30) and n[2] > MIN_NORMAL_Z and d > 0):  # _determines_plane's test
        raise NoPlaneError("the zone points do not determine a plane in front of the sensor")
    return Plane(n, d), s2 / math.sqrt(count)


__all__ = ["PeakParams", "fit_planes", "plane_through", "plane_covariance", "PlaneFitGeometry",
           "plane_fit_geometry", "known_error_covariance", "PAPER_PEAK_M", "PAPER_PEAK_B", "BIN_SIZE", "MM_PER_M"]
