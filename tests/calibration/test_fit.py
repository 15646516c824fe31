"""fit_method: the unit model is a choice of the diff fit only, and only a known one; the frames' stated reference
error goes into the calibration."""

import copy
import math

import pytest

from place_safe.calibration import UNIT_MODELS, Calibration
from place_safe.calibration.fit import fit_method, frames_reference
from place_safe.exceptions import CalibrationError
from place_safe.recovery import make_estimator
from place_safe.recovery.estimator import Reference


def test_the_unit_models_offered():
    assert UNIT_MODELS[0] == "default" and "staged" in UNIT_MODELS


@pytest.mark.parametrize("method, unit_model", [("diff", "learned"), ("peak", "staged"), ("proprietary", "staged")])
def test_an_unknown_unit_model_or_one_for_another_method_is_refused_before_any_fit(method, unit_model):
    cal = Calibration()
    with pytest.raises(ValueError, match="unit model"):
        fit_method(cal, [], method, unit_model=unit_model)
    assert not cal.sections


@pytest.fixture(scope="module")
def sweep_frames(sweep_path):
    from place_safe.io.frame_file import load_frames

    return load_frames(sweep_path)


def _touched(frames, tilt_std):
    """Copies of ``frames`` whose ground truth says it came from a touched plane within ``tilt_std`` rad."""
    out = []
    for f in frames:
        g = copy.copy(f)
        g.extra = {**f.extra, "meta": {"base_plane": {"normal": [0.0, 0.0, 1.0], "offset": 0.0, "reference":
                                                      Reference(tilt_std=tilt_std, points=3).to_dict()}}}
        out.append(g)
    return out


def test_the_frames_reference_is_the_largest_they_state(sweep_frames):
    frames = sweep_frames[:4]
    assert frames_reference(frames) is None  # the public sweep's truth states no error
    mixed = _touched(frames[:2], 0.001) + _touched(frames[2:3], 0.003) + frames[3:]
    assert frames_reference(mixed).tilt_std == pytest.approx(0.003)
    bad = _touched(frames[:1], 0.001)
    bad[0].extra["meta"]["base_plane"]["reference"]["tilt_std"] = -1.0
    with pytest.raises(CalibrationError, match="reference"):
        frames_reference(bad)


def test_a_calibration_keeps_its_frames_reference_per_method_and_its_estimators_carry_it(sweep_frames):
    """Calibrated from a capture against a touched table, the file's ``reference`` section gets an entry for each
    method fitted, and every estimator made from it its tilt error (added once by fusion). Another method calibrated
    into the same file from frames that state none leaves the first method's entry as it was; diff reads the larger of
    its own and peak's (it starts from and blends with peak's plane); the same method calibrated again from such frames
    drops its entry. A calibration without the section, and the naive methods, carry none."""
    frames = sweep_frames[::4]
    cal = Calibration()
    assert "reference" in fit_method(cal, _touched(frames, math.radians(0.124)), "proprietary")
    assert fit_method(cal, _touched(frames, math.radians(0.2)), "peak")
    assert set(cal.sections["reference"]) == {"proprietary", "peak"}
    again = Calibration.from_dict(cal.to_dict())
    assert again.reference("proprietary").tilt_std == pytest.approx(math.radians(0.124))
    assert make_estimator("proprietary", again).reference_tilt_std == pytest.approx(math.radians(0.124))
    assert make_estimator("peak", again).reference_tilt_std == pytest.approx(math.radians(0.2))
    assert make_estimator("diff", again).reference_tilt_std == pytest.approx(math.radians(0.2))  # peak's, the larger
    assert make_estimator("peak-naive", again).reference_tilt_std == 0.0
    assert make_estimator("peak").reference_tilt_std == 0.0
    fit_method(again, frames, "peak")  # a capture that states no error: peak's entry goes, proprietary's stays
    assert set(again.sections["reference"]) == {"proprietary"}
    assert make_estimator("peak", again).reference_tilt_std == 0.0
    assert make_estimator("proprietary", again).reference_tilt_std == pytest.approx(math.radians(0.124))
    fit_method(again, frames, "proprietary")
    assert "reference" not in again.sections and make_estimator("proprietary", again).reference_tilt_std == 0.0


@pytest.mark.parametrize("section", [{"peak": {"tilt_std": "big"}}, {"peak": {"tilt_std": 1.0}}, {"lidar": {}},
                                     {"peak": []}, []])
def test_a_malformed_reference_section_is_one_line_for_the_methods_that_read_it(section):
    cal = Calibration.from_dict({"format": "place_safe.calibration/1", "reference": section})
    with pytest.raises(CalibrationError, match="reference") as err:
        make_estimator("peak", cal)
    assert "\n" not in str(err.value)
    with pytest.raises(CalibrationError, match="reference"):
        Calibration({"reference": section})


def test_the_second_forward_fit_starts_alongside_for_level_sweeps_and_tilted_captures(monkeypatch, sweep_frames):
    """``fit_method(..., "diff")`` starts the second forward fit beside the first (:class:`Alongside`) for every
    capture: on a level sweep the one with the geometry nominal, on a capture with tilted frames the one with each
    zone's time scale and the geometry free (:func:`~place_safe.calibration.second_fit.second_fit_for`)."""
    import numpy as np

    import place_safe.calibration.fit as fit
    from place_safe.calibration import second_fit as sf
    from place_safe.geometry import Plane

    started = []

    class Stop(Exception):
        pass

    class Recorder:
        def __init__(self, fn, *args, **kw):
            started.append(fn)
            raise Stop

    monkeypatch.setattr(fit, "Alongside", Recorder)
    level = sweep_frames[10:20]
    tilted = copy.deepcopy(level)
    for k, f in enumerate(tilted):
        t = math.radians(12.0) * (k % 2)
        f.truth = Plane(np.array([math.sin(t), 0.0, math.cos(t)]), f.truth.offset)
    for frames, expected in ((level, sf.nominal_geometry_fit), (tilted, sf.scales_and_geometry_fit)):
        with pytest.raises(Stop):
            fit_method(Calibration(), frames, "diff")
        assert started[-1] is expected


def _spread(frames, n, start=0):
    """``n`` of the sweep's frames from 9.5 cm on, spread evenly over its range."""
    far = sorted((f for f in frames if f.truth.z0 >= 0.09), key=lambda f: f.truth.z0)
    return [far[round(start + k * (len(far) - 1 - start) / (n - 1))] for k in range(n)]


@pytest.mark.parametrize("method", ["peak", "proprietary", "diff"])
def test_too_few_frames_or_distances_are_one_error_before_any_fit(sweep_frames, method):
    """3 frames (the adversarial round's c_three: peak wrote tilt_std 0, offset_std 0 and planes 300 times too certain)
    or frames at fewer than 3 distances: one line saying how many are needed, nothing written."""
    cal = Calibration()
    for frames, words in ((_spread(sweep_frames, 3), "3 frames with ground truth"),
                          ([sweep_frames[30]] * 8, "at 1 distinct distance"),
                          ([f for f in sweep_frames if f.truth.z0 < 0.03], "0 frames")):
        with pytest.raises(CalibrationError, match=words) as info:
            fit_method(cal, frames, method)
        assert "needs 5 or more frames at 3 or more distances" in str(info.value) and "\n" not in str(info.value)
    assert not cal.sections


def test_a_small_calibration_says_so_and_widens_what_its_own_frames_state(sweep_frames):
    """6 frames (5-9: the project's own smallest calibrations are 6 and 8 frames): the fit goes on, its report carries
    a note (printed even with -q) and peak's scale and the on-sensor distances' residuals are widened by the
    small-sample factor (n + p) / (n - p); from 10 frames on neither."""
    from place_safe.calibration.points import small_sample_factor

    cal = Calibration()
    fit_method(cal, _spread(sweep_frames, 6), "peak")
    rep = cal.reports["peak"]
    n, p = rep["readings"], rep["parameters"]
    assert rep["frames"] == 6 and n == 54 and 20 <= p <= 40
    factor = (n + p) / (n - p)
    assert small_sample_factor(rep) == pytest.approx(factor)
    widened = cal.reports["uncertainty"]["peak"]["small_sample"]
    assert widened["factor"] == pytest.approx(factor)
    assert cal.uncertainty("peak").scale == pytest.approx(min(widened["scale_in_sample"] * factor, 10.0))
    note = rep["small_sample"]["note"]
    assert "calibrated on only 6 frames" in note and f"{factor:.2f}" in note
    fit_method(cal, _spread(sweep_frames, 6), "proprietary")
    prop = cal.reports["proprietary"]
    assert "calibrated on only 6 frames" in prop["small_sample"]["note"]
    own = prop["small_sample"]["zone_residual_mm_in_sample"]["own"] * 1e-3
    f2 = prop["small_sample"]["factor"]
    assert cal.proprietary().zone_residual == pytest.approx(min(own * math.sqrt(f2), 0.1))
    big = Calibration()
    fit_method(big, _spread(sweep_frames, 10), "peak")
    assert "small_sample" not in big.reports["peak"] and "small_sample" not in big.reports["uncertainty"]["peak"]


def test_a_fit_that_leaves_a_floorless_uncertainty_is_refused_not_written(sweep_frames):
    """Mostly near frames (7, of which 2 beyond the near-range table's end): the floor's fit had fewer than 3 frames
    and wrote no floor at all, a file every command then refuses (Calibration.uncertainty): calibrate says so."""
    near = sorted(sweep_frames, key=lambda f: f.truth.z0)
    pick = [min(near, key=lambda f: abs(f.truth.z0 - z)) for z in (0.035, 0.045, 0.06, 0.07, 0.08, 0.2, 0.3)]
    with pytest.raises(CalibrationError, match="peak's model error could not be fitted.*add frames farther out"):
        fit_method(Calibration(), pick, "peak")


def test_frames_the_mapping_could_not_use_count_against_the_small_sample_note(sweep_frames):
    """12 frames with ground truth, 4 of them with a return in 2 zones only: the mapping fits 8 and widens its
    covariance for 8; the note said nothing, counting 12 (a review). Both now count the frames the mapping kept."""
    import dataclasses as dc

    import numpy as np

    frames = _spread(sweep_frames, 12)
    blind = []
    for i, f in enumerate(frames):
        if i % 3 == 0:
            h = np.array(f.hists, dtype=float)
            h[2:] = np.median(h[2:], axis=1, keepdims=True)  # zones 3-9: the floor alone
            f = dc.replace(f, hists=h)
        blind.append(f)
    cal = Calibration()
    fit_method(cal, blind, "peak")
    rep = cal.reports["peak"]
    assert rep["frames"] < 10 and "calibrated on only" in rep["small_sample"]["note"]


@pytest.mark.slow
def test_the_whole_real_sweep_calibrates_diff_to_a_file_that_loads(sweep_path, tmp_path):
    """`place-safe calibrate tests/data/tmf8820_ur5_sweep.json --method diff -o CAL`, the command the docs and the
    issues give: diff's covariances there already cover its errors (NEES per dof 0.59 without a floor), so the floor's
    fit wanted no term and wrote an entry stating none, which the write refused (an adversarial round, session 68).
    The file is written, loads, and diff reads the sweep's far frames with it."""
    import numpy as np
    import torch

    from place_safe.cli import main
    from place_safe.io.frame_file import load_frames

    torch.set_num_threads(1)
    out = tmp_path / "cal.json"
    assert main(["calibrate", str(sweep_path), "--method", "diff", "-o", str(out), "-q"]) == 0
    cal = Calibration.load(out)
    assert not cal.uncertainty("diff").states_no_floor()
    est = make_estimator("diff", cal)
    far = [f for f in load_frames(sweep_path) if f.truth is not None and f.truth.z0 > 0.1][::6]
    tilts = [math.degrees(math.acos(min(1.0, abs(float(np.dot(est.estimate(f).plane.normal, f.truth.normal))))))
             for f in far]
    assert len(far) >= 4 and max(tilts) < 0.5


@pytest.mark.parametrize("method", ["peak", "proprietary", "diff"])
def test_frames_given_twice_count_once(sweep_frames, method):
    """3 frames at 3 distances, each given 5 times (15 frames): they passed the 5-frame minimum, and peak wrote a
    calibration with no floor (tilt_std 0, offset_std 1e-6 m) and the smallest covariance scale, 0.1 (session 82).
    Each measurement now counts once: the repeats are left out with a note, and 3 frames are too few (one line,
    nothing written)."""
    cal = Calibration()
    lines: list[str] = []
    with pytest.raises(CalibrationError, match="3 frames with ground truth") as info:
        fit_method(cal, _spread(sweep_frames, 3) * 5, method, log=lines.append)
    assert "\n" not in str(info.value) and not cal.sections
    assert len(lines) == 1 and "frame 3 repeats frame 0 exactly" in lines[0] and "12 frames repeat" in lines[0]


@pytest.mark.parametrize("method", ["peak", "proprietary"])
def test_a_sweep_given_twice_calibrates_as_the_sweep(sweep_frames, method):
    """The sweep given twice in one file (files joined) fitted every frame twice and held each out beside its own copy;
    now it writes the sections the sweep gives once, and says what it left out."""
    once, twice = Calibration(), Calibration()
    fit_method(once, list(sweep_frames), method)
    lines: list[str] = []
    fit_method(twice, list(sweep_frames) + list(sweep_frames), method, log=lines.append)
    assert twice.sections == once.sections
    assert any(f"frame {len(sweep_frames)} repeats frame 0 exactly" in line for line in lines)
