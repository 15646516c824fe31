"""Plane-recovery methods (the paper's Table I) behind one protocol.

===================== ==========================================================================
method                what it uses
===================== ==========================================================================
``diff``              differentiable rendering of the forward model (fast Gauss-Newton solver;
                      ``mode="paper"`` is the paper's Adam, 100 iterations, 2304 random rays)
``peak``              calibrated histogram-peak finding, plane fit by SVD
``peak-naive``        the same with uncalibrated (physical) constants
``proprietary``       on-sensor distances, calibrated
``proprietary-naive`` on-sensor distances as reported
===================== ==========================================================================
"""

from __future__ import annotations

import os
from typing import Any

from place_safe.recovery.estimator import Estimator, PlaneEstimate, Uncertainty
from place_safe.exceptions import ArgumentTypeError, ConfigError, PlaceSafeError

METHODS = ("diff", "peak", "peak-naive", "proprietary", "proprietary-naive")
#: What a calibration answers (:class:`place_safe.calibration.Calibration`, :class:`BuiltInParameters`); ``reference``
#: besides is optional.
_SECTION_METHODS = ("peak", "proprietary", "forward", "diff", "diff_options", "uncertainty")


class BuiltInParameters:
    """The parameters every method uses without a calibration: the same section methods as
    :class:`place_safe.calibration.Calibration` (which the estimators are built from), answered with
    the built-in defaults. Recovery never imports the calibration package: calibration depends on
    recovery, not the other way round."""

    def peak(self):
        from place_safe.recovery.points import PeakParams

        return PeakParams.default_peak()

    def proprietary(self):
        from place_safe.recovery.points import PeakParams

        return PeakParams.default_proprietary()

    def forward(self):
        from place_safe.recovery.forward import ForwardParams

        return ForwardParams()

    def diff(self):
        from place_safe.recovery.differentiable import RangeCorrection

        return RangeCorrection()

    def diff_options(self):
        from place_safe.recovery.differentiable import SolverOptions

        return SolverOptions()

    def reference(self, method: str | None = None):
        from place_safe.recovery.estimator import Reference

        return Reference() if method is not None else {}

    def uncertainty(self, method: str | None = None):
        return Uncertainty() if method is not None else {}


def make_estimator(method: str, calibration: Any = None, **options) -> Estimator:
    """The estimator for a CLI method name, using ``calibration`` where the method has one.

    ``calibration``: a :class:`~place_safe.calibration.Calibration` (``Calibration.load(path)`` reads a
    file) or None; anything else (a path, a dict, a number) raises
    :class:`~place_safe.exceptions.ArgumentTypeError` saying what was expected. Without a calibration (or without a section for the method) each method uses its
    built-in defaults (:class:`BuiltInParameters`). ``options`` go to the estimator (e.g.
    ``mode="paper"`` for ``diff``). The estimator's ``reference_tilt_std`` is the calibration's reference error
    (``calibration.reference(method)``, a :class:`~place_safe.recovery.estimator.Reference`; 0 for a calibration object
    without the method, and for the naive methods), which fusion adds once to the fused tilt.
    """
    if not isinstance(method, str):
        raise ArgumentTypeError(f"make_estimator: method must be a str, one of {', '.join(METHODS)}; "
                                f"got {type(method).__name__}")
    if calibration is not None and not all(callable(getattr(calibration, s, None)) for s in _SECTION_METHODS):
        hint = (" (a path: read it with place_safe.calibration.Calibration.load(path))"
                if isinstance(calibration, (str, bytes, os.PathLike)) else
                " (a dict of sections: Calibration(sections), or Calibration.from_dict(file_contents))"
                if isinstance(calibration, dict) else "")
        raise ArgumentTypeError(f"make_estimator: calibration must be a place_safe.calibration.Calibration or None, "
                                f"got {type(calibration).__name__}{hint}")
    cal = calibration if calibration is not None else BuiltInParameters()
    try:
        est = _made(method, cal, options)
    except PlaceSafeError:
        raise
    except TypeError as exc:  # an option the estimator does not take: one line of the package's own kind
        raise ArgumentTypeError(f"make_estimator({method!r}): {exc}") from None
    except ValueError as exc:  # an option's value it refuses (diff's mode="x")
        raise ConfigError(f"make_estimator({method!r}): {exc}") from None
    if not method.endswith("-naive"):  # a naive method uses no calibration, nor its reference
        reference = getattr(cal, "reference", None)  # optional: a task script's own calibration object may lack it
        est.reference_tilt_std = float(reference(method).tilt_std) if callable(reference) else 0.0
    return est


def _made(method: str, cal: Any, options: dict) -> Estimator:
    """The estimator of ``method`` from the sections of ``cal`` (see :func:`make_estimator`)."""
    if method == "peak":
        from place_safe.recovery.peak import PeakEstimator
        return PeakEstimator(cal.peak(), uncertainty=cal.uncertainty("peak"), **options)
    if method == "peak-naive":
        from place_safe.recovery.peak import PeakEstimator
        return PeakEstimator.naive(**options)
    if method == "proprietary":
        from place_safe.recovery.proprietary import ProprietaryEstimator
        return ProprietaryEstimator(cal.proprietary(), **options)
    if method == "proprietary-naive":
        from place_safe.recovery.proprietary import ProprietaryEstimator
        return ProprietaryEstimator.naive(**options)
    if method == "diff":
        from place_safe.recovery.differentiable import DifferentiableEstimator
        options.setdefault("options", cal.diff_options())  # the solver window the calibration holds for
        return DifferentiableEstimator(cal.forward(), cal.peak(), correction=cal.diff(),
                                       uncertainty=cal.uncertainty("diff"), peak_uncertainty=cal.uncertainty("peak"),
                                       **options)
    raise ConfigError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


__all__ = ["Estimator", "PlaneEstimate", "METHODS", "make_estimator", "BuiltInParameters"]
