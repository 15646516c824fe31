"""A second forward fit that reads the unit's geometry the other way, and when a capture adopts it.

A level table cannot tell the zones' directions (their fields of view, the mount) from each zone's own time scale:
both move a zone's range by a factor that does not change with distance. The first forward fit
(:func:`~place_safe.calibration.forward_fit.fit_forward`) reads it one way; a second fit reads it the other
(:func:`second_fit_for`: on a level sweep the geometry held nominal and each zone's time scale fitted, on a capture
with tilted frames both fitted at once), and :func:`reconsider_geometry` keeps the one the capture supports: the
better fit to the counts by a clear margin, converged, determined, and reading one table as one albedo. The report's
``geometry`` section says which and why; :func:`geometry_note` warns when a level sweep set the geometry far from the
nominal one.
"""
from __future__ import annotations

import math
import sys
from collections.abc import Sequence

import numpy as np
from tqdm import tqdm

from place_safe.calibration import forward_fit  # its fit_forward through the module: a test stands in for it there
from place_safe.calibration.forward_fit import (FITTED, SAME_SURFACE_CV, ZONE_SCALE_TERMS, free_crosstalk_std,
                                               level_sweep)
from place_safe.recovery.differentiable import SolverOptions
from place_safe.recovery.forward import ForwardParams
from place_safe.recovery.points import PeakParams
from place_safe.sensor.frame import Frame


#: A forward fit to level frames whose mount tilt (rad, either component) or edge / corner field-of-view scale lands
#: beyond these gets :func:`geometry_note`. The simulated units and the independent generator land within 0.1 deg
#: and 0.97-1.08; the real sweep at 4.2 deg and 0.81 / 0.67, and a simulated unit whose zones keep their own time
#: (+-1.5 %) at 1.1 deg and 0.68 / 0.93, where diff then misreads tilted planes by 2.9 deg (docs/results.md, "Each
#: zone's own time scale").
GEOMETRY_NOTE_MOUNT_TILT = math.radians(0.5)
GEOMETRY_NOTE_FOV = (0.9, 1.1)
#: The note (``calibrate`` prints it) when a level sweep set the zones' geometry far from the nominal one.
GEOMETRY_NOTE = ("the level sweep set the zones' geometry away from the nominal (edge / corner fields of view "
                 "{edge:.2f} / {corner:.2f}, mount tilt {tilt:.1f} deg): a level table cannot tell the zones' "
                 "directions from each zone's own time scale, so diff may misread tilted planes by degrees while its "
                 "covariance says tenths; capture tilted poses too (capture --distances 80,150,220 --incidences "
                 "12,24 --azimuths 0,90,180,270) and calibrate on both files")


def _geometry_beyond(params: ForwardParams, fov: tuple[float, float], mount_tilt: float) -> bool:
    """Whether ``params`` puts the mount tilt (either component) beyond ``mount_tilt`` (rad) or the edge or corner
    field-of-view scale outside ``fov``."""
    lo, hi = fov
    return (float(np.max(np.abs(params.mount_tilt))) > mount_tilt
            or not all(lo <= s <= hi for s in (params.edge_fov_scale, params.corner_fov_scale)))


def geometry_note(params: ForwardParams, frames: Sequence[Frame]) -> str | None:
    """:data:`GEOMETRY_NOTE` when ``frames`` (their truths) are level and ``params`` puts the mount tilt or the edge or
    corner field of view beyond :data:`GEOMETRY_NOTE_MOUNT_TILT` / :data:`GEOMETRY_NOTE_FOV`, else None."""
    if not level_sweep(frames) or not _geometry_beyond(params, GEOMETRY_NOTE_FOV, GEOMETRY_NOTE_MOUNT_TILT):
        return None
    tilt = float(np.max(np.abs(params.mount_tilt)))
    return GEOMETRY_NOTE.format(edge=params.edge_fov_scale, corner=params.corner_fov_scale, tilt=math.degrees(tilt))


#: The zones' geometry that a level sweep cannot tell from each zone's own time scale, held at its nominal value (fields
#: of view 1, the mount level) by the second fit of :func:`reconsider_geometry`, the way the peak method holds its own
#: geometry and fits a gain per zone. ``beam_power`` (the beam's weighting of a footprint, which the staged fit holds
#: with :data:`~place_safe.calibration.forward_fit.GEOMETRY` while it fits the scales from stage 1's values) stays
#: fitted here: this fit starts from the default start, not from geometry a fit has already set; held as well, the real
#: even half's second fit came out the same (RMS 3.479, its albedo spread alike; docs/results.md, "A far geometry").
NOMINAL_GEOMETRY = ("edge_fov_scale", "corner_fov_scale", "mount_tilt")
#: What the second fit of :func:`reconsider_geometry` fits: :data:`~place_safe.calibration.forward_fit.FITTED` and each
#: zone's own time scale (:data:`~place_safe.calibration.forward_fit.ZONE_SCALE_TERMS`) less :data:`NOMINAL_GEOMETRY`.
NOMINAL_GEOMETRY_FITTED: dict[str, str] = {k: v for k, v in {**FITTED, **ZONE_SCALE_TERMS}.items()
                                           if k not in NOMINAL_GEOMETRY}
#: The relative fall of the level fit's RMS scaled residual the nominal-geometry fit must show to be adopted. Measured
#: (docs/results.md, "A far geometry"): units whose zones keep their own time, or whose tails are heavy, -7 .. -24 %
#: (35, 32, 34, 36); units that land near nominal within 0.2 %; the real sweep -4.5 .. -5.4 %. On the simulator since
#: 2026-11-30 (zone time scales that move the returns before the bins, no blur): the time-scale units 34-58 -9.5 ..
#: -56 %, unit 60 (scales of 0.8 %) -3.7 %, units without them within 0.1 % (but 32, -17.9 %). Lowered 5 -> 2.5 % on
#: unit 60 (its sweep then left both readings open: diff's own plane 1.06 deg), then measured on units 65-69 set before
#: it (docs/results.md, "Each zone's own time scale rendered before the bins"); the real halves' -4.5 / -5.4 % stay
#: refused by their albedos.
NOMINAL_GEOMETRY_GAIN = 0.025
#: The nominal-geometry fit is adopted only while the per-frame albedos of the level sweep (one table: one albedo,
#: ``report["one_surface"]["albedo_cv_after"]``, each frame's albedo free in both fits) spread at most this many times
#: as much as in the first fit: a reading of the zones' time that makes one surface read many albedos is not the unit's.
#: Measured on the albedos the counts determined (:func:`~place_safe.calibration.forward_fit.albedo_spread`;
#: docs/results.md, "The level sweep's albedo"): the real halves 4.5 -> 21 % and 3.0 -> 27 % (4.7, 9.2 times; kept:
#: their albedo's range law does not survive the time scales, 1.9 / 1.4 -> 5.8 / 7.0 % on the other half); units whose
#: zones keep their own time rise at most 2.7 times (34 3.0 -> 8.2 %, 36 4.0 -> 7.6 %, 48 5.1 -> 6.7 %) or fall (35, 47,
#: 52); units with both the time scales and a mount 2.85 times (41), 4.1 (54) and 4.9 (50). Set at 1.5 when a saturated
#: frame at its albedo bound read as a CV of 93-114 % (34, 36), it then kept 34 and 36 at 1.52 / 0.44 deg against 0.13 /
#: 0.11 adopted. (The simulated units' figures here were measured before 2026-11-30, on a simulator whose zone time
#: scales also blurred each return; with the returns moved before the bins, every time-scale unit's second reading reads
#: its table at a CV of 0.6-4.6 %, mostly below its first's, and unit 52's rose 0.58 -> 2.64 %:
#: :data:`NOMINAL_GEOMETRY_ALBEDO_CV`.)
NOMINAL_GEOMETRY_ALBEDO_SPREAD = 3.0
#: ...or by at most this much more (an absolute CV), whichever is larger: a first fit whose frames read nearly one
#: albedo (its CV near 0) does not refuse every second fit for noise. Where the two readings are alike (units without
#: their zones' own time or with a mount alone), their CVs differ by up to 2 % either way (33 2.9 -> 1.0 %, 55 2.5 ->
#: 0.8 %, 38 2.2 -> 3.6 %). At 0.5 % it refused unit 52's time scales (0.58 -> 2.64 %, RMS 18.6 % lower; diff then read
#: its tilted planes at 1.5 deg, the time scales at about 0.1) once the simulator's time scales stopped blurring the
#: returns (docs/results.md, "Each zone's own time scale rendered before the bins"); set to 3 % on that, then measured
#: on units 60-64. The real halves' second readings spread 16.5 and 24.5 % more.
NOMINAL_GEOMETRY_ALBEDO_CV = 0.03
#: ...and the nominal-geometry fit must read the sweep as one surface: its frames' albedo CV at most
#: :data:`~place_safe.calibration.forward_fit.SAME_SURFACE_CV`, the fit's own bound for a sweep of one table. Frames of
#: surfaces of many albedos (the independent generator draws one per frame: CV 190-250 %) cannot witness for either
#: reading, and the RMS alone does not choose: the generator with sensor seed 5 (first fit's fields of view 0.945 /
#: 0.952) read 6 % better with the time scales, which were adopted, and diff then read its tilted frames at 1.2 deg
#: against peak's 0.34 (NEES 46; docs/results.md, "The independent generator's other sensors"). Units whose second fit
#: is adopted read 0.8-8 %.

#: The albedo's evidence alone: the nominal-geometry fit is also adopted on a smaller fall of the RMS (at least
#: :data:`ALBEDO_CLUE_GAIN`) where the level table reads one albedo much more closely with it: the frames' albedo CV at
#: most 1 / :data:`ALBEDO_CLUE_FACTOR` of the first fit's, which must be at least :data:`ALBEDO_CLUE_MIN_CV` (a fall
#: within noise is no evidence) and both at most :data:`~place_safe.calibration.forward_fit.SAME_SURFACE_CV` (one
#: surface). A zone whose time runs its own scale, read as a field of view, makes the table's brightness drift with
#: range; the time scales read it flat. Measured (docs/results.md, "The level sweep's albedo, counted on the frames that
#: determine it"): units 44 and 47, whose zones keep their own time, RMS 4.0 / 4.7 % lower with the time scales and the
#: albedo CV 3.7 -> 0.7 % / 7.3 -> 1.1 %; units mounted off alone (37, 45, 49, 53, 59: the first reading exact) 0-1.3 %
#: higher, their CV falling at most 1.7 times. Set before units 48-59 were measured. (44's and 47's figures are the
#: simulator's before 2026-11-30, whose zone time scales also blurred each return; without that blur their second fits
#: are 9.5 / 10.0 % lower and adopted by :data:`NOMINAL_GEOMETRY_GAIN`.)
ALBEDO_CLUE_GAIN = 0.02
ALBEDO_CLUE_FACTOR = 3.0
ALBEDO_CLUE_MIN_CV = 0.01


#: A level sweep tells its two readings apart (``report["geometry"]["told_apart"]``, :func:`reconsider_geometry`) where
#: the second fit is adopted (a clearly better fit, one table still one albedo), or where the first is kept and the
#: second's RMS scaled residual is at least this much above the first's. Otherwise both readings stay possible, and on
#: a tilted plane they read different slopes: diff's covariance there holds the difference
#: (:func:`~place_safe.calibration.uncertainty.reading_disagreement`). Measured (docs/results.md, "Two readings of a
#: level sweep"): units whose zones keep their own time and whose sensor is mounted off (simulated units 40, 41) kept
#: the fitted geometry with the second fit 0.9 % worse and 12.6 % better (its albedos spread 2.9 times as much), and
#: diff read their tilted planes 6-9 % too shallow (1.3-1.8 deg) with NEES 68-75; the other reading, rendered, shows
#: that slope to within 0.3 points. (On the simulator before 2026-11-30, whose zone time scales also blurred each
#: return; without that blur 40's and 41's sweeps adopt the time scales themselves. New unit 60, whose scales are 0.8 %,
#: is not told apart: RMS 3.7 % lower.)
TOLD_APART_GAIN = 0.05


def _number(x) -> float:
    """``x`` as a float (NaN when it is not a real number)."""
    try:
        return float(x)
    except (TypeError, ValueError, OverflowError):
        return math.nan


def _frames_left_out(report: dict) -> int:
    """Frames a forward fit's ``report`` left out of its albedo spread: excluded as bad, or at an albedo bound."""
    return int(report.get("frames_excluded_as_bad") or 0) + int((report.get("one_surface") or {})
                                                                  .get("frames_at_albedo_bound") or 0)


def _albedo_cv(report: dict) -> float:
    """The per-frame albedo CV a forward fit's ``report`` gives (NaN: none)."""
    return _number((report.get("one_surface") or {}).get("albedo_cv_after"))


def _compared(report: dict, alt: ForwardParams, alt_report: dict) -> tuple[float, float, float, float, bool, dict, str]:
    """The first fit's ``report`` against the second fit (``alt``, ``alt_report``) of :func:`reconsider_geometry`:
    the two RMS scaled residuals and albedo CVs (NaN: not known), whether the second converged, its summary for the
    report's ``geometry`` section, and the comparison as the user's line says it."""
    rms, rms_alt = _number(report.get("rms_scaled_residual_after")), _number(alt_report.get("rms_scaled_residual_after"))
    cv, cv_alt = _albedo_cv(report), _albedo_cv(alt_report)
    converged = bool(alt_report.get("converged"))
    summary = {"rms_scaled_residual": rms_alt, "converged": converged, "albedo_cv": cv_alt,
               "frames_left_out": _frames_left_out(alt_report),
               "zone_bin_scales": [float(s) for s in alt.zone_bin_scales],
               "seconds": (alt_report.get("solver") or {}).get("seconds")}
    compared = (f"RMS {rms:.3f} -> {rms_alt:.3f}{'' if converged else ' (not converged)'}, the frames' albedo CV "
                f"{100 * cv:.1f} -> {100 * cv_alt:.1f} %")
    return rms, rms_alt, cv, cv_alt, converged, summary, compared


def nominal_geometry_fit(frames: Sequence[Frame], progress: bool = False) -> tuple[ForwardParams, dict]:
    """The second fit of :func:`reconsider_geometry`: :func:`forward_fit.fit_forward` from the default start with
    :data:`NOMINAL_GEOMETRY_FITTED` (a module-level function: ``calibrate`` may run it in a process alongside the
    first fit, :class:`~place_safe.calibration.alongside.Alongside`)."""
    return forward_fit.fit_forward(frames, init=None, progress=progress, fitted=NOMINAL_GEOMETRY_FITTED)


#: What a capture with tilted frames fits beside its first fit (:func:`scales_and_geometry_fit`):
#: :data:`~place_safe.calibration.forward_fit.FITTED` and each zone's own time scale
#: (:data:`~place_safe.calibration.forward_fit.ZONE_SCALE_TERMS`), the geometry free too. A level table reads the two
#: alike (:data:`NOMINAL_GEOMETRY`); a tilted plane turns the zones' directions and not their time, so tilted frames
#: tell them apart and both can be fitted at once.
SCALES_AND_GEOMETRY_FITTED: dict[str, str] = {**FITTED, **ZONE_SCALE_TERMS}


def scales_and_geometry_fit(frames: Sequence[Frame], progress: bool = False) -> tuple[ForwardParams, dict]:
    """The second fit of :func:`reconsider_geometry` on a capture with tilted frames: :func:`forward_fit.fit_forward`
    from the default start with :data:`SCALES_AND_GEOMETRY_FITTED` (module level: ``calibrate`` may run it alongside
    the first fit)."""
    return forward_fit.fit_forward(frames, init=None, progress=progress, fitted=SCALES_AND_GEOMETRY_FITTED)


def second_fit_for(frames: Sequence[Frame]):
    """The second fit :func:`reconsider_geometry` compares on ``frames``: :func:`nominal_geometry_fit` on a level
    sweep, :func:`scales_and_geometry_fit` on a capture with tilted frames."""
    return nominal_geometry_fit if level_sweep(frames) else scales_and_geometry_fit


def reconsider_geometry(frames: Sequence[Frame], params: ForwardParams, report: dict, progress: bool = True,
                        log=None, second_fit: bool = True, second=None, unlabelled: Sequence[Frame] = (),
                        peak=None) -> tuple[ForwardParams, dict]:
    """The forward fit to keep after ``params`` (with its ``report``) from :func:`forward_fit.fit_forward` on
    ``frames``.

    On a level sweep (whatever geometry its fit set: simulated unit 52, whose zones keep their own time, landed within
    0.5 % and 0.2 deg of the nominal geometry and read tilted planes 0.74 deg off with NEES per dof 9.3, on the
    simulator before 2026-11-30), a second fit
    runs from the default start with :data:`NOMINAL_GEOMETRY` held nominal and each zone's own time scale fitted
    (:data:`NOMINAL_GEOMETRY_FITTED`), from every start of the first (its basin may lie elsewhere: unit 32's first fit
    ended on the measured reference floor, its second on the published one): a level table reads both alike, so the
    zones' directions cannot choose between them. Two things the sweep does show can: how well each explains the counts,
    and whether one table reads one albedo. The second fit is adopted (its params and report are returned) when it
    converged, its RMS scaled residual is at least :data:`NOMINAL_GEOMETRY_GAIN` below the first fit's, and its frames'
    albedos spread at most :data:`NOMINAL_GEOMETRY_ALBEDO_SPREAD` times as much (or :data:`NOMINAL_GEOMETRY_ALBEDO_CV`
    more; both must be known) and at most :data:`SAME_SURFACE_CV` (a sweep of one table reads as one surface); or, on
    the albedo's evidence alone, when its RMS is at least :data:`ALBEDO_CLUE_GAIN` lower and the table reads one albedo
    :data:`ALBEDO_CLUE_FACTOR` times more closely (the albedos the counts determined:
    :func:`forward_fit.albedo_spread`). Either way the returned report's ``geometry`` section says what was compared
    (``free``, ``nominal_time_scales``) and which was kept (``adopted``; ``why``), the reading not kept
    (``other_params``, where that fit converged) and whether the sweep told the two apart (``told_apart``:
    :data:`TOLD_APART_GAIN`). A first fit beyond the note's limits
    (:func:`geometry_note`) that is kept also gets the ``note``, printed by ``calibrate``, which names the comparison or
    the second fit's failure. The first fit's ``report`` gets its ``geometry`` section in place when it is kept.
    ``second_fit`` False: the note alone (a fit whose geometry is not free to swap, e.g. the staged unit model). Not a
    level sweep (tilted frames among them): :func:`_tilted_capture`, the second fit with each zone's own time scale
    and the geometry free together, which tilted frames tell apart. ``log`` gets a line for the user (None: silent).
    ``second``: a callable returning the second fit's ``(params, report)`` (the result of :func:`second_fit_for`'s fit
    run alongside the first fit); None: that fit here, when needed. ``unlabelled``: tilted frames, ground truth not
    needed, that choose between readings the sweep left both possible (:mod:`place_safe.calibration.readings`, with the
    calibrated ``peak`` params to find their tilts); the report's ``geometry.unlabelled`` says what they showed."""
    note = geometry_note(params, frames)
    free = {"edge_fov_scale": params.edge_fov_scale, "corner_fov_scale": params.corner_fov_scale,
            "mount_tilt_deg": [math.degrees(float(t)) for t in params.mount_tilt],
            "rms_scaled_residual": report.get("rms_scaled_residual_after"), "converged": report.get("converged"),
            "albedo_cv": (report.get("one_surface") or {}).get("albedo_cv_after"),
            "frames_left_out": _frames_left_out(report)}
    if not second_fit:
        if note is not None:
            report["geometry"] = {"note": note, "free": free, "adopted": "free"}
        return params, report
    say = log if log is not None else (lambda _line: None)
    if not level_sweep(frames):  # tilted frames tell the readings apart: both fitted at once
        return _tilted_capture(frames, params, report, free, progress, say, second)
    # every level sweep (a first fit near nominal geometry may hide the time scales)

    def keep(nominal: dict, reason: str, other: ForwardParams | None = None,
             told_apart: bool = False) -> tuple[ForwardParams, dict]:
        """The first fit, its report saying why (and, beyond the note's limits, its note naming the comparison); with
        the second fit's params ``other`` where it converged, and whether the sweep ``told_apart`` the readings."""
        report["geometry"] = {"adopted": "free", "free": free, "nominal_time_scales": nominal,
                              "why": f"kept the fitted geometry: {reason}", "told_apart": told_apart}
        if other is not None:
            report["geometry"]["other_params"] = other.to_dict()
        if note is not None:
            report["geometry"]["note"] = (f"{note} (a second fit with the nominal geometry and each zone's own time "
                                          f"scale: kept the fitted geometry: {reason})")
        say(f"forward model: kept the fitted geometry ({reason})")
        return params, report

    say("forward model: a level table cannot tell the zones' directions from each zone's own time scale; comparing a "
        "fit of each zone's own time scale with the geometry held nominal")
    try:
        alt, alt_report = second() if second is not None else nominal_geometry_fit(frames, progress)
    except (ArithmeticError, ValueError) as exc:  # the first fit stands, with its note
        failed = f"{type(exc).__name__}: {exc}"
        return keep({"failed": failed}, f"the second fit failed: {failed}")
    rms, rms_alt, cv, cv_alt, converged, nominal, compared = _compared(report, alt, alt_report)

    def adopt(why: str, shown: str, **extra) -> tuple[ForwardParams, dict]:
        """The second fit, its report saying ``why`` (and ``extra``), the first fit's params kept as the other reading;
        ``shown`` is what the user's line says."""
        alt_report["geometry"] = {"adopted": "nominal_time_scales", "free": free, "nominal_time_scales": nominal,
                                  "why": why, "told_apart": True, "other_params": params.to_dict(), **extra}
        say(f"forward model: adopted the nominal geometry with each zone's own time scale ({shown})")
        return alt, alt_report

    def fell_by(gain: float) -> bool:
        """Whether the second fit converged with an RMS scaled residual at least ``gain`` (a share) below the first's."""
        return converged and math.isfinite(rms_alt) and rms_alt <= (1.0 - gain) * rms

    better_fit = fell_by(NOMINAL_GEOMETRY_GAIN)
    compared_albedo = math.isfinite(cv) and math.isfinite(cv_alt)
    one_surface = compared_albedo and cv_alt <= SAME_SURFACE_CV
    one_albedo = one_surface and cv_alt <= max(NOMINAL_GEOMETRY_ALBEDO_SPREAD * cv, cv + NOMINAL_GEOMETRY_ALBEDO_CV)
    albedo_clue = (fell_by(ALBEDO_CLUE_GAIN) and one_surface
                   and ALBEDO_CLUE_MIN_CV <= cv <= SAME_SURFACE_CV and cv_alt * ALBEDO_CLUE_FACTOR <= cv
                   # (on as many frames: a spread made small by leaving frames out is no evidence)
                   and nominal["frames_left_out"] <= free["frames_left_out"])
    if (better_fit and one_albedo) or albedo_clue:
        why = (f"{compared}: a clearly better fit with the geometry nominal and each zone's own time scale, one table "
               "still reading one albedo" if better_fit and one_albedo else
               f"{compared}: a better fit with the geometry nominal and each zone's own time scale, one table reading "
               f"one albedo {min(cv / max(cv_alt, 1e-12), 100.0):.1f} times more closely")
        return adopt(why, compared)
    why = (f"not a converged fit {NOMINAL_GEOMETRY_GAIN:.1%} lower" if not better_fit else
           "the frames' albedos could not be compared" if not compared_albedo else
           f"the frames do not read as one surface (albedo CV above {SAME_SURFACE_CV:.0%}): their albedos cannot tell "
           "the two readings apart" if not one_surface else
           f"the frames' albedos spread more than {NOMINAL_GEOMETRY_ALBEDO_SPREAD:g} times as much: one table would "
           "read many albedos")
    # the sweep tells the readings apart only where the second fit is clearly worse; a better fit set aside for its
    # albedos, or one about as good, leaves both readings possible (TOLD_APART_GAIN)
    told_apart = converged and math.isfinite(rms_alt) and rms_alt >= (1.0 + TOLD_APART_GAIN) * rms
    if told_apart or not converged or not unlabelled:
        return keep(nominal, f"{compared}; {why}", alt if converged else None, told_apart)
    from place_safe.calibration.readings import compare_readings, decide

    say(f"forward model: the level sweep left two readings of the zones' geometry; fitting {len(unlabelled)} frames "
        "without ground truth with each")
    bar = tqdm(total=len(unlabelled), desc="two readings", unit="frame",
               disable=None if progress else True, file=sys.stderr)
    try:  # (the solver as calibrate will run it on the kept reading: each frame's own crosstalk where the sweep left it)
        comparison = compare_readings(unlabelled, params, alt, peak if peak is not None else PeakParams.default_peak(),
                                      SolverOptions(crosstalk_std=free_crosstalk_std(params, report)),
                                      progress=bar.update)
    finally:
        bar.close()
    choice, shown = decide(comparison)
    if choice == "other" and cv <= SAME_SURFACE_CV and not one_surface:  # the sweep's evidence against it stands
        choice, shown = None, (f"{shown}, but the second reading reads the level table as many albedos (CV "
                               f"{100 * cv_alt:.0f} %, above {SAME_SURFACE_CV:.0%}) where the first reads one surface: "
                               "not adopted")
    seen = {**comparison, "chose": choice or "neither", "why": shown}
    if choice == "other":
        return adopt(f"{compared}; {why}; the tilted frames without ground truth chose each zone's own time scale with "
                     f"the geometry nominal: {shown}", shown, unlabelled=seen)
    params, report = keep(nominal, f"{compared}; {why}" + (
        f"; the tilted frames without ground truth chose it: {shown}" if choice == "kept" else ""), alt,
        choice == "kept")
    report["geometry"]["unlabelled"] = seen
    if choice == "kept":  # the frames told the readings apart: the note's warning about them no longer holds
        report["geometry"].pop("note", None)
    if choice is None:
        say(f"forward model: the frames without ground truth did not choose a reading ({shown})")
    return params, report


#: What a capture with tilted frames must determine for its second fit (:func:`_tilted_capture`) to be adopted: none of
#: these may be in the fit's ``posterior_std.not_determined`` (too few tilted frames leave the scales traded against the
#: geometry as a level table does). Measured (docs/results.md, "A few tilted frames"): 4, 8 and 12 tilted frames on a
#: 150-frame level sweep determined all of them on simulated units 43 and 50.
TILTED_DETERMINES = ("zone_bin_scales", "edge_fov_scale", "corner_fov_scale", "mount_tilt")


def _tilted_capture(frames: Sequence[Frame], params: ForwardParams, report: dict, free: dict, progress: bool, say,
                    second=None) -> tuple[ForwardParams, dict]:
    """:func:`reconsider_geometry` on a capture with tilted frames: the first fit (the geometry free, no zone time
    scales) against :func:`scales_and_geometry_fit` (both free), adopted where it converged with an RMS scaled residual
    at least :data:`NOMINAL_GEOMETRY_GAIN` lower, determined :data:`TILTED_DETERMINES`, and where the frames are of one
    surface by either reading (its albedo CV at most :data:`SAME_SURFACE_CV`) it reads them as one surface, its albedos
    spreading no more than the level sweep's rule allows (:data:`NOMINAL_GEOMETRY_ALBEDO_SPREAD`,
    :data:`NOMINAL_GEOMETRY_ALBEDO_CV`); frames that both readings call many surfaces (the independent generator's)
    cannot witness, and the tilted frames' RMS decides; albedos that cannot be compared (a CV not known) refuse it. (A
    first fit without the time scales can misread one table's albedos by far: unit 39's level sweep with 12 tilted
    frames at a CV of 95 %, 1.1 % with the time scales.) The report's ``geometry`` has ``capture: "tilted"``, what was compared and
    what kept (``adopted``: ``free`` or ``time_scales``, ``why``), the reading set aside (``other_params``) and
    ``told_apart`` where the second fit converged (the tilted frames tell the readings apart; nothing is left for
    diff's covariance to hold)."""
    try:
        alt, alt_report = second() if second is not None else scales_and_geometry_fit(frames, progress)
    except (ArithmeticError, ValueError) as exc:  # the first fit stands
        failed = f"{type(exc).__name__}: {exc}"
        report["geometry"] = {"capture": "tilted", "adopted": "free", "free": free, "time_scales": {"failed": failed},
                              "why": f"kept the fitted geometry: the second fit failed: {failed}", "told_apart": False}
        say(f"forward model: kept the fitted geometry (the fit with each zone's own time scale failed: {failed})")
        return params, report
    rms, rms_alt, cv, cv_alt, converged, scales, compared = _compared(report, alt, alt_report)
    undetermined = sorted(set(TILTED_DETERMINES) & set((alt_report.get("posterior_std") or {}).get("not_determined")
                                                       or ()))
    scales.update({"not_determined": undetermined, "edge_fov_scale": alt.edge_fov_scale,
                   "corner_fov_scale": alt.corner_fov_scale,
                   "mount_tilt_deg": [math.degrees(float(t)) for t in alt.mount_tilt]})
    known = math.isfinite(cv) and math.isfinite(cv_alt)
    # many surfaces where both readings say so (a first fit that misreads one table can spread its albedos too)
    many_surfaces = known and min(cv, cv_alt) > SAME_SURFACE_CV
    why = ("not converged" if not converged else
           "the RMS scaled residuals could not be compared" if not (math.isfinite(rms) and math.isfinite(rms_alt)) else
           f"not {NOMINAL_GEOMETRY_GAIN:.1%} lower" if rms_alt > (1.0 - NOMINAL_GEOMETRY_GAIN) * rms else
           f"the tilted frames do not determine {', '.join(undetermined)}" if undetermined else
           "the frames' albedos could not be compared" if not known else
           None if many_surfaces else
           f"the frames do not read as one surface with it (albedo CV above {SAME_SURFACE_CV:.0%}) where the first "
           "fit reads one" if cv_alt > SAME_SURFACE_CV else
           f"the frames' albedos spread more than {NOMINAL_GEOMETRY_ALBEDO_SPREAD:g} times as much: one surface would "
           "read many albedos"
           if cv_alt > max(NOMINAL_GEOMETRY_ALBEDO_SPREAD * cv, cv + NOMINAL_GEOMETRY_ALBEDO_CV) else None)
    if why is None:
        why = (f"{compared}: tilted frames tell the zones' directions from their time, and each zone's own time scale "
               "fits" + (" (frames of many surfaces: their albedos cannot witness)" if many_surfaces else ""))
        alt_report["geometry"] = {"capture": "tilted", "adopted": "time_scales", "free": free, "time_scales": scales,
                                  "why": why, "told_apart": True, "other_params": params.to_dict()}
        say(f"forward model: adopted each zone's own time scale with the geometry ({compared})")
        return alt, alt_report
    report["geometry"] = {"capture": "tilted", "adopted": "free", "free": free, "time_scales": scales,
                          "why": f"kept the fitted geometry: {compared}; {why}", "told_apart": converged}
    if converged:
        report["geometry"]["other_params"] = alt.to_dict()
    say(f"forward model: kept the fitted geometry ({compared}; {why})")
    return params, report
