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


def test_the_zone_time_units_calibration_is_its_own_level_sweep_with_the_time_scales_taken():
    """``sim/sensors/calibration_mismatch_zone_time.json`` (sim/make_unit_calibration.py; the zone_time_* scenarios):
    valid, made from a level sweep of the unit it names, whose far geometry ``calibrate`` replaced by each zone's own
    time scale (the zones' scales within 1 +- 1.5 % of the centre zone's, the fields of view and the mount nominal)."""
    path = calibration_file("mismatch").with_name("calibration_mismatch_zone_time.json")
    cal = Calibration.load(path).check()
    reports = json.loads(path.read_text())["reports"]
    cap = reports["capture"]
    assert cap["unit"] == {"zone_time_scale": 0.015} and cap["max_tilt_deg"] == 0.0 and cap["frames"] >= 100
    assert reports["forward"]["geometry"]["adopted"] == "nominal_time_scales"
    fwd = cal.forward()
    assert fwd.edge_fov_scale == 1.0 and fwd.corner_fov_scale == 1.0 and list(fwd.mount_tilt) == [0.0, 0.0]
    assert all(0.97 <= s <= 1.03 for s in fwd.zone_bin_scales) and np.ptp(fwd.zone_bin_scales) > 0.005
