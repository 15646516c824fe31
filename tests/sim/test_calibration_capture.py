"""The simulated user calibration is made by the chain a user runs on the arm: touch, capture, calibrate."""

from __future__ import annotations

import json
import math

import numpy as np

from place_safe.calibration import Calibration
from place_safe.sim.calibration_capture import CHAIN, calibration_file, capture_arm_sweep


def test_arm_capture_measures_the_table_by_touch_and_records_frames_with_it(tmp_path):
    path = capture_arm_sweep(tmp_path / "cap.jsonl", "nominal", poses=4, seed=3)
    rows = [json.loads(line) for line in path.read_text().splitlines()]
    assert len(rows) == 4
    for r in rows:
        # the ground truth written is what the arm touched, not the simulator's table (kept apart for checks)
        assert r["plane"] != r["meta"]["source_truth"]
        n, t = np.array(r["plane"]["normal"]), np.array(r["meta"]["source_truth"]["normal"])
        assert math.degrees(math.acos(min(1.0, float(n @ t)))) < 0.3
        assert abs(r["plane"]["offset"] - r["meta"]["source_truth"]["offset"]) < 0.002
        assert len(r["hists"]) == 9 and len(r["joint_angles"]) == 6


def test_packaged_calibrations_record_their_capture_chain():
    for sensor in ("nominal", "mismatch"):
        path = calibration_file(sensor)
        cal = Calibration.load(path)
        assert set(cal.sections) >= {"peak", "forward", "diff", "proprietary"}
        rep = json.loads(path.read_text())["reports"]["capture"]
        assert "place-safe calibrate" in rep["chain"] and rep["sensor"] == sensor and rep["frames"] >= 40
    # the nominal sensor's is the arm chain a user runs, over the heights placements start from
    rep = json.loads(calibration_file("nominal").read_text())["reports"]["capture"]
    assert rep["chain"] == CHAIN and max(rep["distances_m"]) >= 0.45
