"""Fit one method family's sections of a calibration to frames with ground truth: what ``place-safe calibrate``
runs, as a library function (the simulated user calibration calls it too).

``fit_method(calibration, frames, method)`` updates ``calibration`` in place and returns the names of the
sections it wrote, in order:

* ``peak``: ``peak`` (the histogram-peak mapping, pile-up and near-range table), then ``uncertainty``;
* ``proprietary``: ``proprietary`` (the on-sensor distances);
* ``diff``: ``peak`` first when the calibration has none (the diff method starts from calibrated peak), then
  ``forward`` (the forward model's parameters and residual weighting), ``diff`` (a z0 correction) and
  ``uncertainty``. ``unit_model`` chooses the forward model's fit (:data:`~place_safe.calibration.UNIT_MODELS`):
  ``default`` (:func:`~place_safe.calibration.forward_fit.fit_forward` with its default terms; on a level sweep, also
  with the geometry nominal and each zone's own time scale, kept when it fits clearly better and the table still reads
  one albedo, or fits better and reads it much more closely; on a capture with tilted frames, also with each zone's own
  time scale and the geometry free, kept when it fits clearly better, determines both and (frames of one surface)
  still reads one albedo:
  :func:`~place_safe.calibration.second_fit.reconsider_geometry`; that second fit starts at once beside the first when
  a core is spare, :class:`~place_safe.calibration.alongside.Alongside`) or ``staged`` (the
  learned unit model in three fits, :func:`~place_safe.calibration.forward_fit.fit_forward_staged`); the rest of
  the chain is the same, with the diff solver comparing the staged model with the counts above the arriving ambient
  (the ``diff`` section's ``ambient``). Where the forward fit's frames (a level sweep) left its crosstalk undetermined,
  the diff solver solves each frame's own under a prior about it (the ``diff`` section's ``crosstalk_std``,
  :func:`~place_safe.calibration.forward_fit.free_crosstalk_std`).

Every method also writes its entries of ``reference`` (those of the methods it fitted: diff's, and peak's when it fitted
peak) when the frames' ground truth states how far it may be off (a capture's touched plane, or a table stated level
within some angle: :func:`frames_reference`), and drops them when the frames state none.

Each frame once: a frame that repeats another exactly (:func:`~place_safe.sensor.frame.repeated_frames`; frames pasted
or files joined, a noise-free synthetic frame drawn twice) is one measurement: the repeats are left out, with a note,
before the frames are counted (counted twice, a copy passed the count and was held out beside itself).

How many frames: at least :data:`~place_safe.calibration.points.MIN_CALIBRATION_FRAMES` (5) with ground truth at
:data:`~place_safe.calibration.points.MIN_CALIBRATION_RANGE` or farther, at
:data:`~place_safe.calibration.points.MIN_CALIBRATION_DISTANCES` (3) or more distances; fewer raise a one-line
:class:`~place_safe.exceptions.CalibrationError` before any fit. Why an error there and not wider covariances: the peak
and on-sensor mappings fit about 24 parameters to 9 readings a frame, so 3-4 frames leave almost nothing over and the
fit reads its own frames to micrometres; their covariances, fitted on those frames, were 20-130 times too small on the
rest of the real sweep, and no factor on an error fitted away recovers it. From 5 to
:data:`~place_safe.calibration.points.FEW_CALIBRATION_FRAMES` (10) frames the calibration goes on (the project's own
smallest ones: 6 synthetic frames in its command-line tests, 8 simulated ones for ``calibrate --sim``) but says so (a
report ``note``, which ``calibrate`` prints even with -q) and widens what the mapping's in-sample errors state by the
small-sample factor ``(n + p) / (n - p)`` (:func:`~place_safe.calibration.points.small_sample_factor`): peak's covariance
scale, the on-sensor distances' zone residuals. Diff's own entry is cross-validated in part (its fallback limits) and
fitted on the frames diff's global forward model reads; it is not widened, but the note is given.

Reports go into ``calibration.reports`` as plain JSON values. SI units throughout (see the fits' modules).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from place_safe.calibration import REQUIRED_SECTIONS, UNIT_MODELS, Calibration
from place_safe.calibration.alongside import Alongside, spare_cores
from place_safe.calibration.points import (FEW_CALIBRATION_FRAMES, MIN_CALIBRATION_DISTANCES, MIN_CALIBRATION_FRAMES,
                                           MIN_CALIBRATION_RANGE, adopt_pileup, fit_peak, fit_proprietary,
                                           small_sample_factor)
from place_safe.exceptions import CalibrationError
from place_safe.recovery.points import MIN_DOMAIN_WIDTH
from place_safe.calibration.uncertainty import update_calibration
from place_safe.io.json_values import jsonable
from place_safe.recovery.diff_settings import SolverOptions
from place_safe.recovery.estimator import Reference
from place_safe.sensor.frame import Frame, without_repeats

def _store(cal: Calibration, fitted: list[str], name: str, section: dict, report: dict) -> None:
    """Put a freshly fitted section and its report into ``cal`` (clearing an earlier load error of that
    section) and note it in ``fitted``."""
    cal.errors.pop(name, None)
    cal.sections[name] = section
    cal.reports[name] = jsonable(report)
    fitted.append(name)


def unlabelled_summary(report: dict, n: int) -> dict:
    """What ``n`` frames without ground truth did in the forward fit whose ``report`` this is (``reports.forward.
    unlabelled``): ``used`` where they were compared (``geometry.unlabelled`` has the comparison, whose choice and reason
    are repeated), else why not."""
    geometry = report.get("geometry") if isinstance(report.get("geometry"), dict) else {}
    seen = geometry.get("unlabelled")
    if isinstance(seen, dict):
        return {"frames": n, "used": True, "chose": seen.get("chose"), "why": seen.get("why")}
    nominal = geometry.get("nominal_time_scales") if isinstance(geometry.get("nominal_time_scales"), dict) else {}
    why = ("the capture has tilted frames with ground truth: they, not frames without it, choose each zone's time "
           "scale and the geometry" if geometry.get("capture") == "tilted" else
           "the level sweep told its two readings apart" if geometry.get("told_apart") else
           f"the second reading's fit failed ({nominal['failed']})" if "failed" in nominal else
           "the second reading's fit did not converge" if nominal else
           "the frames are not a level sweep: they left one reading of the zones' geometry")
    return {"frames": n, "used": False, "why": why}


def fit_method(calibration: Calibration, frames: Sequence[Frame], method: str, progress: bool = False,
               log: Callable[[str], None] | None = None, unit_model: str = "default",
               unlabelled: Sequence[Frame] = ()) -> list[str]:
    """Fit ``method``'s sections of ``calibration`` (in place) to ``frames`` with ground truth; the sections
    written, in order. ``log`` gets one line per step worth telling a user (None: silent). ``unit_model``: the
    forward model's fit for ``diff`` (see the module). ``unlabelled``: for ``diff``, tilted frames (ground truth not
    needed) that choose between the two readings a level sweep may leave (:mod:`place_safe.calibration.readings`)."""
    if method not in REQUIRED_SECTIONS:  # the method families that have a calibration
        raise ValueError(f"calibrate: method must be one of {', '.join(REQUIRED_SECTIONS)}, got {method!r}")
    if unit_model not in UNIT_MODELS:
        raise ValueError(f"calibrate: unit model must be one of {', '.join(UNIT_MODELS)}, got {unit_model!r}")
    if unit_model != "default" and method != "diff":
        raise ValueError(f"calibrate: a unit model is a fit of the diff method's forward model, not of {method}")
    if len(unlabelled) and (method != "diff" or unit_model != "default"):
        raise ValueError("calibrate: frames that choose a reading of the diff method's forward model go with diff and "
                         f"the default unit model, not {method} / {unit_model}")
    say = log if log is not None else (lambda _line: None)
    frames, repeats, _ = without_repeats(frames, "counting the frames with ground truth from 0")
    if repeats is not None:  # a copy passed the count below and was held out beside itself
        say(f"calibrate {method}: {repeats}")
    count, distances = calibration_frames(frames)
    if count < MIN_CALIBRATION_FRAMES or distances < MIN_CALIBRATION_DISTANCES:
        raise CalibrationError(
            f"calibrate {method}: {count} frame{'' if count == 1 else 's'} with ground truth at "
            f"{MIN_CALIBRATION_RANGE * 1e3:.0f} mm or farther, at {distances} distinct distance"
            f"{'' if distances == 1 else 's'}; a calibration needs {MIN_CALIBRATION_FRAMES} or more frames at "
            f"{MIN_CALIBRATION_DISTANCES} or more distances {MIN_DOMAIN_WIDTH * 1e3:g} mm apart "
            f"({FEW_CALIBRATION_FRAMES} or more frames recommended, e.g. a level sweep from 3 to 40 cm)")
    cal = calibration
    fitted: list[str] = []
    if method in ("peak", "diff") and (method == "peak" or "peak" not in cal.sections):
        if method == "diff":
            say("the diff method starts from the calibrated peak method: fitting the 'peak' section first")
        params, report = fit_peak(frames, progress=progress)
        _store(cal, fitted, "peak", params.to_dict(), report)
    if method == "proprietary":
        params, report = fit_proprietary(frames, progress=progress)
        _store(cal, fitted, "proprietary", params.to_dict(), report)
    if method == "diff":
        # (the forward model's fits are torch's: imported here, so `calibrate --method peak` and `proprietary` never
        # load it, a second and a few hundred megabytes they do not use)
        from place_safe.calibration.forward_fit import fit_forward, fit_forward_staged, free_crosstalk_std
        from place_safe.calibration.model_error import select_model_error
        from place_safe.calibration.plane_correction import fit_range_correction
        from place_safe.calibration.second_fit import reconsider_geometry, second_fit_for

        if unit_model == "staged":  # (its geometry is set by its first stage: a far one gets the note alone)
            params, report = reconsider_geometry(frames, *fit_forward_staged(frames, progress=progress, log=log),
                                                 second_fit=False)
        else:  # a second fit with each zone's own time scale (on a level sweep with the geometry nominal, with tilted
            # frames with the geometry free): it starts beside the first on a spare core
            parallel = spare_cores() > 0
            with Alongside(second_fit_for(frames), frames, progress and not parallel, parallel=parallel) as second:
                params, report = reconsider_geometry(frames, *fit_forward(frames, init=None, progress=progress),
                                                     progress=progress, log=log, second=second.result,
                                                     unlabelled=unlabelled, peak=cal.peak())
        if len(unlabelled):
            report["unlabelled"] = unlabelled_summary(report, len(unlabelled))
            if not report["unlabelled"]["used"]:
                say(f"forward model: the {len(unlabelled)} frames without ground truth were not needed: "
                    f"{report['unlabelled']['why']}")
        # the solver compares the model with the data as it was fitted (the staged model: above the arriving ambient);
        # where a level sweep left the crosstalk undetermined, each frame solves its own under a prior about the fit's
        options = SolverOptions(ambient=unit_model == "staged", crosstalk_std=free_crosstalk_std(params, report))
        if options.crosstalk_std > 0.0:
            say(f"diff: each frame solves its own crosstalk between zones (prior std {options.crosstalk_std:.4f} about "
                f"the fit's {params.crosstalk:.4f}): a level sweep does not tell it from the zones' fields of view")
        if "peak" in fitted:  # the forward fit sees pile-up in the histograms' shapes: the peak method undoes it
            peak, peak_report, adopted = adopt_pileup(frames, cal.peak(), cal.reports["peak"], params.pileup)
            cal.reports["peak"] = jsonable(peak_report)
            if adopted:
                cal.sections["peak"] = peak.to_dict()
                say(f"peak: undoing the forward fit's SPAD pile-up ({params.pileup:.3g} per count)")

        params.model_error, report["model_error"] = select_model_error(frames, params, cal.peak(), progress=progress,
                                                                       options=options)
        _store(cal, fitted, "forward", params.to_dict(), report)

        section, report = fit_range_correction(frames, params, cal.peak(), progress=progress, options=options)
        section = {**section, "window_after_peak": options.window_after_peak}
        report["crosstalk_std"] = options.crosstalk_std
        if options.crosstalk_std > 0.0:  # (absent: 0, the crosstalk held, as files without the key were made)
            section["crosstalk_std"] = options.crosstalk_std
        if options.ambient:  # (absent: false, as files without the key were made)
            section["ambient"] = True
        _store(cal, fitted, "diff", section, report)
    widen = small_sample_factor(cal.reports["peak"]) if "peak" in fitted else 1.0
    if method in ("peak", "diff"):
        cal.reports["uncertainty"] = jsonable(update_calibration(cal, frames, method, widen_peak=widen))
        cal.errors.pop("uncertainty", None)  # (entries rewritten; _check_fitted reads the section again)
        fitted.append("uncertainty")
    fitted_frames = [int((cal.reports.get(name) or {}).get("frames", count)) for name in ("peak", "proprietary")
                     if name in fitted and isinstance(cal.reports.get(name), dict)]
    if min([count] + fitted_frames) < FEW_CALIBRATION_FRAMES:  # (as the widening counts: the frames a mapping kept)
        _small_sample_note(cal, fitted, method)
    _check_fitted(cal, fitted, method)
    _keep_reference(cal, fitted, frames, [m for m in ("peak", "proprietary") if m in fitted] +
                    (["diff"] if method == "diff" else []), say)
    return fitted


def _check_fitted(cal: Calibration, fitted: list[str], method: str) -> None:
    """Raise a one-line :class:`CalibrationError` where a section just fitted would not load (a file ``calibrate``
    writes is one every command reads): e.g. an ``uncertainty`` entry without a floor, which the floor's fit leaves
    when fewer than 3 frames lie beyond the near-range table (:func:`~place_safe.calibration.uncertainty.fit_floor`)."""
    again = Calibration.from_dict(cal.to_dict(), "the fitted calibration")
    for name in fitted:
        if name not in again.errors:
            continue
        for entry, rep in ((cal.reports.get("uncertainty") or {}).items() if name == "uncertainty" else ()):
            if isinstance(rep, dict) and rep.get("why"):
                beyond = rep.get("min_range_m")
                raise CalibrationError(
                    f"calibrate {method}: {entry}'s model error could not be fitted: {rep['why']} (of frames at "
                    f"{beyond * 1e3:.0f} mm or farther, beyond the near-range table); add frames farther out"
                    if isinstance(beyond, (int, float)) else
                    f"calibrate {method}: {entry}'s model error could not be fitted: {rep['why']}; add frames")
        kept = " (an entry this fit does not replace: fix or remove it)" if name == "uncertainty" else ""
        raise CalibrationError(f"calibrate {method}: the fitted section '{name}' would not load: {again.errors[name]}"
                               f"{kept}")


def calibration_frames(frames: Sequence[Frame]) -> tuple[int, int]:
    """(frames, distinct distances) of ``frames`` a calibration can use: those with ground truth at
    :data:`~place_safe.calibration.points.MIN_CALIBRATION_RANGE` or farther along the optical axis, and how many of
    their axis distances lie :data:`~place_safe.recovery.points.MIN_DOMAIN_WIDTH` or more beyond the last counted."""
    z = sorted(float(f.truth.z0) for f in frames if f.truth is not None and f.truth.z0 >= MIN_CALIBRATION_RANGE)
    distances, last = 0, -math.inf
    for v in z:
        if v - last >= MIN_DOMAIN_WIDTH:
            distances, last = distances + 1, v
    return len(z), distances


def _small_sample_note(cal: Calibration, fitted: list[str], method: str) -> None:
    """Put the small-calibration warning (fewer than :data:`~place_safe.calibration.points.FEW_CALIBRATION_FRAMES`)
    into the report of each section fitted now that states how far to trust it (``calibrate`` prints report notes even
    with -q): the mappings (``peak``, ``proprietary``) with what was widened, else diff's ``forward``."""
    for name in ("peak", "proprietary", "forward"):
        rep = cal.reports.get(name) if name in fitted else None
        if not isinstance(rep, dict) or (name == "forward" and {"peak", "proprietary"} & set(fitted)):
            continue
        frames = rep.get("frames")
        if name == "forward":
            text = (f"calibrated on only {frames} frames ({FEW_CALIBRATION_FRAMES} or more recommended): diff's "
                    "forward model and floor are fitted on these frames and read them better than new ones (not "
                    "widened)")
        else:
            small = ((cal.reports.get("uncertainty") or {}).get("peak") if name == "peak" else rep) or {}
            factor = (small.get("small_sample") or {}).get("factor", 1.0)
            n, p = rep.get("readings", 0), rep.get("parameters", 0)
            widened = "peak's covariance scale" if name == "peak" else "its stated zone residuals' variances"
            text = (f"calibrated on only {frames} frames ({FEW_CALIBRATION_FRAMES} or more recommended): the mapping's "
                    f"{p} parameters leave {n - p} of its {n} zone readings over, so it reads these frames better than "
                    f"it will read new ones; {widened} widened by {factor:.2f} (the small-sample factor)"
                    + ("; diff's own floor is fitted on these frames too (not widened)" if method == "diff" else ""))
        rep.setdefault("small_sample", {})["note"] = text + ": capture more frames at more distances and calibrate again"


def _keep_reference(cal: Calibration, fitted: list[str], frames: Sequence[Frame], methods: list[str],
                    say: Callable[[str], None]) -> None:
    """Set the ``reference`` entries of the ``methods`` just fitted to what ``frames`` state (:func:`frames_reference`),
    or drop them when the frames state none (an entry from another capture does not hold for these fits); the other
    methods' entries stay; the section goes when it is left empty."""
    reference = frames_reference(frames)
    section = dict(cal.sections.get("reference") or {}) if "reference" not in cal.errors else {}
    for m in methods:
        section.pop(m, None)
        if reference is not None:
            section[m] = reference.to_dict()
    cal.errors.pop("reference", None)
    if section:
        _store(cal, fitted, "reference", section, {"frames": len(frames), "methods": sorted(section)})
    else:
        cal.sections.pop("reference", None)
        cal.reports.pop("reference", None)
    if reference is not None:
        what = f"a plane touched at {reference.points} points" if reference.points else "a table stated level"
        say(f"reference: the frames' ground truth is {what}, within {math.degrees(reference.tilt_std):.2f} deg "
            f"(1 sigma): every plane {', '.join(methods)} reads shares that error, and fusion adds it once")


def frames_reference(frames: Sequence[Frame]) -> Reference | None:
    """How far the frames' ground truth may be off: the largest ``meta.base_plane.reference`` (a capture's touched
    plane, :func:`~place_safe.calibration.capture.touched_reference`) among them (a resumed capture, or several files,
    may mix frames that state one with frames that do not: the largest holds for all); None when no frame states one.
    A stated one that is not a valid :class:`~place_safe.recovery.estimator.Reference` raises its one-line
    CalibrationError."""
    found: list[Reference] = []
    for f in frames:
        meta = (getattr(f, "extra", None) or {}).get("meta")
        base = meta.get("base_plane") if isinstance(meta, dict) else None
        if isinstance(base, dict) and base.get("reference") is not None:
            found.append(Reference.from_dict(base["reference"], "frame meta.base_plane.reference"))
    return max(found, key=lambda r: r.tilt_std) if found else None


__all__ = ["calibration_frames", "fit_method", "frames_reference"]
