"""Choosing between a level sweep's two readings with tilted frames without ground truth
(:mod:`place_safe.calibration.readings`, and its use in
:func:`~place_safe.calibration.second_fit.reconsider_geometry`).

The frames here are rendered by the forward model with one of the two readings and read with both: convention checks
(the comparison picks the reading that made the frames). That tilted frames of simulated units choose the unit's own
reading is measured in docs/results.md ("Tilted frames without ground truth choose the reading")."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

import place_safe.calibration.forward_fit as ff
import place_safe.calibration.second_fit as sf
from place_safe.calibration.readings import (READING_MAJORITY, READING_MIN_APART, READING_MIN_FRAMES, READING_MIN_TILT,
                                             compare_readings, decide)
from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
from place_safe.recovery.forward import ForwardParams
from place_safe.recovery.points import PeakParams

#: The first fit's reading (fields of view wide, the mount off) and the second's (nominal geometry, each zone's own
#: time scale), as a level sweep may leave them.
FREE = ForwardParams(edge_fov_scale=1.12, corner_fov_scale=1.08, mount_tilt=[0.012, 0.014])
TIME_SCALES = ForwardParams(zone_bin_scales=[1.004, 1.009, 1.012, 0.999, 1.0, 1.003, 1.0, 1.006, 1.003])


def tilted(params: ForwardParams, n: int = 12, seed: int = 3) -> list:
    """``n`` frames of planes tilted 12-30 deg, 8-25 cm, rendered with ``params``, their ground truth taken out."""
    spec = SyntheticSpec(z_range=(0.08, 0.25), theta_range=(math.radians(12.0), math.radians(30.0)))
    frames = make_frames(n, params, spec, seed=seed)
    for f in frames:
        f.truth = None
    return frames


def test_the_decision_needs_enough_tilted_frames_readings_apart_and_a_clear_majority():
    """:func:`decide`: fewer than READING_MIN_FRAMES frames compared, readings whose planes of them lie closer than
    READING_MIN_APART, or a share between the majorities, leaves both readings; a share at or beyond the majority
    chooses one, and the reason says what was seen."""
    n = READING_MIN_FRAMES
    base = {"frames": 30, "tilted": n, "compared": n, "median_ratio": 0.9, "apart_deg": 1.2}
    for apart in (0.0, math.degrees(READING_MIN_APART) * 0.99, math.nan):
        choice, why = decide({**base, "other_lower": 1.0, "apart_deg": apart})
        assert choice is None and "alike" in why
    assert decide({**base, "other_lower": 0.0, "apart_deg": math.degrees(READING_MIN_APART)})[0] == "kept"
    assert decide({**base, "compared": n - 1, "other_lower": 1.0})[0] is None
    assert "are needed" in decide({**base, "compared": n - 1, "other_lower": 1.0})[1]
    assert decide({**base, "other_lower": READING_MAJORITY})[0] == "other"
    assert decide({**base, "other_lower": 1.0 - READING_MAJORITY})[0] == "kept"
    for share in (0.5, READING_MAJORITY - 0.01, 1.0 - READING_MAJORITY + 0.01):
        choice, why = decide({**base, "other_lower": share})
        assert choice is None and "neither" in why
    assert "100 % of 10 tilted frames" in decide({**base, "other_lower": 1.0})[1]


def test_the_reading_that_rendered_tilted_frames_fits_them_better():
    """Convention check: frames rendered with one reading, fitted with both, leave the smaller residual with it on a
    clear majority; level frames are not compared (both readings read a level plane alike)."""
    peak = PeakParams.default_peak()
    made_by_other = compare_readings(tilted(TIME_SCALES), FREE, TIME_SCALES, peak)
    assert made_by_other["tilted"] == made_by_other["compared"] == 12
    assert made_by_other["other_lower"] >= READING_MAJORITY and made_by_other["median_ratio"] < 1.0
    assert made_by_other["apart_deg"] >= math.degrees(READING_MIN_APART)
    assert decide(made_by_other)[0] == "other"
    made_by_kept = compare_readings(tilted(FREE, seed=4), FREE, TIME_SCALES, peak)
    assert made_by_kept["other_lower"] <= 1.0 - READING_MAJORITY and decide(made_by_kept)[0] == "kept"

    spec = SyntheticSpec(z_range=(0.08, 0.25), theta_range=(0.0, 0.5 * READING_MIN_TILT))
    level = compare_readings(make_frames(6, TIME_SCALES, spec, seed=5), FREE, TIME_SCALES, peak)
    assert level["tilted"] == level["compared"] == 0 and math.isnan(level["other_lower"])
    assert decide(level)[0] is None


@pytest.fixture
def sweep_left_both(monkeypatch):
    """A level sweep (three level truths) whose first fit ``FREE`` is kept with the second fit ``TIME_SCALES`` a little
    better in RMS (half the lower of ``NOMINAL_GEOMETRY_GAIN`` and ``ALBEDO_CLUE_GAIN``) and its albedos spread 1.5
    times less: neither a clear gain nor the albedo's evidence, so both readings stay possible (the second fit stood in
    by what it returns)."""
    level = [SimpleNamespace(truth=SimpleNamespace(normal=np.array([0.0, 0.0, 1.0]))) for _ in range(3)]
    first = {"rms_scaled_residual_after": 1.40, "converged": True, "one_surface": {"albedo_cv_after": 0.03}}
    gain = 0.5 * min(sf.NOMINAL_GEOMETRY_GAIN, sf.ALBEDO_CLUE_GAIN)
    second = {"rms_scaled_residual_after": 1.40 * (1.0 - gain), "converged": True, "solver": {"seconds": 1.0},
              "one_surface": {"albedo_cv_after": 0.02}}
    monkeypatch.setattr(ff, "fit_forward", lambda *a, **k: (TIME_SCALES, dict(second)))
    return level, first


def test_tilted_frames_without_truth_adopt_the_other_reading_of_a_level_sweep(sweep_left_both):
    """``reconsider_geometry`` with ``unlabelled`` frames made by the second reading: it is adopted, the readings count
    as told apart, the report keeps the first as the other reading and says what the frames showed."""
    level, first = sweep_left_both
    lines: list[str] = []
    p, r = sf.reconsider_geometry(level, FREE, dict(first), progress=False, log=lines.append,
                                  unlabelled=tilted(TIME_SCALES), peak=PeakParams.default_peak())
    g = r["geometry"]
    assert p is TIME_SCALES and g["adopted"] == "nominal_time_scales" and g["told_apart"] is True
    assert g["other_params"]["edge_fov_scale"] == FREE.edge_fov_scale
    assert g["unlabelled"]["chose"] == "other" and g["unlabelled"]["compared"] == 12
    assert "without ground truth chose" in g["why"] and "adopted" in lines[-1]


def test_tilted_frames_without_truth_keep_the_first_reading_or_leave_both(sweep_left_both):
    """Frames made by the first reading keep it and tell the readings apart; too few tilted frames leave both readings
    (as without frames), and the report says why; no frames: the sweep's own choice, unchanged."""
    level, first = sweep_left_both
    p, r = sf.reconsider_geometry(level, FREE, dict(first), progress=False, unlabelled=tilted(FREE, seed=4),
                                  peak=PeakParams.default_peak())
    g = r["geometry"]
    assert p is FREE and g["adopted"] == "free" and g["told_apart"] is True and g["unlabelled"]["chose"] == "kept"
    assert g["other_params"]["zone_bin_scales"][2] == TIME_SCALES.zone_bin_scales[2]
    assert "note" not in g  # the geometry note warns of the two readings, which the frames told apart

    p, r = sf.reconsider_geometry(level, FREE, dict(first), progress=False, unlabelled=tilted(FREE, n=4),
                                  peak=PeakParams.default_peak())
    g = r["geometry"]
    assert p is FREE and g["told_apart"] is False and g["unlabelled"]["chose"] == "neither"
    assert "are needed" in g["unlabelled"]["why"] and "capture tilted poses" in g["note"]

    p, r = sf.reconsider_geometry(level, FREE, dict(first), progress=False)
    assert p is FREE and r["geometry"]["told_apart"] is False and "unlabelled" not in r["geometry"]


def test_the_report_says_whether_the_frames_were_used_and_the_note_what_they_showed(sweep_left_both):
    """``reports.forward.unlabelled`` (:func:`~place_safe.calibration.fit.unlabelled_summary`): used, with the choice,
    where the frames were compared; else why not, for each shape the forward report takes (told apart, the second fit
    failed or did not converge, one reading). The uncertainty note's tail (:func:`~place_safe.calibration.uncertainty.
    readings_note_tail`) names --readings-from where no frames were compared, and what they showed where they chose
    neither."""
    from place_safe.calibration import Calibration
    from place_safe.calibration.fit import unlabelled_summary
    from place_safe.calibration.uncertainty import READINGS_FROM_NOTE, readings_note_tail

    level, first = sweep_left_both
    _, used = sf.reconsider_geometry(level, FREE, dict(first), progress=False, unlabelled=tilted(FREE, n=4),
                                     peak=PeakParams.default_peak())
    summary = unlabelled_summary(used, 4)
    assert summary["used"] and summary["chose"] == "neither" and "are needed" in summary["why"]
    cases = (({"geometry": {"told_apart": True}}, "told its two readings apart"),
             ({"geometry": {"told_apart": False, "nominal_time_scales": {"failed": "ArithmeticError: x"}}},
              "failed (ArithmeticError: x)"),
             ({"geometry": {"told_apart": False, "nominal_time_scales": {"converged": False}}}, "did not converge"),
             ({"geometry": {"note": "n", "free": {}, "adopted": "free"}}, "one reading"),
             ({"geometry": {"capture": "tilted", "told_apart": True, "adopted": "time_scales"}}, "tilted frames with "
              "ground truth"),
             ({"geometry": {"capture": "tilted", "told_apart": False, "time_scales": {"failed": "x"}}},
              "tilted frames"),
             ({}, "one reading"))
    for report, says in cases:
        summary = unlabelled_summary(report, 20)
        assert summary == {"frames": 20, "used": False, "why": summary["why"]} and says in summary["why"]

    assert readings_note_tail(Calibration()) == READINGS_FROM_NOTE
    cal = Calibration()
    cal.reports["forward"] = used
    assert "chose neither" in readings_note_tail(cal) and "are needed" in readings_note_tail(cal)


def test_the_frames_adopt_the_second_reading_only_where_the_sweep_reads_one_surface_with_it(monkeypatch):
    """A second fit that reads the level table as many albedos (CV above SAME_SURFACE_CV) where the first reads one
    surface is not adopted, whatever the frames' residuals say; the frames may still keep the first; where both read
    many albedos, the albedos do not witness and the frames choose. (The figures are unit 43's before the albedo spread
    left out frames at their bound: its second fit's 110 % was one saturated frame.)"""
    level = [SimpleNamespace(truth=SimpleNamespace(normal=np.array([0.0, 0.0, 1.0]))) for _ in range(3)]
    first = {"rms_scaled_residual_after": 1.99, "converged": True, "one_surface": {"albedo_cv_after": 0.09}}
    second = {"rms_scaled_residual_after": 1.49, "converged": True, "solver": {"seconds": 1.0},
              "one_surface": {"albedo_cv_after": 1.10}}
    monkeypatch.setattr(ff, "fit_forward", lambda *a, **k: (TIME_SCALES, dict(second)))
    p, r = sf.reconsider_geometry(level, FREE, dict(first), progress=False, unlabelled=tilted(TIME_SCALES),
                                  peak=PeakParams.default_peak())
    g = r["geometry"]
    assert p is FREE and g["told_apart"] is False and g["unlabelled"]["chose"] == "neither"
    assert "many albedos" in g["unlabelled"]["why"] and "110 %" in g["unlabelled"]["why"]
    p, r = sf.reconsider_geometry(level, FREE, dict(first), progress=False, unlabelled=tilted(FREE, seed=4),
                                  peak=PeakParams.default_peak())
    assert p is FREE and r["geometry"]["told_apart"] is True and r["geometry"]["unlabelled"]["chose"] == "kept"
    many = dict(first, one_surface={"albedo_cv_after": 1.04})  # both read many albedos
    p, r = sf.reconsider_geometry(level, FREE, many, progress=False, unlabelled=tilted(TIME_SCALES),
                                  peak=PeakParams.default_peak())
    assert p is TIME_SCALES and r["geometry"]["told_apart"] is True and r["geometry"]["unlabelled"]["chose"] == "other"
