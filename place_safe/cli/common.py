"""What every place-safe command shares: the program name, the method names, one-line usage errors,
logging and progress on standard error, and loading calibrations and frame files for a command.

Conventions at this edge: distances on the command line are metres unless an option says otherwise,
angles are printed in degrees; standard output carries only a command's result.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from place_safe.calibration import UNCALIBRATED_MARK  # noqa: F401 - the commands' row marker
from place_safe.exceptions import CalibrationError, FrameError, FrameFileError, PlaceSafeError, UsageError  # noqa: F401
from place_safe.io.json_values import jsonable
from place_safe.recovery import METHODS, make_estimator  # noqa: F401 - the one list of method names, for the commands
from place_safe.io.frame_file import iter_frames
from place_safe.io.input_file import input_file_problem
from place_safe.calibration import (FORMAT, REQUIRED_SECTIONS, Calibration, missing_section, missing_uncertainty,
                                   uncalibrated_reason)

PROG = "place-safe"
CALIBRATE_METHODS = ("diff", "peak", "proprietary")
#: What --robot says of a robot file (URConfig's module docstring has the whole list).
ROBOT_FILE_HELP = ("start from a copy of robots/ur5/real.toml: its [connection], [limits], [gripper] and [tool] "
                   "values are required (one missing is an error naming it); [motion] and [contact] may be left out")


#: What argparse takes for a value, not an option, where it begins with "-": a negative number, a comma list of numbers
#: beginning with one (``--touch -0.45,-0.05``, ``--sim-mount-error -5,0,0,0,2,0``, ``--azimuths -60,300``), a number
#: with an exponent (``--table-height -1e-3``), ``-inf`` and ``-nan`` (which the option's type then refuses by name).
#: argparse's own pattern takes only ``-5`` and ``-0.5``: the rest ended "expected one argument", the capture help's
#: own example among them (round 14). No option of place-safe's begins with "-" and a digit.
NEGATIVE_VALUE = re.compile(r"^-(\d|\.\d)[\d.eE+\-,:_]*$|^-(inf|infinity|nan)$", re.IGNORECASE)


class Parser(argparse.ArgumentParser):
    """argparse with one-line errors (no usage dump) so scripts see exactly one line on stderr, and values that begin
    with "-" read as values where they are numbers (:data:`NEGATIVE_VALUE`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self._negative_number_matcher = NEGATIVE_VALUE

    def error(self, message: str):  # type: ignore[override]
        where = self.prog[len(PROG):].strip() if self.prog.startswith(PROG) else self.prog
        raise UsageError(f"{where + ': ' if where else ''}{message} (see '{self.prog} --help')")


def log(msg: str = "") -> None:
    print(msg, file=sys.stderr, flush=True)


def progress_options(enabled: bool):
    """tqdm keyword arguments: bars on stderr, shown only when enabled and stderr is a terminal."""
    return {"file": sys.stderr, "disable": None if enabled else True, "leave": False}


# ------------------------------------------------------------------------------------------------
# shared helpers
# ------------------------------------------------------------------------------------------------
#: Why ``place --sim`` and ``scenarios`` refuse ``--oracle`` with ``--calibration`` (the calibration was checked, then
#: never read: the oracle's parameters replaced it, even ``--calibration none``, an uncalibrated run asked for).
ORACLE_NOT_A_CALIBRATION = ("--oracle gives the estimator the simulator's true sensor parameters in place of a "
                            "calibration: --calibration does not go with it")


def flags_said(flags: Sequence[str], verb: str, plural: str) -> str:
    """The options ``flags`` given, as the subject of a usage error's verb: ``"--a does"`` or ``"--a and --b do"``
    (``verb`` for one, ``plural`` for more)."""
    return f"{' and '.join(flags)} {verb if len(flags) == 1 else plural}"


def given_twice(paths: list[str]) -> str | None:
    """The second name of a file given twice in ``paths`` (the same file by any path), or None. ``calibrate F F`` fitted
    every frame twice (48 frames for 24, peak's scale 71.94 -> 70.14), and its leave-one-out and fold choices then
    held each frame out beside its own copy (an adversarial round, session 74); ``scenarios S S`` ran S twice and
    counted it twice in the suite's summary (session 82)."""
    seen: set = set()
    for path in paths:
        try:
            st = os.stat(path)
            key = (st.st_dev, st.st_ino)
        except OSError:  # unreadable: the reader says so, with the file's name
            key = os.path.abspath(path)
        if key in seen:
            return path
        seen.add(key)
    return None


def not_a_file(path: str | Path) -> str | None:
    """Why ``path`` cannot be read as an input file ("does not exist", "is a FIFO ...", ...), or None.

    The checks of :func:`place_safe.io.input_file.input_file_problem` (no size limit here: the reader that
    opens the file applies its kind's limit)."""
    return input_file_problem(path, None)


def require_frame_file(path: str | Path) -> None:
    """A one-line :class:`FrameFileError` where ``path`` cannot be read as a frame file (:func:`not_a_file`), or is a
    calibration file (its ``format`` in its first bytes: ``recover cal.json`` said "its first frame spans more than one
    line (a pretty-printed frame?)", session 83)."""
    if (why := not_a_file(path)) is not None:
        raise FrameFileError(f"frame file {path} {why}")
    try:
        with open(path, "rb") as fh:
            head = fh.read(256)
    except OSError:
        return  # (the reader says why)
    if f'"format": "{FORMAT}"'.encode() in head or f'"format":"{FORMAT}"'.encode() in head:
        raise FrameFileError(f"{path} is a calibration file ({FORMAT}), not frames: give it with --calibration")


def refuse_overwrite(path: str | Path, force: bool, option: str = "") -> None:
    """A one-line :class:`UsageError` where ``path`` is a file already there and ``force`` (``--force``) was not given:
    a command that writes a file replaces one only when told to (``sensor record``, ``synth``, ``calibrate --sim
    --save-frames``; ``calibrate`` updates a calibration file and refuses to replace anything else). A device or a pipe
    (``/dev/null``) is written as ever. ``option``: what the message names first (``"calibrate: --save-frames"``)."""
    if not force and os.path.isfile(path):
        raise UsageError(f"{option + ' ' if option else ''}{path} exists; use --force to overwrite it")


def load_calibration(path: str | None):

    if path is None:
        return None
    if (why := not_a_file(path)) is not None:
        raise CalibrationError(f"calibration file {path} {why}")
    return Calibration.load(path)


def load_any_frames(path: str) -> tuple[list, str]:
    """The readable frames of ``path``, with or without ground truth, and a note on those skipped (a frame that does not
    read, e.g. ``"2 unreadable (the first: ...)"``; '' for none); a one-line error where the file is not a frame file,
    or holds no readable frame."""
    require_frame_file(path)
    frames: list = []
    bad: list = []
    for f in iter_frames(path):
        (bad if isinstance(f, FrameError) else frames).append(f)
    note = f"{len(bad)} unreadable (the first: {bad[0]})" if bad else ""
    if not frames:
        raise FrameFileError(f"no readable frames in {path}" + (f": {note}" if note else ""))
    return frames, note


def load_truth_frames(paths: Sequence[str], min_distance: float | None = None,
                       max_distance: float | None = None, valid_only: bool = False) -> tuple[list, str]:
    """All frames with ground truth from ``paths`` (within the distance limits), and a note on the skipped ones.

    Unreadable frames, frames without ground truth or whose ground truth is not a plane, and frames
    outside the limits are skipped and counted; the note is empty when none was. ``valid_only`` (calibrate) skips
    frames whose histograms no estimator reads (:meth:`~place_safe.sensor.frame.Frame.validate`: NaN, negative counts)
    too: they counted towards the frames a fit needs and entered it (evaluate keeps them: they score as failures).
    """
    from collections import Counter

    frames: list = []
    skipped: Counter = Counter()
    for p in paths:
        require_frame_file(p)
        for f in iter_frames(p):
            if isinstance(f, FrameError):
                skipped["unreadable"] += 1
            elif f.truth is None:
                skipped["ground truth not a plane" if f.truth_error else "no ground truth"] += 1
            elif valid_only and not f.is_valid():
                skipped["invalid histograms"] += 1
            elif ((min_distance is not None and f.truth.offset < min_distance)
                  or (max_distance is not None and f.truth.offset > max_distance)):
                skipped["outside the distance limits"] += 1
            else:
                frames.append(f)
    if not frames:
        limits = ""
        if min_distance is not None or max_distance is not None:
            limits = f" between {min_distance or 0:g} m and {max_distance if max_distance is not None else math.inf:g} m"
        raise FrameFileError(f"no frames with ground truth{limits} in {', '.join(paths)} "
                             "(expected 'plane' or 'pose' + 'dist_to_plane' per frame)"
                             + (f"; {count_note(skipped)}" if skipped else ""))
    return frames, count_note(skipped)


def count_note(counts) -> str:
    """``"3 skipped: 2 unreadable, 1 no ground truth"`` for a Counter of reasons ('' when empty)."""
    total = sum(counts.values())
    if not total:
        return ""
    return f"{total} skipped: " + ", ".join(f"{n} {why}" for why, n in counts.most_common())


def report_items(report: dict, prefix: str = ""):
    """The entries of a (nested) report that are not dicts, as ``(dotted key, value)`` in order."""
    for k, v in report.items():
        if isinstance(v, dict):
            yield from report_items(v, f"{prefix}{k}.")
        else:
            yield f"{prefix}{k}", v


def summarise(report: Any, indent: str = "  ") -> list[str]:
    """Scalar entries of a fit report, one per line (nested dicts flattened with dots)."""
    rep = jsonable(report)
    if not isinstance(rep, dict):
        return [f"{indent}{rep}"]
    lines: list[str] = []
    rep = {k: v for k, v in rep.items() if k != "params"}  # the parameters themselves are in the file
    for key, v in report_items(rep):
        if isinstance(v, list):
            if len(v) <= 16 and all(isinstance(x, (int, float)) or x is None for x in v):
                lines.append(f"{indent}{key}: [{', '.join('-' if x is None else f'{x:.4g}' for x in v)}]")
            elif len(v) <= 32 and all(isinstance(x, str) for x in v):  # names (e.g. the terms not determined)
                lines.append(f"{indent}{key}: {', '.join(v)}")
            else:
                lines.append(f"{indent}{key}: list of {len(v)}")
        elif isinstance(v, float):
            lines.append(f"{indent}{key}: {v:.6g}")
        else:
            lines.append(f"{indent}{key}: {v}")
    return lines


def _g(value: Any) -> str:
    """A report's number in three figures (``-`` where it is not one)."""
    return f"{value:.3g}" if isinstance(value, (int, float)) and not isinstance(value, bool) else "-"


#: The before/after errors :func:`fit_summary` gives of a mapping's fit (peak, proprietary): (label, key, unit).
SUMMARY_ERRORS = (("angular", "angular_mean_deg", "deg"), ("linear", "linear_mean_mm", "mm"),
                  ("point", "point_mean_mm", "mm"))


def fit_summary(report: Any) -> str:
    """One line of a section's fit report, what ``calibrate`` prints by default (``--report``: :func:`summarise`'s
    whole listing, which the file's ``reports`` keeps either way): the frames fitted and what says whether the fit
    helped -- the mean errors on them before and after (peak, proprietary), the forward model's RMS scaled residual and
    whether it converged, the corrections kept (diff), each method's NEES per degree of freedom (uncertainty)."""
    rep = jsonable(report)
    if not isinstance(rep, dict):
        return "fitted"
    parts = [f"{rep['frames']} frames"] if isinstance(rep.get("frames"), int) else []
    before, after = rep.get("before"), rep.get("after")
    if isinstance(before, dict) and isinstance(after, dict):
        parts.append("mean errors on them before -> after the fit: " + ", ".join(
            f"{label} {_g(before.get(key))} -> {_g(after.get(key))} {unit}" for label, key, unit in SUMMARY_ERRORS))
    if "rms_scaled_residual_after" in rep:
        parts.append(f"RMS scaled residual {_g(rep.get('rms_scaled_residual_before'))} -> "
                     f"{_g(rep['rms_scaled_residual_after'])}")
    if "converged" in rep:
        why = str(rep.get("why") or "")
        parts.append(why if rep["converged"] is True and why.startswith("converged") else
                     "converged" if rep["converged"] is True else f"NOT converged ({why or 'no reason given'})")
    if isinstance(rep.get("kept"), list):
        parts.append("kept: " + (", ".join(map(str, rep["kept"])) or "nothing (no correction helped held out)"))
    for method, entry in rep.items():  # (uncertainty: an entry per method)
        if isinstance(entry, dict) and "nees_per_dof_after" in entry:
            parts.append(f"{method}: NEES per dof {_g(entry.get('nees_per_dof_before'))} -> "
                         f"{_g(entry['nees_per_dof_after'])}"
                         + (f" on {entry['frames']} frames" if isinstance(entry.get("frames"), int) else ""))
    return "; ".join(parts) or "fitted"


def report_notes(report: Any, where: str = "") -> list[tuple[str, str]]:
    """Every ``note`` in a calibration report (nested dicts), with the dotted place of the report that holds it
    (``where`` first): ``(place, text)``."""
    if not isinstance(report, dict):
        return []
    return [(key.removesuffix(".note") if key != "note" else "", str(v))
            for key, v in report_items(report, f"{where}." if where else "") if key.split(".")[-1] == "note"]



def uncalibrated_note(methods: str | Sequence[str], calibration, path: str | None = None,
                      advice: str | None = None) -> str | None:
    """The first line of a command's output when a method of ``methods`` runs without its calibration, or None.

    Without a calibration each method runs on built-in constants (another unit's published parameters):
    the peak method reads a level table 200 mm away as tilted by about 11 degrees. Commands print this
    line first on standard output (never on standard error, which stays one line for errors) and mark
    every row with :data:`UNCALIBRATED_MARK` or ``"calibrated": false``. ``advice``: the line's last sentence in place
    of how to fit and pass a calibration (a command without a ``--calibration`` option says what it does instead)."""

    names = [methods] if isinstance(methods, str) else list(methods)
    bare = [m for m in names if uncalibrated_reason(m, calibration) is not None]
    if not bare:
        return None
    naive = [m for m in bare if m not in REQUIRED_SECTIONS]
    fitted = [m for m in bare if m in REQUIRED_SECTIONS]
    why = []
    if fitted:
        where = ("no --calibration" if calibration is None else
                 f"{path or 'the calibration'} has no "
                 f"{'/'.join(dict.fromkeys(missing_section(m, calibration) for m in fitted))} section")
        why.append(f"{where}: {', '.join(fitted)} run{'s' if len(fitted) == 1 else ''} on built-in constants "
                   "(another unit's published parameters)")
    if naive:
        why.append(f"{', '.join(naive)} {'is a naive baseline' if len(naive) == 1 else 'are naive baselines'} "
                   "on built-in constants")
    fit = (fitted or [m.removesuffix("-naive") for m in naive])[0]
    if advice is None and fitted:
        advice = (f"Fit one with 'place-safe calibrate FRAMES.json --method {fit} -o cal.json' and pass --calibration "
                  "cal.json")
    elif advice is None:  # baselines only: a calibration would change nothing (evaluate --calibration C advised one)
        plain = ", ".join(dict.fromkeys(m.removesuffix("-naive") for m in naive))
        advice = (("They use no calibration (baselines" if len(naive) > 1 else "It uses no calibration (a baseline")
                  + f" to compare with); for calibrated planes use {plain} with --calibration")
    return f"UNCALIBRATED: {'; '.join(why)}; planes can be off by degrees. {advice}"


def uncertainty_note(methods: str | Sequence[str], calibration, path: str | None = None) -> str | None:
    """A note (``note: ...``, one line) when a calibrated method of ``methods`` reads ``uncertainty`` entries the
    calibration lacks (:func:`~place_safe.calibration.missing_uncertainty`), else None.

    Its planes are calibrated (no :func:`uncalibrated_note`, rows unmarked), but their covariances are the fits' alone,
    with no model-error floor, and diff never falls back to peak: the planes' stated precision is not the sensor's. A
    placement refuses such a file (:func:`~place_safe.calibration.placement_reason`); ``recover``, ``evaluate`` and
    ``stream`` run and say so on standard error. Every file ``calibrate`` writes has the entries."""
    names = [methods] if isinstance(methods, str) else list(methods)
    if calibration is None:
        return None
    lacking = {m: missing_uncertainty(m, calibration) for m in dict.fromkeys(names)
               if uncalibrated_reason(m, calibration) is None}
    lacking = {m: entries for m, entries in lacking.items() if entries}
    if not lacking:
        return None
    entries = list(dict.fromkeys(e for es in lacking.values() for e in es))
    which = ", ".join(lacking)
    return (f"note: {path or 'the calibration'} has no {' or '.join(repr(e) for e in entries)} entr"
            f"{'y' if len(entries) == 1 else 'ies'}, so {which}'s covariances are the fit's alone (no model-error "
            f"floor){' and diff never falls back to peak' if 'diff' in lacking else ''}; a placement refuses this "
            f"file. Calibrate again: place-safe calibrate FRAMES.json --method {next(iter(lacking))} -o cal.json")


def evaluated_methods(given: Sequence[str] | None, calibration,
                      path: str | None = None) -> tuple[list[str], str | None]:
    """The methods ``evaluate`` runs, each once in the order given, and a one-line note on those it left out (or None).

    ``given``: the methods named with ``--methods`` (None: the default, every method of :data:`METHODS`). By default a
    calibration's methods are evaluated: a fitted method whose section the file lacks (``calibrate --method diff`` or
    ``peak`` fit no proprietary section) would run on built-in constants, proprietary's row the same as
    proprietary-naive's, so it is left out and the note says how to fit it or see it anyway. The naive baselines stay
    (no calibration is theirs), and so does every method without a calibration, or when the file calibrates none of
    them (the UNCALIBRATED note says so). Named methods always run."""
    if given is not None:
        return list(dict.fromkeys(given)), None
    fitted = [m for m in METHODS if m in REQUIRED_SECTIONS]
    bare = [m for m in fitted if uncalibrated_reason(m, calibration) is not None]
    if calibration is None or not bare or len(bare) == len(fitted):
        return list(METHODS), None
    where = path or "the calibration"
    sections = " or ".join(dict.fromkeys(missing_section(m, calibration) for m in bare))
    one = len(bare) == 1
    it = "it" if one else "them"
    again = "".join(f" and again with --method {m}" for m in bare[1:])
    note = (f"note: {', '.join(bare)} left out of the default methods: {where} has no {sections} section, so "
            f"{'it' if one else 'they'} would run on built-in constants (another unit's published parameters); fit "
            f"{it} into the file with 'place-safe calibrate FRAMES.json --method {bare[0]} -o {where}'{again}, or name "
            f"{it} with --methods to see {it} uncalibrated")
    return [m for m in METHODS if m not in bare], note


def estimator_for(method: str, calibration, mode: str | None = None):
    if mode is not None and method != "diff":  # (the other methods have one solver: the option was never read)
        raise UsageError(f"--mode is the diff method's solver; it goes with --method diff, not {method}")
    options = {"mode": mode} if mode else {}
    return make_estimator(method, calibration, **options)


#: Help formatter of every command (keeps the line breaks of descriptions and epilogs).
FMT = argparse.RawDescriptionHelpFormatter
