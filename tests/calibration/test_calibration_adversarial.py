"""Adversarial and property-based tests of calibration loading and the calibration data selection.

Properties: any JSON in a calibration file is either loaded or refused with one CalibrationError
line; a bad section breaks only the methods that use it; every accepted parameter is inside its
documented physical range (so no accepted file can give a NaN plane or a plane behind the sensor).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from place_safe.calibration import FORMAT, Calibration
from place_safe.calibration.forward_fit import usable_frames
from place_safe.calibration.model_error import select_model_error
from place_safe.config import field_range
from place_safe.exceptions import CalibrationError
from place_safe.recovery import make_estimator
from place_safe.recovery.differentiable import RangeCorrection
from place_safe.recovery.forward import ForwardParams
from place_safe.recovery.points import PeakParams
from place_safe.sensor.frame import N_BINS, Frame
from place_safe.sensor.histogram import COUNT_MAX

json_scalars = (st.none() | st.booleans() | st.integers(-10**30, 10**30)
                | st.floats(allow_nan=True, allow_infinity=True) | st.text(max_size=5))
json_values = st.recursive(json_scalars, lambda inner: st.lists(inner, max_size=10)
                           | st.dictionaries(st.text(max_size=6), inner, max_size=3), max_leaves=15)


def _in_range(value, model, name) -> bool:
    """Whether ``value`` of field ``name`` lies in the range its ``Field`` declares."""
    r = field_range(model, name)
    values = value if isinstance(value, list) else [value]
    if r.min_length is not None and len(values) < r.min_length or r.max_length is not None and len(values) > r.max_length:
        return False
    for v in values:
        if not math.isfinite(v):
            return False
        if v <= r.lo if r.lo_open else v < r.lo:
            return False
        if v >= r.hi if r.hi_open else v > r.hi:
            return False
    return True


def _ranged(model) -> list[str]:
    """The fields of ``model`` that declare a range."""
    return [n for n in model.model_fields if math.isfinite(field_range(model, n).lo) or
            math.isfinite(field_range(model, n).hi)]


def _section_dicts(fields: dict, required: dict):
    """Dicts mixing good defaults, random JSON values and boundary numbers for the given fields."""
    numbers = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([0, -1, 1e300, -1e300, 1e-300])
    value = json_values | numbers | st.lists(numbers, min_size=0, max_size=10)
    return st.fixed_dictionaries(required, optional={k: value for k in fields if k not in required}) | st.dictionaries(
        st.text(max_size=8), value, max_size=3)


_REQUIRED = {ForwardParams: {}, PeakParams: {"m": st.floats(1, 1e5) | json_values, "b": st.floats(-50, 50)}}


@pytest.mark.parametrize("model", [ForwardParams, PeakParams], ids=lambda m: m.__name__)
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_parameters_are_in_range_or_refused(model, data):
    d = data.draw(_section_dicts(model.model_fields, _REQUIRED[model]))
    try:
        p = model.from_dict(d)
    except CalibrationError as exc:
        assert "\n" not in str(exc) and str(exc).startswith(model.what)
        return
    for name in _ranged(model):
        assert _in_range(getattr(p, name), model, name), name


@settings(max_examples=200, deadline=None)
@given(doc=st.fixed_dictionaries({"format": st.just(FORMAT)},
                                 optional={"peak": json_values, "proprietary": json_values,
                                           "forward": json_values, "diff": json_values, "reports": json_values}),
       extra=st.dictionaries(st.sampled_from(["fromat", "peek", "x"]), json_values, max_size=1))
def test_any_calibration_document_loads_per_section_or_fails_in_one_line(doc, extra):
    doc = {**doc, **extra}
    try:
        cal = Calibration.from_dict(doc)
    except CalibrationError as exc:
        assert extra and "unknown keys" in str(exc)
        return
    assert not extra
    for view in ("peak", "proprietary", "forward", "diff"):
        try:
            getattr(cal, view)()
        except CalibrationError as exc:
            assert view in cal.errors and f"section '{view}'" in str(exc) and "\n" not in str(exc)
        else:
            assert view not in cal.errors


# -- the cases of the issue -----------------------------------------------------------------------------
BAD_SECTIONS = [
    ("diff", [1, 2]),
    ("diff", "correction"),
    ("diff", {"range_correction": [0.1]}),
    ("diff", {"range_correction": "x"}),
    ("diff", {"range_correction": {"coeffs": [-10.0]}}),
    ("diff", {"range_correction": {"coeffs": [1e300]}}),
    ("diff", {"range_correction": {"coeffs": [0.001], "domain": [0.3, 0.1]}}),
    ("peak", {"m": True, "b": 13.0}),
    ("peak", {"m": 72.0, "b": 13.0, "zone_gains": [-1.0] * 9}),
    ("peak", {"m": 72.0, "b": 13.0, "residual_coeffs": [1e300]}),
    ("peak", {"m": 72.0, "b": 13.0, "zone_offsets": [float("nan")] * 9}),
    ("proprietary", {"m": 1000.0, "b": "0"}),
    ("forward", {"rays_per_zone": 0}),
    ("forward", {"rays_per_zone": -4}),
    ("forward", {"albedo": 0.0}),
    ("forward", {"albedo": -1.0}),
    ("forward", {"specular_exponent": 0.0}),
    ("forward", {"specular_exponent": -2.0}),
    ("forward", {"ref_time_scale": 1e6}),
    ("forward", {"mount_tilt": [100.0, 0.0]}),
    ("forward", {"crosstalk": 1e300}),
    ("forward", {"zone_offsets": [float("nan")] * 9}),
    ("forward", {"edge_gain": -0.5}),
    ("forward", {"bogus": 1.0}),
    # an entry that is no method family's (a misspelt "diff"): no estimator would read it, and it was accepted silently
    ("uncertainty", {"dif": {"tilt_std": 0.001, "offset_std": 0.0001}}),
    ("uncertainty", {"peak": {"tilt_std": 0.001, "offset_std": 0.0001}, "bogus": {}}),
    # a section that is not an object would otherwise read as absent: the built-in constants, silently
    ("peak", None),
    ("proprietary", [72.0, 13.0]),
    ("forward", None),
    ("diff", None),
]
USES = {"peak": {"peak", "diff"}, "proprietary": {"proprietary"}, "forward": {"diff"}, "diff": {"diff"},
        "uncertainty": {"peak", "diff"}}


@pytest.mark.parametrize("section, content", BAD_SECTIONS)
def test_bad_section_breaks_only_its_methods(tmp_path, section, content):
    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"format": FORMAT, section: content}))
    cal = Calibration.load(path)
    assert section in cal.errors
    for method in ("diff", "peak", "peak-naive", "proprietary", "proprietary-naive"):
        if method in USES[section]:
            with pytest.raises(CalibrationError, match=f"section '{section}'") as info:
                make_estimator(method, cal)
            assert str(path) in str(info.value) and "\n" not in str(info.value)
        else:
            make_estimator(method, cal)


@pytest.mark.parametrize("raw", [b"\xff\xfe{}", b"[" * 100_000, b'{"format": ' + b"9" * 5000 + b"}",
                                 b'{"format": "place_safe.calibration/1", "extra": 1}', b"", b"null"])
def test_unreadable_calibration_files_are_one_line(tmp_path, raw):
    path = tmp_path / "cal.json"
    path.write_bytes(raw)
    with pytest.raises(CalibrationError) as info:
        Calibration.load(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


@pytest.mark.parametrize("raw, key", [
    ('{"format": "place_safe.calibration/1", "peak": {"m": 72.0, "b": 13.0}, "peak": {"m": 70.0, "b": 12.0}}', "peak"),
    ('{"format": "place_safe.calibration/1", "uncertainty": {"diff": {"chi2_limit": 3.0, "chi2_limit": 300.0}}}',
     "chi2_limit"),
])
def test_a_key_given_twice_is_refused_naming_it(tmp_path, raw, key):
    """JSON's reader keeps the last of two equal keys silently: a hand edit that added a second ``chi2_limit`` would
    be used or not by its place in the file. The file is refused in one line that names the key."""
    path = tmp_path / "cal.json"
    path.write_text(raw)
    with pytest.raises(CalibrationError, match=f"key '{key}' appears twice") as info:
        Calibration.load(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_byte_order_mark_is_accepted(tmp_path):
    path = tmp_path / "cal.json"
    path.write_bytes(b"\xef\xbb\xbf" + json.dumps({"format": FORMAT}).encode())
    assert Calibration.load(path).sections == {}


def test_range_correction_bounds_are_physical():
    assert field_range(RangeCorrection, "coeffs").hi <= 0.1  # metres: a correction, not a relocation


def test_the_diff_solver_window_comes_from_the_calibration():
    """A file records the window its chi-square limit and covariance scale were calibrated with; a file from
    before the key keeps the old window; no diff section: the solver's default."""
    from place_safe.recovery.diff_settings import LEGACY_WINDOW_AFTER_PEAK, SolverOptions

    base = {"format": FORMAT, "forward": ForwardParams().to_dict()}
    new = Calibration.from_dict({**base, "diff": {"range_correction": {}, "window_after_peak": 48}})
    old = Calibration.from_dict({**base, "diff": {"range_correction": {}}})
    none = Calibration.from_dict(base)
    assert make_estimator("diff", new).opt.window_after_peak == 48
    assert make_estimator("diff", old).opt.window_after_peak == LEGACY_WINDOW_AFTER_PEAK
    assert make_estimator("diff", none).opt.window_after_peak == SolverOptions().window_after_peak
    for bad in (0, 500, 2.5, True, "60"):
        cal = Calibration.from_dict({**base, "diff": {"window_after_peak": bad}})
        with pytest.raises(CalibrationError, match="window_after_peak"):
            make_estimator("diff", cal)
        assert make_estimator("peak", cal).name == "peak"  # a bad diff section stops only diff


def test_the_diff_sections_ambient_reaches_the_solver():
    """``diff.ambient`` (written by ``calibrate --unit-model staged``): the solver compares the model with the counts
    above the arriving ambient; absent, as before; anything but true/false stops diff only, with a one-line error."""
    base = {"format": FORMAT, "forward": ForwardParams().to_dict()}
    on = Calibration.from_dict({**base, "diff": {"range_correction": {}, "window_after_peak": 60, "ambient": True}})
    off = Calibration.from_dict({**base, "diff": {"range_correction": {}, "window_after_peak": 60}})
    assert make_estimator("diff", on).opt.ambient is True
    assert make_estimator("diff", off).opt.ambient is False
    for bad in (1, "true", None):
        cal = Calibration.from_dict({**base, "diff": {"ambient": bad}})
        with pytest.raises(CalibrationError, match="ambient"):
            make_estimator("diff", cal)
        assert make_estimator("peak", cal).name == "peak"


def test_the_diff_sections_crosstalk_std_reaches_the_solver():
    """``diff.crosstalk_std`` (written by ``calibrate`` after a level sweep that left the crosstalk undetermined): each
    frame solves its own crosstalk under that prior, one more unknown; absent, held as before; anything but a number in
    0..0.5 stops diff only, with a one-line error."""
    base = {"format": FORMAT, "forward": ForwardParams().to_dict()}
    on = Calibration.from_dict({**base, "diff": {"range_correction": {}, "window_after_peak": 60, "crosstalk_std": 0.005}})
    off = Calibration.from_dict({**base, "diff": {"range_correction": {}, "window_after_peak": 60}})
    est_on, est_off = make_estimator("diff", on), make_estimator("diff", off)
    assert est_on.opt.crosstalk_std == 0.005 and est_off.opt.crosstalk_std == 0.0
    assert est_on._renderer.n_unknowns == est_off._renderer.n_unknowns + 1
    for bad in (-0.1, 0.7, "0.01", None, True, float("nan"), 1e-300, 10 ** 400):
        cal = Calibration.from_dict({**base, "diff": {"crosstalk_std": bad}})
        with pytest.raises(CalibrationError, match="crosstalk_std") as err:
            make_estimator("diff", cal)
        assert len(str(err.value)) < 200  # one line, the value shortened
        assert make_estimator("peak", cal).name == "peak"


def test_range_correction_gains_scale_the_slopes():
    from place_safe.recovery.differentiable import RangeCorrection

    c = RangeCorrection(domain=[0.0, 1.0], slope_a=[0.001], gain_b=[-0.01])
    assert c.slopes(0.2, 0.3, 0.4) == pytest.approx((0.001, -0.004))
    assert RangeCorrection.from_dict(c.to_dict()) == c
    assert RangeCorrection.from_dict({"coeffs": [], "domain": [0.0, 1.0], "slope_a": [], "slope_b": []}).gain_a == []
    with pytest.raises(CalibrationError, match="gain_b"):
        RangeCorrection.from_dict({**c.to_dict(), "gain_b": [0.9]})


# -- data selection for the forward fit and the model-error choice ------------------------------------------
def _with(frame: Frame, hists=None, reference=None) -> Frame:
    return Frame(frame.hists if hists is None else hists, frame.reference if reference is None else reference,
                 frame.distances, frame.confidences, truth=frame.truth)


def test_saturated_frames_and_invalid_references_are_left_out_with_a_count(synthetic_frames):
    f = synthetic_frames[0]
    saturated = np.array(f.hists, dtype=float)
    saturated[4, 20] = COUNT_MAX
    frames = [f, _with(f, hists=saturated), _with(f, reference=np.zeros(N_BINS)),
              _with(f, reference=np.r_[np.full(N_BINS - 1, 30.0), 9000.0]), Frame(f.hists, f.reference)]
    skipped: dict = {}
    assert usable_frames(frames, 0.0, 10.0, skipped) == [f]
    assert skipped == {"saturated": 1, "invalid reference histogram": 2, "no ground truth": 1}


def test_model_error_is_not_chosen_from_infinite_scores(synthetic_frames):
    """Frames no value can recover (no return in any zone) must not make the first grid value win."""
    f = synthetic_frames[0]
    blank = [_with(g, hists=np.full_like(np.asarray(g.hists, dtype=float), 40.0)) for g in synthetic_frames[:3]]
    params = ForwardParams(model_error=0.02)
    chosen, report = select_model_error(blank, params, grid=(0.0, 0.01), progress=False)
    assert chosen == 0.02 and "no value" in report["why"]
    # a saturated frame among good ones is left out, so it cannot make every score infinite
    sat = np.array(f.hists, dtype=float)
    sat[4, 20] = COUNT_MAX
    chosen, report = select_model_error([*synthetic_frames[:3], _with(f, hists=sat)], params,
                                        grid=(0.0, 0.01), progress=False)
    assert report["frames_skipped"] == {"saturated": 1}
    assert all(v is not None and math.isfinite(v) for v in report["mean_point_error_mm"].values())


def test_null_sections_are_not_a_calibration_for_placement(tmp_path):
    from place_safe.calibration import uncalibrated_reason

    path = tmp_path / "cal.json"
    path.write_text(json.dumps({"format": FORMAT, "peak": None, "forward": None, "uncertainty": "x"}))
    cal = Calibration.load(path)
    for method in ("peak", "diff", "proprietary"):
        assert "not calibrated" in uncalibrated_reason(method, cal)
    with pytest.raises(CalibrationError, match="section 'uncertainty'"):
        cal.uncertainty("peak")


def test_a_calibration_without_fallback_returns_diffs_own_plane_and_keeps_every_other_section(sweep_path):
    from place_safe import simulated_calibration
    from place_safe.io.frame_file import load_frames

    cal = simulated_calibration("nominal")  # a simulated unit's: on real frames diff falls back often
    own = cal.without_fallback()
    assert {k: v for k, v in own.to_dict().items() if k != "uncertainty"} == \
        {k: v for k, v in cal.to_dict().items() if k != "uncertainty"}
    assert own.to_dict()["uncertainty"]["peak"] == cal.to_dict()["uncertainty"]["peak"]
    assert all(own.to_dict()["uncertainty"]["diff"].get(k) is None for k in ("chi2_limit", "consistency_limit"))
    frames = [f for f in load_frames(sweep_path) if f.truth is not None and 0.05 <= f.truth.z0 <= 0.4][::6]
    used = {e.method_used for e in make_estimator("diff", cal).estimate_many(frames) if e.ok}
    own_used = {e.method_used for e in make_estimator("diff", own).estimate_many(frames) if e.ok}
    assert "peak" in used and own_used == {"diff"}


def _ten_frames(sweep_path, tmp_path):
    """10 of the real sweep's frames from 9.5 cm on (a calibration of the recommended size), as a frame file."""
    entries = sorted((e for e in json.loads(sweep_path.read_text()) if e["dist_to_plane"] >= 0.09),
                     key=lambda e: e["dist_to_plane"])
    path = tmp_path / "ten.json"
    path.write_text(json.dumps([entries[round(k * (len(entries) - 1) / 9)] for k in range(10)]))
    return path


def test_calibrate_onto_a_file_whose_peak_domain_has_no_width_refits_it(tmp_path, sweep_path, capsys):
    """``calibrate -o`` onto a file whose peak section has ``residual_domain`` [0.1, 0.1] and zone_inverse read it
    with an internal ZeroDivisionError (exit 1): now the section is one invalid section, which the fit replaces."""
    from place_safe.cli.app import main

    out = tmp_path / "cal.json"
    out.write_text(json.dumps({"format": FORMAT, "peak": {"m": 72.0, "b": 13.0, "residual_domain": [0.1, 0.1],
                                                          "zone_inverse": [0.1] * 9}}))
    assert "residual_domain must be" in Calibration.load(out).errors["peak"]
    assert main(["calibrate", str(_ten_frames(sweep_path, tmp_path)), "--method", "peak", "-o", str(out), "-q"]) == 0
    assert "warning" not in capsys.readouterr().err
    Calibration.load(out).check()


def test_calibrate_into_a_file_with_another_broken_section_says_so_even_quietly(tmp_path, sweep_path, capsys):
    """A file whose peak section is broken (m out of range) took a proprietary fit silently with -q and kept the broken
    section, and place then refused the whole file: one warning line names the section."""
    from place_safe.cli.app import main

    out = tmp_path / "cal.json"
    out.write_text(json.dumps({"format": FORMAT, "peak": {"m": -1.0, "b": 13.0}}))
    assert main(["calibrate", str(_ten_frames(sweep_path, tmp_path)), "--method", "proprietary", "-o", str(out),
                 "-q"]) == 0
    warnings = [x for x in capsys.readouterr().err.splitlines() if x.startswith("warning")]
    assert len(warnings) == 1 and f"{out}: section 'peak' kept invalid (peak parameters: m" in warnings[0]
    cal = Calibration.load(out)
    assert set(cal.errors) == {"peak"} and "proprietary" in cal.sections
