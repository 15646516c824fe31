"""On-sensor distances: reported and calibrated, and bad input."""

from pathlib import Path

import numpy as np
import pytest

from place_safe.calibration.points import fit_proprietary
from place_safe.recovery import make_estimator
from place_safe.recovery.proprietary import ProprietaryEstimator
from place_safe.io.frame_file import load_frames
from place_safe.evaluation.metrics import linear_error
from place_safe.sensor.frame import Frame
from place_safe.evaluation.synthetic import make_frames

SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"


def _frame(dist, conf=None):
    return Frame(np.zeros((9, 128)), None, distances=None if dist is None else np.asarray(dist, float),
                 confidences=None if conf is None else np.asarray(conf, float))


def test_synthetic_distances_give_the_plane():
    est = make_estimator("proprietary-naive")
    assert est.name == "proprietary-naive" and not est.needs_histograms
    for f in make_frames(5, seed=2):
        e = est.estimate(f)
        assert e.ok and linear_error(e.plane, f.truth) < 5e-3


def test_real_sweep_calibrated_cross_validated():
    sweep = load_frames(SWEEP)
    params, _ = fit_proprietary(sweep[0::2], progress=False)
    test = [f for f in sweep[1::2] if f.truth.z0 >= 0.05]
    cal = [linear_error(ProprietaryEstimator(params).estimate(f).plane, f.truth) for f in test]
    raw = [linear_error(ProprietaryEstimator.naive().estimate(f).plane, f.truth) for f in test]
    assert np.mean(cal) < 2e-3 < np.mean(raw)


@pytest.mark.parametrize("dist, conf, words", [
    (None, None, "distances"),
    ([0.1] * 8, None, "shape"),
    ([np.nan] + [0.1] * 8, None, "NaN"),
    ([-0.1] + [0.1] * 8, None, "negative"),
    ([0.0] * 7 + [0.1] * 2, None, "3 or more"),
    ([0.1] * 9, [0] * 7 + [200] * 2, "3 or more"),
    ([1e4] + [0.1] * 8, None, "outside what the sensor reports"),  # 10 km: beyond 16-bit millimetres
    ([1e-12] * 9, None, "outside what the sensor reports"),  # nonzero, under the field's 1 mm
])
def test_bad_input_gives_reason(dist, conf, words):
    e = ProprietaryEstimator().estimate(_frame(dist, conf))
    assert e.plane is None and words in e.reason
