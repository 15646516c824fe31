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
