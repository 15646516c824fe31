"""Choosing between the two readings of a level sweep with tilted frames that need no ground truth.

A level table cannot tell the zones' directions (fields of view, the mount) from each zone's own time scale: both
move a zone's range by a factor that does not change with distance (:func:`~place_safe.calibration.second_fit.
reconsider_geometry`). Where the sweep did not tell them apart (``reports.forward.geometry.told_apart`` false), the
two readings read tilted planes differently, by up to a quarter of the slope (the real sweep's 27 %), and diff's
covariance holds that difference (:func:`~place_safe.calibration.uncertainty.reading_disagreement`).

A tilted surface tells them apart without knowing its plane: each reading's diff fit of the same frame leaves a
residual, and the reading that describes the unit leaves the smaller one. Frames the arm records above anything
tilted (a ramp, a book on the table, ``place-safe sensor record``) will do; their ground truth, if any, is not used.

How it decides (:func:`compare_readings`, then :func:`decide`):

1. each frame's tilt by the calibrated peak method; frames tilted less than :data:`READING_MIN_TILT` are not used
   (on a level plane both readings read the same plane and fit alike);
2. each tilted frame fitted by diff with either reading, both under the same noise model (the kept reading's model
   error: in ``calibrate`` the first fit's, as the choice comes before the model error is selected) and solver
   options, so their residuals compare bin for bin over the same window;
3. where the two readings' planes of those frames lie :data:`READING_MIN_APART` or more apart (median), the share of
   frames where the other reading leaves the smaller residual: at least :data:`READING_MAJORITY` adopts it, at most
   ``1 - READING_MAJORITY`` keeps the first; both tell the readings apart. Between the two, with readings that read
   the frames alike, or with fewer than :data:`READING_MIN_FRAMES` tilted frames, nothing changes and the report says
   why.

The frames do not adopt the second reading where the level sweep speaks against it: the first fit reads the table as
one surface and the second as many albedos (the frames' albedo CV above ``SAME_SURFACE_CV``; where both do, the
albedos cannot witness). The rule was set on unit 43, whose second fit seemed to read its table at 110 % against the
first's 9 %; that 110 % was one saturated frame at its albedo bound (``forward_fit.albedo_spread`` now leaves such
frames out), and its sweep now adopts the second reading itself. (Unit 43's figures here and below were measured on the
simulator before 2026-11-30, whose zone time scales also blurred each return; with the returns moved before the bins
its sweep adopts the time scales and diff reads it at 0.15 deg, NEES per dof 0.91: docs/results.md, "Each zone's own
time scale rendered before the bins".)

The second reading holds the mount level: a unit mounted off keeps the mount in the first reading, and where the
second is adopted its offsets on tilted planes err by the mount (0.67-0.99 mm mean at 5-30 cm and 0-30 deg on the
units measured, about peak's). Tilted frames without ground truth cannot show the mount (turning the sensor and the plane
together changes no histogram); tilted poses with ground truth can (``calibrate`` on both files).

Measured (docs/results.md, "Tilted frames without ground truth choose the reading"): on simulated units whose level
sweeps did not tell the readings apart, 20 such frames chose the unit's reading on 40, 41, 44 and 47 (the other
reading lower on 90-100 % of them), and diff's own plane on their 150 tilted test frames went from 1.4-1.9 deg to
0.07-0.18 (NEES per dof 0.01-0.08 -> 0.15-0.65); on the independent generator's seed 5, whose first reading is the
better one, they chose neither (44 %); on unit 43 the second (above); on units 37 and 45, mounted off alone, the
readings read them alike. Since the level sweep's own rule also weighs the albedo (``second_fit.ALBEDO_CLUE_FACTOR``),
the sweeps of 44 and 47 adopt their reading without the frames.
"""
from __future__ import annotations

import math
from typing import Callable, Sequence

import numpy as np

from place_safe.evaluation.metrics import angular_error
from place_safe.recovery.forward import ForwardParams
from place_safe.recovery.points import PeakParams
from place_safe.sensor.frame import Frame

#: rad: frames whose plane peak reads tilted less than this do not count (a level plane reads alike in both readings).
READING_MIN_TILT = math.radians(5.0)
#: Tilted frames needed before the readings are compared at all.
READING_MIN_FRAMES = 10
#: rad: readings whose planes of the tilted frames lie closer than this (median) read them alike, and the sweep's own
#: choice stands: choosing would move slopes less than diff's own error on tilted planes (0.06-0.2 deg on simulated
#: units), and the first reading keeps the mount, which the second holds level (unit 45, mounted 0.5 deg off, read
#: 0.41 mm off in offset with the second reading against 0.07 with the first; its readings 0.06 deg apart).
READING_MIN_APART = math.radians(0.3)
#: Share of the tilted frames on which one reading must leave the smaller residual to be chosen. On unit 40, the
#: noisiest of the units measured, 86 % of the frames tilted 10 deg or more chose the unit's reading: 20 such frames
#: reach this share with a probability of 0.96 (binomial), and choose the wrong reading with one of about 1e-6.
READING_MAJORITY = 0.75


def compare_readings(frames: Sequence[Frame], kept: ForwardParams, other: ForwardParams, peak: PeakParams,
                     options=None, progress: Callable[[int], None] | None = None) -> dict:
    """Each tilted frame of ``frames`` fitted by diff with the ``kept`` and the ``other`` reading (both with
    ``kept``'s model error, ``options`` the solver's): a dict with ``frames`` (all), ``tilted`` (tilted at least
    :data:`READING_MIN_TILT` by ``peak``), ``compared`` (those both readings fitted), ``other_lower`` (the share of
    those where ``other`` left the smaller residual; NaN with none), ``median_ratio`` (other's residual over kept's),
    ``tilt_deg`` (the compared frames' median tilt) and ``apart_deg`` (the median angle between the two readings'
    planes of a frame). ``progress`` gets the number of frames done."""
    from place_safe.recovery.differentiable import DifferentiableEstimator
    from place_safe.recovery.peak import PeakEstimator

    tilts = np.array([e.plane.theta if e.ok else math.nan for e in PeakEstimator(peak).estimate_many(list(frames))],
                     dtype=float)
    with np.errstate(invalid="ignore"):
        tilted = [f for f, t in zip(frames, tilts) if t >= READING_MIN_TILT]
    if progress is not None:
        progress(len(frames) - len(tilted))  # the frames not compared
    same_noise = other.model_copy(update={"model_error": kept.model_error})
    ka = DifferentiableEstimator(kept, peak, options=options)
    kb = DifferentiableEstimator(same_noise, peak, options=options)
    ratios, used_tilts, apart = [], [], []
    for i in range(0, len(tilted), 16):
        chunk = tilted[i:i + 16]
        for a, b in zip(ka.estimate_many(chunk), kb.estimate_many(chunk)):
            ra, rb = a.residual, b.residual
            if a.ok and b.ok and ra is not None and rb is not None and ra > 0 and math.isfinite(ra) and math.isfinite(rb):
                ratios.append(rb / ra)
                used_tilts.append(a.plane.theta)
                apart.append(angular_error(a.plane, b.plane))
        if progress is not None:
            progress(len(chunk))
    r = np.array(ratios)
    return {"frames": len(frames), "tilted": len(tilted), "compared": len(r),
            "other_lower": float(np.mean(r < 1.0)) if len(r) else math.nan,
            "median_ratio": float(np.median(r)) if len(r) else math.nan,
            "tilt_deg": float(np.degrees(np.median(used_tilts))) if used_tilts else math.nan,
            "apart_deg": float(np.degrees(np.median(apart))) if apart else math.nan}


def decide(comparison: dict) -> tuple[str | None, str]:
    """``("other" | "kept" | None, why)`` from :func:`compare_readings`' ``comparison``: None leaves both readings
    possible."""
    n, share = comparison["compared"], comparison["other_lower"]
    if n < READING_MIN_FRAMES:
        return None, (f"{comparison['tilted']} of {comparison['frames']} frame(s) read tilted "
                      f"{math.degrees(READING_MIN_TILT):.0f} deg or more by peak, {n} of them fitted by both readings; "
                      f"{READING_MIN_FRAMES} are needed")
    if not comparison["apart_deg"] >= math.degrees(READING_MIN_APART):
        return None, (f"the two readings read the {n} tilted frames alike (their planes a median "
                      f"{comparison['apart_deg']:.2f} deg apart, under {math.degrees(READING_MIN_APART):.1f})")
    told = (f"the other reading left the smaller residual on {100 * share:.0f} % of {n} tilted frames (median "
            f"residual ratio {comparison['median_ratio']:.3f})")
    if share >= READING_MAJORITY:
        return "other", told
    if share <= 1.0 - READING_MAJORITY:
        return "kept", told
    return None, f"{told}: neither reading on {100 * READING_MAJORITY:.0f} % of them"


__all__ = ["compare_readings", "decide", "READING_MIN_TILT", "READING_MIN_FRAMES", "READING_MIN_APART",
           "READING_MAJORITY"]
