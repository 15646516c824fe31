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

Reports go into ``calibration.reports`` as plain JSON values. SI units throughout (see the fits' modules).
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from place_safe.calibration import REQUIRED_SECTIONS, UNIT_MODELS, Calibration
from place_safe.calibration.alongside import Alongside, spare_cores
from place_safe.calibration.forward_fit import fit_forward, fit_forward_staged, free_crosstalk_std
from place_safe.calibration.model_error import select_model_error
from place_safe.calibration.plane_correction import fit_range_correction
from place_safe.calibration.second_fit import reconsider_geometry, second_fit_for
from place_safe.calibration.points import adopt_pileup, fit_peak, fit_proprietary
from place_safe.calibration.uncertainty import update_calibration
from place_safe.io.json_values import jsonable
from place_safe.recovery.differentiable import SolverOptions
from place_safe.recovery.estimator import Reference
from place_safe.sensor.frame import Frame

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
    if method in ("peak", "diff"):
        cal.reports["uncertainty"] = jsonable(update_calibration(cal, frames, method))
        fitted.append("uncertainty")
    _keep_reference(cal, fitted, frames, [m for m in ("peak", "proprietary") if m in fitted] +
                    (["diff"] if method == "diff" else []), say)
    return fitted


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


__all__ = ["fit_method", "frames_reference"]
