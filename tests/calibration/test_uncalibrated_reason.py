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



def test_diff_without_a_peak_section_is_uncalibrated(sweep_path, tmp_path, capsys):
    """diff starts from the calibrated peak method and falls back to its plane; a calibration with diff's `forward`
    section but no `peak` one (the simulated unit's, less that section) passed as calibrated: `recover --method diff`
    printed unmarked planes 14-16 deg off on level frames of the real sweep (peak's, from built-in constants; the whole
    calibration read 0.6-0.7 deg), and `place --sim place_level` refused "surface tilted 6.6 deg". Now diff needs both:
    the reason names the missing section, and `recover` says UNCALIBRATED naming it."""
    import json

    from place_safe.cli.app import main
    from place_safe.sim.tof import calibration_file

    assert uncalibrated_reason("diff", Calibration.load(calibration_file("nominal"))) is None
    data = json.loads(calibration_file("nominal").read_text())
    del data["peak"]
    path = tmp_path / "no_peak.json"
    path.write_text(json.dumps(data))
    cal = Calibration.load(path)
    assert uncalibrated_reason("diff", cal).startswith("sensor not calibrated for diff (no 'peak' section)")
    del cal.sections["forward"]
    assert uncalibrated_reason("diff", cal).startswith("sensor not calibrated for diff (no 'forward' section)")
    assert main(["recover", str(sweep_path), "--method", "diff", "--calibration", str(path), "-q"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith(f"UNCALIBRATED: {path} has no peak section: diff runs on built-in constants")


@pytest.mark.parametrize("method, cut", [("diff", "diff"), ("diff", "peak"), ("peak", "peak")])
def test_a_placement_refuses_a_calibration_without_the_uncertainty_its_method_reads(tmp_path, method, cut):
    """A calibration whose ``uncertainty`` section lacks the method's entry (diff reads peak's too: its start and
    fallback) loaded as calibrated: the estimates carried the built-in Uncertainty, no model-error floor (the fit's
    covariance alone) and, for diff, no fallback to peak, so the release rule trusted each plane beyond what the sensor
    measures (the sixteenth round's leftover). The planes are still calibrated (``uncalibrated_reason`` is None);
    ``placement_reason`` names the missing entry, and ``place --sim`` refuses before anything moves."""
    import json

    from place_safe.calibration import placement_reason
    from place_safe.sim.placement_run import run_placement
    from place_safe.sim.tof import calibration_file

    whole = Calibration.load(calibration_file("nominal"))
    assert placement_reason(method, whole) is None
    data = json.loads(calibration_file("nominal").read_text())
    del data["uncertainty"][cut]
    path = tmp_path / "cut.json"
    path.write_text(json.dumps(data))
    cal = Calibration.load(path)
    assert uncalibrated_reason(method, cal) is None
    why = placement_reason(method, cal)
    assert why.startswith(f"sensor's uncertainty not calibrated for {method} (no 'uncertainty.{cut}' entry)")
    assert ("never fall back to peak" in why) == (method == "diff")
    assert f"--method {method}" in why
    del data["uncertainty"]
    path.write_text(json.dumps(data))
    none = placement_reason(method, Calibration.load(path))
    assert "'uncertainty.peak'" in none and (("'uncertainty.diff'" in none) == (method == "diff"))
    res = run_placement("place_level", method=method, calibration=Calibration.load(path))
    assert res.outcome == "refused" and res.frames == 0 and res.reason == none
