"""Why a method is not a calibrated sensor (:func:`place_safe.calibration.uncalibrated_reason`), as a placement's
refusal states it."""

from __future__ import annotations

import pytest

from place_safe.calibration import Calibration, uncalibrated_reason

pytestmark = pytest.mark.fast


@pytest.mark.parametrize("method", ["peak-naive", "proprietary-naive"])
def test_a_naive_method_is_refused_by_design_and_not_told_to_calibrate(method):
    """``demo --method peak-naive`` (and ``place``) refused with "calibrate it first: ... then pass the calibration
    file", which a naive method never reads: it would be refused with any calibration (a new user's walkthrough). The
    reason says it takes none and names the calibrated method."""
    plain = method.removesuffix("-naive")
    for calibration in (None, Calibration()):
        why = uncalibrated_reason(method, calibration)
        assert why.startswith("sensor not calibrated") and "built-in constants" in why
        assert "takes no calibration" in why and "by design" in why and "then pass the calibration file" not in why
        assert f"use {plain}" in why and f"--method {plain}" in why


def test_a_calibrated_method_without_its_section_is_told_how_to_calibrate():
    why = uncalibrated_reason("proprietary", Calibration())
    assert why.startswith("sensor not calibrated for proprietary (no 'proprietary' section)")
    assert "place-safe calibrate FRAMES.json --method proprietary" in why and "pass the calibration file" in why
