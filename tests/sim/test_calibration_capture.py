"""The simulated user calibration is made by the chain a user runs on the arm: touch, capture, calibrate."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

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
        # and how far the touch may be off goes with it: here 0.075 deg off, stated 0.124 deg (1 sigma)
        assert r["meta"]["base_plane"]["reference"]["points"] == 3
        assert math.acos(min(1.0, float(n @ t))) < 3 * r["meta"]["base_plane"]["reference"]["tilt_std"]


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
    # against a table the arm touched: how far the touch may be off goes with it; the rig's truth is exact
    nominal = Calibration.load(calibration_file("nominal"))
    assert set(nominal.reference()) == {"peak", "diff", "proprietary"}
    for method in nominal.reference():
        assert math.degrees(nominal.reference(method).tilt_std) == pytest.approx(0.124, abs=0.002)
    assert Calibration.load(calibration_file("mismatch")).reference() == {}


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


def test_the_zone_time_and_mount_units_calibration_takes_the_time_scales_for_both():
    """``sim/sensors/calibration_mismatch_zone_time_mount.json`` (sim/make_unit_calibration.py; the zone_time_mount_*
    scenarios): valid, made from a level sweep of the unit whose zones keep their own time and which is mounted 1.0 deg
    off, the two things a level table cannot tell apart; ``calibrate`` keeps the time-scale reading (the mount and the
    fields of view nominal), whose scales then take up the mount as well (they spread wider than without it)."""
    path = calibration_file("mismatch").with_name("calibration_mismatch_zone_time_mount.json")
    cal = Calibration.load(path).check()
    reports = json.loads(path.read_text())["reports"]
    cap = reports["capture"]
    assert cap["unit"]["zone_time_scale"] == 0.015 and cap["max_tilt_deg"] == 0.0 and cap["frames"] >= 100
    assert math.degrees(np.hypot(*cap["unit"]["mount_tilt"])) == pytest.approx(1.0, abs=0.01)
    assert reports["forward"]["geometry"]["adopted"] == "nominal_time_scales"
    fwd = cal.forward()
    assert fwd.edge_fov_scale == 1.0 and fwd.corner_fov_scale == 1.0 and list(fwd.mount_tilt) == [0.0, 0.0]
    sister = Calibration.load(path.with_name("calibration_mismatch_zone_time.json")).forward()
    assert all(0.97 <= s <= 1.03 for s in fwd.zone_bin_scales)
    assert np.ptp(fwd.zone_bin_scales) > np.ptp(sister.zone_bin_scales)


def test_the_zone_time_and_mount_unit_with_tilted_frames_finds_both_and_reads_tilted_planes_better():
    """``sim/sensors/calibration_mismatch_zone_time_mount_tilts.json`` (sim/make_unit_calibration.py ``--tilted 12``;
    the zone_time_mount_tilts_* scenarios): the same unit as ``calibration_mismatch_zone_time_mount.json``, its level
    sweep with 12 tilted frames added. ``calibrate`` fits each zone's time scale with the geometry (tilted frames tell
    them apart) and finds the scales within 0.2 % and the mount within 0.1 deg; on 96 tilted frames of the unit diff
    reads the slopes and the offsets better than with the level sweep alone (0.047 deg / 0.048 mm against 0.113 /
    0.585: the mount the level sweep's time scales held level moved every tilted plane's offset), with NEES per dof at
    most 2."""
    from place_safe.evaluation.metrics import angular_error, nees
    from place_safe.recovery import make_estimator
    from place_safe.sim.calibration_capture import OPERATING_TEMPERATURE, capture_level_sweep
    from place_safe.sim.tof_mismatch import MismatchConfig

    path = calibration_file("mismatch").with_name("calibration_mismatch_zone_time_mount_tilts.json")
    cal = Calibration.load(path).check()
    reports = json.loads(path.read_text())["reports"]
    cap = reports["capture"]
    assert cap["tilted"]["frames"] == 12 and cap["frames"] == 162 and cap["unit"]["zone_time_scale"] == 0.015
    g = reports["forward"]["geometry"]
    assert g["capture"] == "tilted" and g["adopted"] == "time_scales" and not g["time_scales"]["not_determined"]
    assert g["told_apart"] and "many surfaces" not in g["why"]  # one table: the first fit's 95 % CV was its misreading
    fwd = cal.forward()
    assert math.degrees(np.abs(np.array(fwd.mount_tilt) - np.array(cap["unit"]["mount_tilt"])).max()) < 0.1
    # the zones' time scales as the simulator drew them (the centre zone's the gauge): within 0.2 % (0.09 %; the level
    # sweep's reading, whose scales also hold the mount, is 0.48 % off)
    from place_safe.sim.scene import SceneConfig, build_scene
    from place_safe.sim.tof import ToFConfig
    from place_safe.sim.tof_mismatch import make_sensor

    scene = build_scene(SceneConfig())
    unit_sensor = make_sensor("mismatch", scene, scene.make_data(), ToFConfig(seed=cap["seed"]),
                              MismatchConfig(**cap["unit"]))
    drawn = unit_sensor._time_scale / unit_sensor._time_scale[4]
    assert np.abs(np.array(fwd.zone_bin_scales) - drawn).max() < 0.002
    tilted = capture_level_sweep("mismatch", 96, seed=6, temperature=OPERATING_TEMPERATURE, heights=(0.05, 0.30),
                                 max_tilt=math.radians(30.0), mismatch=MismatchConfig(**cap["unit"]))
    read = {}
    for name in ("calibration_mismatch_zone_time_mount_tilts.json", "calibration_mismatch_zone_time_mount.json"):
        ests = make_estimator("diff", Calibration.load(path.with_name(name))).estimate_many(tilted)
        read[name] = (float(np.degrees(np.mean([angular_error(e.plane, f.truth) for e, f in zip(ests, tilted)]))),
                      float(np.mean([abs(e.plane.offset - f.truth.offset) for e, f in zip(ests, tilted)])),
                      float(np.nanmean(nees(ests, [f.truth for f in tilted]))))
    (angle, offset, value), (angle_level, offset_level, _) = read.values()
    assert angle < 0.08 and offset < 1e-4 and value <= 2.0, read
    assert angle < 0.6 * angle_level and offset < 0.2 * offset_level, read


def test_the_mount_tilt_units_calibration_keeps_the_mount_and_widens_peaks_offset_by_it():
    """``sim/sensors/calibration_mismatch_mount_tilt.json`` (sim/make_unit_calibration.py; the mount_tilt_*
    scenarios): valid, made from a level sweep of unit A mounted 1.5 deg off its nominal orientation; the forward fit
    keeps the mount (the time-scale reading explains the sweep no better) and finds it within 0.1 deg, and peak's stated
    tilt term has the offset part that mount asks for."""
    from place_safe.calibration.uncertainty import PEAK_MOUNT_OFFSET_REL

    path = calibration_file("mismatch").with_name("calibration_mismatch_mount_tilt.json")
    cal = Calibration.load(path).check()
    reports = json.loads(path.read_text())["reports"]
    cap = reports["capture"]
    assert cap["max_tilt_deg"] == 0.0 and cap["frames"] >= 100
    truth = np.array(cap["unit"]["mount_tilt"])
    assert math.degrees(np.hypot(*truth)) == pytest.approx(1.5, abs=0.01)
    assert reports["forward"]["geometry"]["adopted"] == "free"
    fitted = np.array(cal.forward().mount_tilt)
    assert math.degrees(np.abs(fitted - truth).max()) < 0.1
    peak = cal.sections["uncertainty"]["peak"]
    assert peak["tilt_offset_rel"] == pytest.approx(PEAK_MOUNT_OFFSET_REL * np.hypot(*fitted))


def test_the_level_calibrated_time_scale_units_cover_diffs_errors_on_tilted_planes():
    """The packaged calibrations of the units whose zones keep their own time (with and without a 1.0 deg mount), made
    from a level sweep: on 96 tilted frames of the same unit (another seed, 0-30 deg, 5-30 cm) diff's covariance is
    never overconfident (NEES per dof at most 2), and on the unit with the mount, where a level sweep leaves both
    things undetermined, within 0.5-2 (0.62; 0.31 with the stated tilt floor at 0.005, sized before the simulator
    rendered the time scales before the bins: docs/results.md, "Diff's stated tilt floor re-sized"). The unit without
    a mount stays cautious (0.15): its stated offset holds a mount the sweep cannot rule out. Each packaged unit
    calibration's stated term is the one :func:`diff_tilt_term` states now from its report's inputs (made again when
    the term's constants change)."""
    from place_safe.calibration.uncertainty import diff_tilt_term
    from place_safe.evaluation.metrics import nees
    from place_safe.recovery import make_estimator
    from place_safe.sim.calibration_capture import OPERATING_TEMPERATURE, capture_level_sweep
    from place_safe.sim.tof_mismatch import MismatchConfig

    for name in ("calibration_mismatch_zone_time_mount.json", "calibration_mismatch_zone_time.json",
                 "calibration_mismatch_mount_tilt.json"):  # made with the stated term as the module states it now
        raw = json.loads(calibration_file("mismatch").with_name(name).read_text())
        rep, left = raw["reports"]["uncertainty"]["diff"], raw["reports"]["uncertainty"]["diff"]["tilt_mount_left_deg"]
        term = diff_tilt_term(rep["tilt_model_error"], rep["tilt_crosstalk"], rep["tilt_readings"],
                              None if left is None else math.radians(left))
        assert raw["uncertainty"]["diff"]["tilt_rel"] == pytest.approx(term.tilt_rel, rel=1e-9), name
        assert raw["uncertainty"]["diff"]["tilt_offset_rel"] == pytest.approx(term.tilt_offset_rel, rel=1e-9), name
    for name, band in (("calibration_mismatch_zone_time_mount.json", (0.5, 2.0)),
                       ("calibration_mismatch_zone_time.json", (0.0, 2.0))):
        path = calibration_file("mismatch").with_name(name)
        unit = MismatchConfig(**json.loads(path.read_text())["reports"]["capture"]["unit"])
        tilted = capture_level_sweep("mismatch", 96, seed=6, temperature=OPERATING_TEMPERATURE, heights=(0.05, 0.30),
                                     max_tilt=math.radians(30.0), mismatch=unit)
        ests = make_estimator("diff", Calibration.load(path)).estimate_many(tilted)
        assert sum(e.method_used.startswith("diff") for e in ests) >= 0.9 * len(ests)
        value = float(np.nanmean(nees(ests, [f.truth for f in tilted])))
        assert band[0] <= value <= band[1], (name, value)


def test_a_sensor_mounted_off_its_nominal_orientation_widens_peaks_offset_on_tilted_planes():
    """A unit mounted 0.94 deg off its nominal orientation, calibrated on a level sweep: peak's zone gains read the
    tilt as the zones' own time scales, which a level table cannot tell apart from a mount tilt, and on tilted planes
    its offset parts from the truth in a way its stated term (the plane turning about the point it crosses the axis)
    does not describe. With the forward model's mount tilt in the file (here the simulator's, standing in for the
    forward fit's, which finds it within 0.03 deg: docs/results.md, "A sensor mounted off its nominal orientation")
    peak's covariance gets an offset part and covers those planes; without a forward model it states none."""
    from place_safe.calibration.fit import fit_method
    from place_safe.calibration.uncertainty import PEAK_MOUNT_OFFSET_REL, update_calibration
    from place_safe.evaluation.metrics import nees
    from place_safe.recovery import make_estimator
    from place_safe.recovery.forward import ForwardParams
    from place_safe.sim.calibration_capture import OPERATING_TEMPERATURE, capture_level_sweep
    from place_safe.sim.tof_mismatch import MismatchConfig

    tilt = [math.radians(0.8), math.radians(-0.5)]
    unit = MismatchConfig(mount_tilt=tilt)
    level = capture_level_sweep("mismatch", 60, seed=5, temperature=OPERATING_TEMPERATURE, heights=(0.05, 0.40),
                                max_tilt=0.0, mismatch=unit)
    tilted = capture_level_sweep("mismatch", 40, seed=6, temperature=OPERATING_TEMPERATURE, heights=(0.08, 0.30),
                                 min_tilt=math.radians(15), max_tilt=math.radians(30), mismatch=unit)
    cal = Calibration()
    fit_method(cal, level, "peak")

    def peaks_nees() -> float:
        ests = make_estimator("peak", cal).estimate_many(tilted)
        return float(np.nanmean(nees(ests, [f.truth for f in tilted])))

    assert cal.sections["uncertainty"]["peak"].get("tilt_offset_rel", 0.0) == 0.0
    without = peaks_nees()
    cal.sections["forward"] = ForwardParams(mount_tilt=tilt).to_dict()
    update_calibration(cal, level, "peak")
    stated = cal.sections["uncertainty"]["peak"]["tilt_offset_rel"]
    assert math.isclose(stated, PEAK_MOUNT_OFFSET_REL * math.hypot(*tilt))
    assert without > 5.0 and 0.3 <= peaks_nees() <= 2.0, (without, peaks_nees())
