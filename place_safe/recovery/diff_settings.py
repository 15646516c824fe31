"""What a calibration's ``diff`` section states, and the differentiable method's solver options: the range correction
(:class:`RangeCorrection`) and :class:`SolverOptions` with their checks, and the constants the calibration shares with
the solver (:data:`NEAR_FALLBACK_RANGE`, :data:`BLENDED`, :data:`CROSSTALK_LEFT_SHARE`). No torch here: a calibration
file is read and checked, the peak method runs and ``calibrate --method peak`` fits, without loading the solver
(:mod:`place_safe.recovery.differentiable`, which uses them).
"""

from __future__ import annotations

import math
import reprlib
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np
from pydantic import Field, model_validator

from place_safe.config import ParamModel, field_interval, vector
from place_safe.exceptions import CalibrationError
from place_safe.sensor.frame import N_BINS


#: Share of the peak mapping's calibrated domain end by which a zone's range must lie past it for a calibrated diff to
#: return peak's plane there (``DifferentiableEstimator._past_range``): a few millimetres past the farthest frame the
#: forward model's range law still holds (the real sweep's published frames run 5 mm past its sample's end).
FAR_FALLBACK_PAST = 0.05
NEAR_FALLBACK_RANGE = 0.05
"""m: closer than this (peak's plane offset) a calibrated fast solver returns peak's plane; the fallback limits are
chosen on calibration frames at or beyond it (:func:`place_safe.calibration.uncertainty.fit_diff_uncertainty`).
Measured again with the forward fit and plane correction reaching down to 1.5-2 cm (docs/results.md, "Diff at 2-5 cm"):
on six simulated units diff's own 2-5 cm plane stayed 6-14 times peak's error on level frames (a timing error that
repeats every bin, falling as 1 / z0) with NEES 2-5; moved to 3.5 or 2 cm, the calibrated limits kept real planes
1.8 and 14 deg off where peak read 0.1 and 3.3 deg."""

#: ``method_used`` of a plane blended from diff's and peak's (``Uncertainty.blend``).
BLENDED = "diff+peak"

#: The share of its fitted value that a level sweep leaves undetermined of the crosstalk (taken so: seeds 0 and 3 of
#: the generator fitted 0.012 and 0.0065 against true values near 0.0098 and 0.0080, seeds 1 and 7 2.5-3 times the
#: truth). Sizes the prior under which diff solves each frame's crosstalk after a level sweep
#: (:attr:`SolverOptions.crosstalk_std`, :func:`~place_safe.calibration.forward_fit.free_crosstalk_std`) and the
#: crosstalk's part of its stated tilt term (:data:`~place_safe.calibration.uncertainty.DIFF_TILT_PER_CROSSTALK`).
CROSSTALK_LEFT_SHARE = 0.5


class RangeCorrection(ParamModel):
    """A calibrated correction of the recovered plane as a function of its axis crossing ``z0``.

    ``z0 += c(z0)`` and, in the optical frame, the slopes ``a += ca(z0) + ga(z0) a``,
    ``b += cb(z0) + gb(z0) b`` (plane ``a x + b y + z = z0``; ``ga``, ``gb``: a tilt read a fraction too
    large or too small, e.g. 1 % along y on the independent generator's frames). Each is a Chebyshev
    series (coefficients in metres, or dimensionless for the slopes and gains) on ``domain`` (m) in the range
    ``z0`` or, for the series named in ``inverse``, in the inverse range ``1 / z0`` (:func:`range_argument`:
    an error that grows as the plane comes closer, e.g. a zone's depth disagreement of fixed size seen as a
    slope, is a low-degree series there); outside the domain the value at its nearer end is used. Fitted by
    :func:`place_safe.calibration.plane_correction.fit_range_correction` to what the forward model leaves
    over on data with ground truth; empty coefficients mean no correction.

    ``albedo`` is a series of the log albedo in ``ln z0`` (a range law: a power of the range is a line there): the
    reported albedo is ``exp(log rho + albedo(z0))``. It is what a
    sweep of one surface reads as a trend of its albedo over distance (the real sweep: 14 at 5 cm, 25 at 10 cm, 28
    at 38 cm, smooth and the same on both halves), the return's range law that the forward fit cannot see because
    every calibration frame's albedo is free; fitted to the sweep's mean log albedo, so the scale stays the
    forward model's.

    The ranges: what the forward model leaves over is millimetres and a fraction of a degree, so a correction
    of more than 5 cm (or a slope of 0.5) is not a correction; nor is an albedo factor beyond ``e^3``. Each field's
    range bounds its coefficients and also the series' value: the sizes of a series' coefficients sum to at most
    the range's larger bound (a Chebyshev series on its domain never exceeds that sum), so 400 coefficients of 5 cm
    cannot move a plane by 20 m, nor an albedo series overflow.
    """

    what: ClassVar[str] = "range correction"
    error: ClassVar[type[Exception]] = CalibrationError

    coeffs: vector(ge=-0.05, le=0.05) = Field(default_factory=list, description="m")
    domain: vector(2, ge=0.0, le=10.0) = Field(default_factory=lambda: [0.0, 1.0], description="m")
    slope_a: vector(ge=-0.5, le=0.5) = Field(default_factory=list, description="(slope)")
    slope_b: vector(ge=-0.5, le=0.5) = Field(default_factory=list, description="(slope)")
    gain_a: vector(ge=-0.2, le=0.2) = Field(default_factory=list, description="(of the slope)")
    gain_b: vector(ge=-0.2, le=0.2) = Field(default_factory=list, description="(of the slope)")
    albedo: vector(ge=-3.0, le=3.0) = Field(default_factory=list, description="(log albedo)")
    inverse: list[Literal["coeffs", "slope_a", "slope_b", "gain_a", "gain_b"]] = Field(
        default_factory=list, description="series in the inverse range 1 / z0 (the others: in z0)")

    @model_validator(mode="after")
    def _ordered_domain(self) -> "RangeCorrection":
        if not self.domain[1] > self.domain[0]:
            raise ValueError(f"domain must be [lo, hi] with hi > lo, got {list(self.domain)}")
        if self.inverse and not self.domain[0] >= MIN_INVERSE_DOMAIN:
            raise ValueError(f"a series in 1 / z0 needs a domain from at least {MIN_INVERSE_DOMAIN} m, "
                             f"got {list(self.domain)}")
        return self

    #: the Chebyshev series of a correction (the fields :meth:`series_problem` judges)
    SERIES: ClassVar[tuple[str, ...]] = ("coeffs", "slope_a", "slope_b", "gain_a", "gain_b", "albedo")

    @model_validator(mode="after")
    def _bounded_series(self) -> "RangeCorrection":
        for name in self.SERIES:
            if (why := self.series_problem(name, getattr(self, name))) is not None:
                raise ValueError(why)
        return self

    @classmethod
    def series_problem(cls, name: str, coeffs) -> str | None:
        """Why ``coeffs`` cannot be series ``name`` (one of :data:`SERIES`), or None: a coefficient outside the field's
        range, or coefficients whose sizes sum beyond its larger bound (on its domain a Chebyshev series reaches at
        most that sum, and the range is what the correction may be: 400 coefficients of 5 cm are 20 m)."""
        lo, hi = field_interval(cls, name)
        unit = cls.model_fields[name].description
        if not all(lo <= c <= hi for c in coeffs):
            return f"{name}: a coefficient outside {lo:g} .. {hi:g} {unit}"
        reach, bound = math.fsum(abs(c) for c in coeffs), max(abs(lo), abs(hi))
        if reach > bound:
            return (f"{name}: the series reaches {reach:.4g} {unit} (the sum of its coefficients' sizes), beyond the "
                    f"{bound:g} {unit} a correction may have")
        return None

    def _series(self, name: str, z0):
        coeffs = getattr(self, name)
        if not coeffs:
            return 0.0 if np.ndim(z0) == 0 else np.zeros(np.shape(z0))
        from numpy.polynomial import chebyshev

        value = chebyshev.chebval(range_argument(z0, self.domain, name in self.inverse, name == "albedo"), coeffs)
        return float(value) if np.ndim(value) == 0 else value

    def __call__(self, z0: float) -> float:
        """The correction of z0 (m) at z0 (a float, or an array: element by element)."""
        return self._series("coeffs", z0)

    def log_albedo(self, z0: float) -> float:
        """The correction of the log albedo of a plane at z0."""
        return self._series("albedo", z0)

    def slopes(self, z0: float, a: float = 0.0, b: float = 0.0) -> tuple[float, float]:
        """The corrections of the slopes (a, b) of a plane at z0 (floats, or arrays: element by element)."""
        return (self._series("slope_a", z0) + self._series("gain_a", z0) * a,
                self._series("slope_b", z0) + self._series("gain_b", z0) * b)


#: m: the nearest domain end a series in inverse range may have (1 / z0 stays below 1000 per metre)
MIN_INVERSE_DOMAIN = 1e-3


def range_argument(z0, domain, inverse: bool = False, log: bool = False):
    """The Chebyshev argument in [-1, 1] of a plane at ``z0`` (m; a float or an array) on ``domain`` = [lo, hi]:
    ``z0`` mapped linearly (lo -> -1, hi -> 1) or, ``inverse``, ``1 / z0`` mapped linearly (hi -> -1, lo -> 1), or,
    ``log``, ``ln z0`` mapped linearly (lo -> -1, hi -> 1; ``lo`` at least :data:`MIN_INVERSE_DOMAIN`). ``z0``
    outside the domain is taken at its nearer end."""
    lo, hi = float(domain[0]), float(domain[1])
    z = np.clip(np.asarray(z0, dtype=float), lo, hi)
    if log:
        lo = max(lo, MIN_INVERSE_DOMAIN)
        t = 2.0 * (np.log(np.maximum(z, lo)) - math.log(lo)) / max(math.log(max(hi, lo) / lo), 1e-9) - 1.0
    elif inverse:
        lo = max(lo, MIN_INVERSE_DOMAIN)
        t = 2.0 * (1.0 / np.maximum(z, lo) - 1.0 / hi) / max(1.0 / lo - 1.0 / hi, 1e-9) - 1.0
    else:
        t = 2.0 * (z - lo) / max(hi - lo, 1e-9) - 1.0
    return float(t) if t.ndim == 0 else t


#: The solver's window after the latest peak before calibration files recorded it (bins): a file without
#: ``diff.window_after_peak`` was calibrated (chi-square limit, covariance scale) with this window.
LEGACY_WINDOW_AFTER_PEAK = 24


#: The smallest prior standard deviation of a frame's own crosstalk (``SolverOptions.crosstalk_std``) other than 0 (held):
#: the prior's row weighs 1 / std, and below about 1e-154 its square overflows the normal equations (the solve then never
#: leaves peak's plane while the covariance reads as the floor alone); from 1e-9 down the covariance loses digits to the
#: conditioning. ``calibrate`` writes 5e-4 or more.
MIN_CROSSTALK_STD = 1e-6


def crosstalk_std_problem(value) -> str | None:
    """Why ``value`` is not a ``crosstalk_std`` (0, or a number in :data:`MIN_CROSSTALK_STD`..0.5), or None."""
    ok = (not isinstance(value, bool) and isinstance(value, (int, float, np.integer, np.floating))
          and (value == 0 or MIN_CROSSTALK_STD <= value <= 0.5))  # (no float(): an int beyond a float compares)
    return None if ok else (f"crosstalk_std must be 0 (held) or a number in {MIN_CROSSTALK_STD:g}..0.5, "
                            f"got {reprlib.repr(value)}")


@dataclass(frozen=True)
class SolverOptions:
    """Tuning of the fast solver (defaults chosen on synthetic and real data; see docs/results.md). Frozen: an
    estimator lays out its unknowns from these when it is made (the crosstalk column, the zones' albedos, the rays),
    so options changed afterwards would disagree with that layout (``dataclasses.replace`` makes new ones)."""

    rays: int = 6                 # stratified rays per axis and zone (rays x rays per zone)
    max_iterations: int = 20
    tolerance: float = 1e-7       # relative cost decrease that ends the iterations
    # cost decrease (chi-square units, times the reduced chi-square when above 1) that ends them too: a step
    # that gains less moves the unknowns by under 0.5 standard deviation in the Fisher metric, and the next one
    # (Gauss-Newton: the gains shrink quadratically) by far less. 0.1 against 0.01: the same planes to 1e-3 deg
    # on 60 independent-generator and 60 mismatched-unit frames, 12-16 % less CPU (docs/results.md)
    chi2_tolerance: float = 0.1
    prior_specular_weight: float = 0.05   # std of the specular-weight prior
    prior_log_exponent: float = 0.25      # std of the log specular-exponent prior
    window_after_peak: int = 60   # bins fitted after the frame's latest zone peak (its tail: see docs/results.md)
    test_window: int = 24         # bins after that peak in the residual (the chi-square test of the fit)
    zone_albedo: bool = True      # an albedo per zone, so the plane rests mostly on timing and shape
    zone_albedo_spread: float = 0.1  # std of log zone albedo about the zones' mean (inf: untied)
    # the data's ambient: False, the floor measured after the return is subtracted (the model as it was); True, the
    # ambient as it arrives (sensor.histogram.arriving_ambient) goes through the pile-up with the return and the model is
    # compared with the counts above it, as the forward model was fitted with fit_forward(..., ambient=True)
    ambient: bool = False
    # the frame's scalar crosstalk between zones: 0, held at the calibrated value; above 0, solved with the plane under a
    # prior of that standard deviation about the calibrated value (a fraction; a level sweep trades it against the
    # zones' fields of view, and a tilted plane shows it). The fast solver's, as zone_albedo (paper mode holds the
    # crosstalk and reads one albedo).
    crosstalk_std: float = 0.0  # 0, or MIN_CROSSTALK_STD..0.5
    # paper mode
    paper_iterations: int = 100
    paper_rays: int = 2304
    paper_lr: float = 0.01
    seed: int = 0

    #: whole-number options and their accepted ranges (a ray grid beyond 64 x 64 per zone does not finish in
    #: useful time; the window holds at most the histogram)
    WHOLE: ClassVar[dict[str, tuple[int, int]]] = {
        "rays": (1, 64), "max_iterations": (1, 1000), "window_after_peak": (1, N_BINS), "test_window": (1, N_BINS),
        "paper_iterations": (1, 100_000), "paper_rays": (1, 100_000), "seed": (0, 2 ** 63 - 1)}
    #: real-valued options that must be finite and above 0 (``zone_albedo_spread`` may also be inf: untied)
    POSITIVE: ClassVar[tuple[str, ...]] = ("tolerance", "chi2_tolerance", "prior_specular_weight",
                                           "prior_log_exponent", "paper_lr", "zone_albedo_spread")

    def __post_init__(self) -> None:
        """Refuse options the solver cannot run with, naming the option (one line), instead of a frame without a
        plane ("SVD did not converge") or a solve that never ends."""
        for name, (lo, hi) in self.WHOLE.items():
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(f"SolverOptions: {name} must be a whole number in {lo}..{hi}, got {reprlib.repr(v)}")
        for name in self.POSITIVE:
            v = getattr(self, name)
            try:
                x = float(v) if isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool) \
                    else math.nan
            except OverflowError:  # an int beyond a float
                x = math.nan
            if not x > 0 or (math.isinf(x) and name != "zone_albedo_spread"):
                raise ValueError(f"SolverOptions: {name} must be a number above 0, got {reprlib.repr(v)}")
        if (why := crosstalk_std_problem(self.crosstalk_std)) is not None:
            raise ValueError(f"SolverOptions: {why}")
        for name in ("zone_albedo", "ambient"):
            if not isinstance(v := getattr(self, name), bool):
                raise ValueError(f"SolverOptions: {name} must be true or false, got {reprlib.repr(v)}")
