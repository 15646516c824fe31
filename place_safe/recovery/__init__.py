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

from typing import TYPE_CHECKING

from place_safe.recovery.estimator import Estimator, PlaneEstimate

if TYPE_CHECKING:
    from place_safe.calibration import Calibration

METHODS = ("diff", "peak", "peak-naive", "proprietary", "proprietary-naive")


def make_estimator(method: str, calibration: "Calibration | None" = None, **options) -> Estimator:
    """The estimator for a CLI method name, using ``calibration`` where the method has one.

    ``calibration``: a :class:`~place_safe.calibration.Calibration`, the path of a calibration file, or
    None. Without a calibration (or without a section for the method) each method uses its built-in
    defaults. ``options`` go to the estimator (e.g. ``mode="paper"`` for ``diff``).
    """
    from pathlib import Path

    from place_safe.calibration import Calibration

    if isinstance(calibration, (str, Path)):
        calibration = Calibration.load(calibration)
    cal = calibration if calibration is not None else Calibration()
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
        return DifferentiableEstimator(cal.forward(), cal.peak(), correction=cal.diff(),
                                       uncertainty=cal.uncertainty("diff"), peak_uncertainty=cal.uncertainty("peak"),
                                       **options)
    raise ValueError(f"unknown method {method!r}; expected one of {', '.join(METHODS)}")


__all__ = ["Estimator", "PlaneEstimate", "METHODS", "make_estimator"]
