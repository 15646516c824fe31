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

from typing import Any

from place_safe.recovery.estimator import Estimator, PlaneEstimate

METHODS = ("diff", "peak", "peak-naive", "proprietary", "proprietary-naive")


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

    def uncertainty(self, method: str | None = None):
        from place_safe.recovery.estimator import Uncertainty

        return Uncertainty() if method is not None else {}


def make_estimator(method: str, calibration: Any = None, **options) -> Estimator:
    """The estimator for a CLI method name, using ``calibration`` where the method has one.

    ``calibration``: a :class:`~place_safe.calibration.Calibration` (``Calibration.load(path)`` reads a
    file) or None. Without a calibration (or without a section for the method) each method uses its
    built-in defaults (:class:`BuiltInParameters`). ``options`` go to the estimator (e.g.
    ``mode="paper"`` for ``diff``).
    """
    cal = calibration if calibration is not None else BuiltInParameters()
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
    raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


__all__ = ["Estimator", "PlaneEstimate", "METHODS", "make_estimator", "BuiltInParameters"]
