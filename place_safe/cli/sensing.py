"""The commands on recorded frames: ``calibrate``, ``recover``, ``evaluate``, ``stream`` and ``bench recovery``
(docs/interfaces.md keeps their faces stable)."""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

try:
    import orjson as _orjson
except ImportError:  # pragma: no cover - a dependency; the standard encoder still writes the same values
    _orjson = None

from place_safe.cli import options
from place_safe.cli.options import opt
from place_safe.exceptions import CalibrationError, FrameError, FrameFileError, PlaceSafeError
from place_safe.cli.common import (CALIBRATE_METHODS, METHODS, PROG, UsageError, estimator_for, given_twice,
                                   jsonable, load_any_frames, load_calibration, load_truth_frames, log, progress_options,
                                   refuse_overwrite, report_notes, require_frame_file, summarise, not_a_file,
                                   uncalibrated_note, uncertainty_note, evaluated_methods, fit_summary, flags_said)
from place_safe.evaluation.bench import (DEFAULT_RUNS, MEMORY_METHOD, PAPER_FRAMES, measure_file_rss, report_json,
                                         run_bench)
from place_safe.evaluation.evaluate import evaluate
from place_safe.io.frame_file import iter_frames
from place_safe.io.input_file import output_dir_problem
from place_safe.io.live import run_live
from place_safe.io.replay import FileReplaySource
from place_safe.recovery.estimator import PlaneEstimate
from place_safe.calibration import REQUIRED_SECTIONS, UNIT_MODELS, Calibration, mark, uncalibrated_reason

# ------------------------------------------------------------------------------------------------
# calibrate
# ------------------------------------------------------------------------------------------------
def cmd_calibrate(args: argparse.Namespace) -> int:
    """Fit a method family to frame files (``calibrate FILE... --method M -o CAL``), or with ``--sim SENSOR`` run
    the whole user chain in MuJoCo (touch the table, capture a sweep, fit diff then proprietary)."""

    if args.report and args.quiet:
        raise UsageError("calibrate: --report prints the whole fit report, -q none of it: give one of them")
    if args.sim:
        return _calibrate_sim(args)
    extra = [name for name, given in (("--frames", args.frames is not None), ("--seed", args.seed is not None),
                                      ("--save-frames", args.save_frames)) if given]
    if args.readings_from is not None and (args.method not in (None, "diff") or args.unit_model == "staged"):
        raise UsageError("calibrate: --readings-from chooses between two readings of the diff method's default forward "
                         "model; it goes with --method diff (not --unit-model staged)")
    if args.unit_model is not None and args.method not in (None, "diff"):
        raise UsageError(f"calibrate: --unit-model is the diff method's forward model; it goes with --method diff, "
                         f"not {args.method}")
    if extra:
        raise UsageError(f"calibrate: {', '.join(extra)} go{'es' if len(extra) == 1 else ''} with --sim SENSOR")
    missing = [name for name, value in (("FILE", args.files), ("--method", args.method), ("-o/--output", args.output))
               if not value]
    if missing:
        raise UsageError(f"calibrate: the following arguments are required: {', '.join(missing)} "
                         f"(see '{PROG} calibrate --help')")
    if (twice := given_twice(args.files)) is not None:  # its frames would count twice, and the folds would hold
        raise UsageError(f"calibrate: {twice} is given twice; each frame file once")  # each frame on both sides
    out = Path(args.output)
    cal, note = Calibration(), None
    if out.exists():  # checked before any work so a bad output path fails fast, with one line
        if (why := not_a_file(out)) is not None:  # a directory, a FIFO, /dev/full: never read or write it
            raise PlaceSafeError(f"calibration output {out} {why}")
        try:
            cal = Calibration.load(out)
            note = f"{out} is a calibration file; keeping its other sections (present: {', '.join(cal.sections) or 'none'})"
            if cal.errors:
                note += f"; invalid there: {', '.join(sorted(cal.errors))} (refit them)"
        except CalibrationError as exc:
            if not args.force:
                raise CalibrationError(f"{exc}; refusing to overwrite it (use --force to replace the file)") from None
            note = f"replacing {out}: {exc}"
    frames, skipped = load_truth_frames(args.files, valid_only=True)
    unlabelled, unreadable = ([], "") if args.readings_from is None else load_any_frames(args.readings_from)
    if not args.quiet:
        log(f"calibrate {args.method}: {len(frames)} frames with ground truth" + (f" ({skipped})" if skipped else ""))
        if args.readings_from is not None:
            log(f"calibrate {args.method}: {len(unlabelled)} frames from {args.readings_from} to choose a reading "
                f"(ground truth not used){f' ({unreadable})' if unreadable else ''}")
        if note:
            log(note)
    from place_safe.calibration.fit import fit_method

    fitted = fit_method(cal, frames, args.method, progress=not args.quiet, log=None if args.quiet else log,
                        unit_model=args.unit_model or "default", unlabelled=unlabelled)
    out.parent.mkdir(parents=True, exist_ok=True)
    cal.save(out)
    for name in fitted if not args.quiet else ():  # -q: the fit reports are in the file (its "reports")
        if args.report:
            log(f"fit quality, section '{name}':")
            for line in summarise(cal.reports.get(name, {})):
                log(line)
        else:  # one line a section (the whole report ran to hundreds of lines for diff)
            log(f"fit quality, section '{name}': {fit_summary(cal.reports.get(name, {}))}")
    for name in fitted:  # what a report asks the user to act on, where the long listing cannot hide it (even -q)
        for where, text in report_notes(cal.reports.get(name, {}), name):
            log(f"note ({where}): {text}")
    for name in sorted(cal.errors):  # kept from the file as it was (even -q): place refuses the whole file for it
        log(f"warning: {out}: section '{name}' kept invalid ({cal.errors[name]}); place and scenarios refuse this "
            f"file until it is refit or removed")
    if not args.quiet:
        log(f"wrote {out} (sections: {', '.join(cal.sections)})"
            + ("" if args.report else "; the whole fit report: --report, or the file's 'reports'"))
    return 0


def _calibrate_sim(args: argparse.Namespace) -> int:
    """``calibrate --sim {nominal,mismatch,all}``: make the simulated user calibration by the chain a user runs on the
    arm, in MuJoCo, into ``-o`` or calibration_SENSOR.json in the current folder (the packaged file placements use is
    rewritten only when named: ``-o sim/sensors/calibration_SENSOR.json``, or run in that folder)."""
    import importlib.util

    if args.files or args.method or args.unit_model is not None or args.readings_from is not None or args.report:
        raise UsageError("calibrate: --sim captures its own frames and fits diff, then proprietary: give no FILE, "
                         "--method, --unit-model, --readings-from or --report with it (its fit report is in the file's "
                         "'reports')")
    sensors = ("nominal", "mismatch") if args.sim == "all" else (args.sim,)
    if len(sensors) > 1 and (args.output or args.save_frames):
        raise UsageError("calibrate: -o and --save-frames need one simulated sensor (--sim nominal or mismatch)")
    if importlib.util.find_spec("mujoco") is None:
        raise UsageError("calibrate --sim: the simulation needs MuJoCo, which is not installed: install the [sim] "
                         "extra, e.g. pip install -e \".[sim]\"")
    from place_safe.sim import calibration_capture
    from place_safe.sim.tof import calibration_name

    outs = [Path(args.output or calibration_name(sensor)) for sensor in sensors]  # not the packaged file unless named
    for out in outs:  # checked before minutes of capture and fit; a calibration there is made anew
        if out.exists():
            if (why := not_a_file(out)) is not None:
                raise PlaceSafeError(f"calibration output {out} {why}")
            try:
                Calibration.load(out)
            except CalibrationError as exc:
                if not args.force:
                    raise CalibrationError(f"{exc}; refusing to overwrite it (use --force to replace the file)") from None
    if args.save_frames:  # (a frame file there was replaced by the capture, the real sweep as soon as any)
        refuse_overwrite(args.save_frames, args.force, "calibrate: --save-frames")
    frames = SIM_SWEEP_FRAMES if args.frames is None else args.frames
    for sensor, out in zip(sensors, outs):
        try:
            out = calibration_capture.calibrate_sim(sensor, out, n=frames, seed=args.seed or 0,
                                                    frames_out=args.save_frames)
        except KeyboardInterrupt:  # what the capture left is the user's to fit or delete: say what it holds
            if args.save_frames and Path(args.save_frames).is_file():
                log(f"calibrate: {_capture_kept(Path(args.save_frames))}; {out} was not written")
            raise
        if not args.quiet:
            log(f"wrote {out} ({sensor} simulated sensor, {frames} sweep frames)")
    return 0


def _capture_kept(path: Path) -> str:
    """What an interrupted ``calibrate --sim --save-frames`` left in ``path``: its whole frames, and how to fit them."""
    try:
        n = sum(1 for f in iter_frames(path) if not isinstance(f, FrameError))
    except FrameFileError:
        return f"interrupted: {path} holds a capture cut short, which no command reads (delete it)"
    return (f"interrupted: {path} keeps the capture's {n} whole frame{'' if n == 1 else 's'} (fit them with "
            f"'place-safe calibrate {path} --method diff', or delete it)")


#: Poses (one frame each) of the simulated sweep of ``calibrate --sim`` unless --frames says otherwise.
SIM_SWEEP_FRAMES = 48


# ------------------------------------------------------------------------------------------------
# recover
# ------------------------------------------------------------------------------------------------
def _warm_up(estimator, path: str) -> None:
    """Recover the file's first usable frame once and drop the result, so the process's first-call costs (imports,
    caches: the peak method's first frame imports scipy's interpolation, ~0.2 s) are not timed as a frame's:
    ``recover``'s ``ms`` of frame 0, ``stream``'s first latency. A file that breaks before a usable frame warms nothing
    (the command's own read says why)."""
    try:
        for f in iter_frames(path, truth=False):
            if not isinstance(f, FrameError):
                estimator.estimate(f)
                return
    except FrameFileError:
        return


def _recover_stream(path: str, estimator, batch: int, unstamped: list[str] | None = None) -> Iterator[tuple[int, Any]]:
    """(index, PlaneEstimate) for every entry of the file, in order, recovering ``batch`` frames at a time.
    ``unstamped`` gets ``"frame N: why"`` for each frame whose timestamp was not used (its plane is recovered)."""
    pending: list[tuple[int, Any]] = []

    def flush() -> Iterator[tuple[int, Any]]:
        frames = [f for _, f in pending if not isinstance(f, FrameError)]
        ests = iter(estimator.estimate_many(frames) if len(frames) > 1 else [estimator.estimate(f) for f in frames])
        for i, f in pending:
            yield i, (PlaneEstimate(None, reason=str(f)) if isinstance(f, FrameError) else next(ests))
        pending.clear()

    try:
        for i, f in enumerate(iter_frames(path, truth=False)):  # recovery never reads the ground truth
            if unstamped is not None and getattr(f, "timestamp_error", None):
                unstamped.append(f"frame {i}: {f.timestamp_error}")
            pending.append((i, f))
            if len(pending) >= batch:
                yield from flush()
    except FrameFileError:
        yield from flush()  # the frames read before the file broke still get their lines
        raise
    yield from flush()


def _fmt_row(i: int, est) -> str:
    import numpy as np

    if est.plane is None:
        return f"{i:>5}  {'-':>9} {'-':>9} {'-':>9}  {'-':>7} {est.seconds * 1e3:>8.2f}  {est.reason}"
    p = est.plane
    alb = "-" if est.albedo is None or not np.isfinite(est.albedo) else f"{est.albedo:.3f}"
    return (f"{i:>5}  {math.degrees(p.theta):>9.3f} {math.degrees(p.phi):>9.2f} {p.offset * 1e3:>9.2f}  "
            f"{alb:>7} {est.seconds * 1e3:>8.2f}")


def _write_line(out: TextIO, obj: dict) -> None:
    """One JSON line, written at once (orjson where it can: a tenth of the standard encoder's time, which
    mattered at the peak method's half a millisecond a frame; the same JSON values, without spaces)."""
    try:
        text = _orjson.dumps(obj).decode() if _orjson is not None else json.dumps(obj)
    except TypeError:  # a value orjson does not encode
        text = json.dumps(obj)
    if not text.isascii():  # the standard encoder's \u escapes: any stdout encoding can carry the line
        text = json.dumps(obj)
    out.write(text + "\n")
    out.flush()


def cmd_recover(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    require_frame_file(args.file)
    cal = load_calibration(args.calibration)
    est = estimator_for(args.method, cal, args.mode)
    note = uncalibrated_note(args.method, cal, args.calibration)
    batch = args.batch or (16 if args.method == "diff" and args.mode != "paper" else 1)
    out = sys.stdout
    # frame 0 is timed like the others (docs/interfaces.md: ms is that frame's recovery time): the first-call costs
    # are paid first, on the first frame; the paper mode's seconds a frame would double, its fast mode loads the same
    _warm_up(est if args.mode != "paper" else estimator_for(args.method, cal, "fast"), args.file)
    if not args.jsonl:
        if note is not None:
            out.write(note + "\n")
        out.write(f"{'frame':>5}  {'theta deg':>9} {'phi deg':>9} {'d mm':>9}  {'albedo':>7} {'ms':>8}  reason\n")
    n = bad = 0
    unstamped: list[str] = []
    bar = tqdm(desc=f"recover {args.method}", unit="frame", **progress_options(not args.quiet))
    for i, e in _recover_stream(args.file, est, max(1, batch), unstamped):
        if args.jsonl:
            line = e.to_json(i)
            if e.plane is None and not line.get("reason"):
                line["reason"] = "no plane"
            line["calibrated"] = note is None
            _write_line(out, line)
        else:
            out.write(mark(_fmt_row(i, e), note is None) + "\n")
        n += 1
        bad += 0 if e.ok else 1
        bar.update(1)
    bar.close()
    out.flush()
    if args.jsonl and note is not None and not args.quiet:  # (after the run: an error stays stderr's one line)
        log(note)  # standard output stays JSON lines, each with "calibrated": false
    if (unsure := uncertainty_note(args.method, cal, args.calibration)) is not None and not args.quiet:
        log(unsure)  # the planes are calibrated (rows unmarked); their stated covariances are not the sensor's
    if unstamped and not args.quiet:
        log(f"note: the timestamp of {len(unstamped)} frame{'s' if len(unstamped) > 1 else ''} was not used (first "
            f"{unstamped[0]}); recovery does not read it")
    if not args.quiet:
        log(f"recovered {n - bad} of {n} frames with {args.method}" + (f" ({bad} without a plane)" if bad else ""))
    return 0


# ------------------------------------------------------------------------------------------------
# evaluate
# ------------------------------------------------------------------------------------------------
def cmd_evaluate(args: argparse.Namespace) -> int:
    if not args.no_plots and (why := output_dir_problem(args.out)) is not None:  # before minutes of recovery
        raise UsageError(f"evaluate: --out {args.out + ' ' if args.out else ''}{why} (a folder for the plots)")
    cal = load_calibration(args.calibration)
    # each method once, in the order given ("peak peak": one row); by default the calibration's methods, the baselines
    given = args.methods
    args.methods, left_out = evaluated_methods(args.methods, cal, args.calibration)
    # the methods left out of the default, each with why (in the --json report too: a script reading it sees them)
    left = {m: uncalibrated_reason(m, cal) for m in METHODS if given is None and m not in args.methods}
    if "diff" not in args.methods and (diff_only := [o for o, v in (("--no-fallback", args.no_fallback),
                                                                    ("--diff-mode", args.diff_mode)) if v]):
        why = (f"which {args.calibration} does not calibrate ({left['diff']})" if "diff" in left else
               f"which is not among the methods evaluated ({', '.join(args.methods)}): name it in --methods")
        raise UsageError(f"evaluate: {flags_said(diff_only, 'applies', 'apply')} to the diff method, {why}")
    if args.min_distance is not None and args.max_distance is not None and args.min_distance > args.max_distance:
        raise UsageError(f"evaluate: --min-distance {args.min_distance:g} m exceeds --max-distance "
                         f"{args.max_distance:g} m")
    frames, skipped = load_truth_frames([args.file], args.min_distance, args.max_distance)
    if not args.quiet:
        log(f"evaluate on {len(frames)} frames" + (f" ({skipped})" if skipped else ""))
    if (note := uncalibrated_note(args.methods, cal, args.calibration)) is not None:
        print(note, flush=True)  # the first line; the table marks each uncalibrated method's row
    if left_out is not None:
        print(left_out, flush=True)  # what the table holds: on standard output with it
    if (unsure := uncertainty_note(args.methods, cal, args.calibration)) is not None and not args.quiet:
        log(unsure)  # the rows are calibrated planes; the NEES column reads the fits' covariances alone
    if cal is not None and not args.quiet and (ref := max((cal.reference(m).tilt_std for m in args.methods
                                                            if m in REQUIRED_SECTIONS), default=0.0)) > 0.0:
        log(f"note: the plane this calibration was captured against may be off by {math.degrees(ref):.2f} deg (its "
            f"reference): errors against frames of that same capture do not show it; placements add it to the tilt")
    if args.no_fallback and "diff" in args.methods:
        cal = (cal if cal is not None else Calibration()).without_fallback()
        print("diff without its fallback: its own plane on every frame it solves (never peak's)", flush=True)
    options = {"diff": {"mode": args.diff_mode}} if args.diff_mode else None
    by_reason = {why: int(n) for n, _, why in  # the skipped frames, in the report too (count_note: "N skipped: k why")
                 (item.partition(" ") for item in skipped.partition(": ")[2].split(", ") if item)}
    report = evaluate(frames, cal, list(args.methods), None if args.no_plots else args.out, not args.quiet,
                      estimator_options=options, skipped=by_reason)
    if report.repeats_note is not None and not args.quiet:  # (the table's last line counts them too)
        log(f"evaluate: {report.repeats_note}")
    print(report.table(), flush=True)
    if getattr(report, "plots", None) and not args.quiet:
        log(f"wrote {len(report.plots)} plot{'s' if len(report.plots) > 1 else ''} to {args.out}: "
            + ", ".join(Path(p).name for p in report.plots))
    if args.json:
        data = report.to_dict() if hasattr(report, "to_dict") else report
        data["left_out"] = left
        Path(args.json).write_text(json.dumps(jsonable(data), indent=2) + "\n")
        log(f"wrote {args.json}")
    return 0


# ------------------------------------------------------------------------------------------------
# stream (live replay)
# ------------------------------------------------------------------------------------------------


def cmd_stream(args: argparse.Namespace) -> int:
    cal = load_calibration(args.calibration)
    est = estimator_for(args.method, cal, args.mode)
    note = uncalibrated_note(args.method, cal, args.calibration)

    def on_estimate(index, frame, e, latency) -> None:
        if args.jsonl:
            line = e.to_json(index)
            line["latency_ms"] = round(latency * 1e3, 3)
            line["calibrated"] = note is None
            _write_line(sys.stdout, line)

    _warm_up(est, args.file)
    with FileReplaySource(args.file, rate_hz=args.rate, loop=args.loop) as src:
        stats = run_live(src, est, on_estimate, max_frames=args.max_frames, queue_size=args.queue)
    summary = stats.summary()
    if note is not None:  # the summary's first line carries the mark
        first, _, rest = summary.partition("\n")
        summary = mark(first, False) + (f"\n{rest}" if rest else "")
    if (unsure := uncertainty_note(args.method, cal, args.calibration)) is not None:
        log(unsure)  # (after the run: an error stays standard error's one line)
    if args.jsonl:  # every record says whether it was calibrated
        log(summary)
    else:  # the summary is the output: the note on a missing calibration is its first line
        print(summary if note is None else f"{note}\n{summary}")
    if args.json:
        Path(args.json).write_text(json.dumps({**stats.to_dict(), "calibrated": note is None}, indent=2) + "\n")
    return 0


# ------------------------------------------------------------------------------------------------
# bench
# ------------------------------------------------------------------------------------------------
# ``bench recovery``'s options only one of its runs reads (None on the command line: not given) are filled with the
# defaults of the functions that read them: ``--memory-method`` (with ``--memory-file``: evaluation.bench's
# MEMORY_METHOD), ``--paper-frames`` (with the diff-paper run: PAPER_FRAMES); and ``--seed`` (of the synthetic frames,
# without a FILE) with this command's own:
#: The seed of ``bench recovery``'s synthetic frames when ``--seed`` is not given (passed to ``make_frames``: its module
#: loads torch, which this module does not).
SYNTHETIC_SEED = 0


def bench_unread_option(args: argparse.Namespace) -> str | None:
    """The usage error of a ``bench recovery`` option that its other options leave unread, or None (each printed the
    table and exited 0)."""
    if args.memory_method is not None and not args.memory_file:
        return "bench recovery: --memory-method is the method of --memory-file's measurement, which was not given"
    if args.paper_frames and "diff-paper" not in args.methods:  # (0, "skip it", says what is so)
        return (f"bench recovery: --paper-frames counts the frames of the diff-paper run, which is not among --methods "
                f"({' '.join(args.methods)})")
    if args.seed is not None and args.file:
        return f"bench recovery: --seed draws the synthetic frames, and {args.file}'s frames are read instead"
    return None


def cmd_bench(args: argparse.Namespace) -> int:
    if (unread := bench_unread_option(args)) is not None:
        raise UsageError(unread)
    args.seed = SYNTHETIC_SEED if args.seed is None else args.seed
    args.paper_frames = PAPER_FRAMES if args.paper_frames is None else args.paper_frames
    cal = load_calibration(args.calibration)
    if args.file:
        frames, _ = load_truth_frames([args.file])
        frames = frames[: args.frames] if args.frames else frames
        source = args.file
    else:
        from place_safe.evaluation.synthetic import make_frames

        n = args.frames or 20
        frames = make_frames(n, seed=args.seed)
        source = f"synthetic (make_frames, seed {args.seed})"
    runs = [r for r in DEFAULT_RUNS if r[0] in args.methods]
    if (note := uncalibrated_note([r[1] for r in runs], cal, args.calibration)) is not None:
        print(note, flush=True)  # the first line; the table marks each uncalibrated run's row
    report = run_bench(frames, cal, paper_frames=args.paper_frames, runs=runs, source=source,
                       progress=not args.quiet)
    status = 0
    if args.memory_file:
        if not args.quiet:
            log(f"measuring peak RSS of recover over a {args.memory_file}-frame file ...")
        try:
            report.file_rss = measure_file_rss(args.memory_file, method=args.memory_method or MEMORY_METHOD,
                                               calibration=args.calibration)
        except RuntimeError as exc:  # the timings above stay valid; say what failed and exit 1
            report.file_rss = {"error": str(exc)}
            status = 1
    print(report.table(), flush=True)
    if args.json:
        report_json(report, args.json)
        log(f"wrote {args.json}")
    if status:
        log(f"{PROG}: memory measurement failed: {report.file_rss['error']}")
    return status


def register(sub) -> None:
    """Add calibrate, recover, evaluate and stream to the ``place-safe`` sub-parsers."""
    c = options.command(
        sub, "calibrate", cmd_calibrate, "fit a method's parameters to frames with ground truth",
        "Fit one method family to frames with ground-truth planes and write its section of a calibration file. If "
        "the output already is a calibration file, its other sections are kept, so one file can carry all methods. "
        "With --sim SENSOR instead of FILE, the user's whole chain runs in MuJoCo (touch the table, capture a sweep, "
        "fit diff then proprietary) and writes a simulated calibration (calibration_SENSOR.json in the current folder "
        "unless -o says where).",
        "methods and the sections they write:\n"
        "  peak         -> 'peak' (histogram-peak distance, zone-angle scales, pile-up and, from\n"
        "                  frames closer than 9 cm, a per-zone near-range table kept only if\n"
        "                  leave-one-out cross-validation says it helps) and 'uncertainty'\n"
        "                  (its covariance floor; closer than 9 cm, the zones' cross-validated\n"
        "                  range errors)\n"
        "  proprietary  -> 'proprietary' (on-sensor distances)\n"
        "  diff         -> 'forward' (forward-model camera parameters and the residual weighting\n"
        "                  that recovers the planes best), 'diff' (a z0 correction, kept only if\n"
        "                  leave-one-out cross-validation says it helps), and 'peak' too when the\n"
        "                  file has none (the diff method starts from calibrated peak; to fit\n"
        "                  'peak' again in an existing file, run --method peak)\n\n"
        "example:\n"
        "  place-safe calibrate sweep.json --method peak -o calib.json\n"
        "  place-safe calibrate sweep.json --method diff -o calib.json   # adds 'forward'\n"
        "  place-safe calibrate sweep.json --method diff --unit-model staged -o calib.json\n"
        "  place-safe calibrate sweep.json --method diff --readings-from ramp.json -o calib.json\n"
        "  place-safe calibrate --sim mismatch      # ./calibration_mismatch.json: the simulated one, anew\n"
        "  cd sim/sensors && place-safe calibrate --sim all   # the packaged simulated calibrations, anew",
        opt("files", nargs="*", metavar="FILE", help="frame files with ground truth ('plane' or 'pose' + 'dist_to_plane')"),
        "method",
        opt("--readings-from", metavar="TILTED", default=None,
            help="with --method diff: a frame file of tilted surfaces (5 deg or more; ground truth not needed, e.g. "
                 "`place-safe sensor record` above a ramp or a book on the table; 20 frames or more) that chooses "
                 "between the two readings of the zones' geometry a level sweep may leave (fields of view and mount, "
                 "or each zone's own time scale, which read tilted planes differently): each frame is fitted with "
                 "both, and the reading that fits three in four of them better is kept, unless the two read them "
                 "alike or the sweep's albedos speak against the second. Used only where the sweep left both; the "
                 "report's forward.unlabelled says whether they were used and what they chose"),
        opt("--unit-model", choices=UNIT_MODELS, default=None,
            help="with --method diff: how the forward model is fitted. default: the published model's camera "
                 "parameters (about 20 terms, one fit; 150 frames: 30-90 s). staged (experimental): a model learned "
                 "for a real unit in three fits, each from the one before: (1) all unit terms (crosstalk by "
                 "neighbour, cover-glass return, echo, each zone's pulse shape, a learned impulse response) with "
                 "the ambient light through the pile-up; (2) each zone's time scale, fields of view and beam held; "
                 "(3) the TDC's time warp, the range law held too. The report gives each stage's RMS scaled "
                 "residual, whether it converged, and why. It takes 4-5 times as long (24 real frames: 2-2.5 min "
                 "of CPU; 150 frames: 4-5 min). It fits the real sweep's histograms better (held out about 1.5 "
                 "against 3.7) but did not make diff's planes better there, and on simulated sensors, whose "
                 "ambient does not pile up like the real one's, it is worse (docs/results.md, the unit model, "
                 "step 6). Default: default"),
        "output", "force",
        opt("--report", action="store_true",
            help="print the whole fit report of each section fitted (default: one line a section; the file's "
                 "'reports' keeps the whole report either way)"),
        "quiet",
        method={"choices": CALIBRATE_METHODS, "default": None, "help": "method family to fit (required with FILE)"},
        output={"metavar": "CALIB.json", "help": "calibration file to write or update (required with FILE; with "
                                                 "--sim: default calibration_SENSOR.json in the current folder, made "
                                                 "anew)"},
        force={"help": "replace an output file that is not a valid calibration (with --sim: and a --save-frames file "
                       "already there)"},
        quiet={"help": "print only errors and the notes that ask you to act (e.g. for tilted poses): no progress "
                       "bars, no fit report (it stays in the file's 'reports'), no closing line"})
    options.add(c.add_argument_group("simulation (the [sim] extra)"),
                opt("--sim", choices=("nominal", "mismatch", "all"),
                    help="instead of FILE: regenerate the simulated user calibration of this simulated sensor the way a "
                       "user calibrates the arm: the simulated UR5 touches the level table at three points, captures a "
                       "sweep above it with the simulated sensor and fits it (diff, then proprietary); without -o it "
                       "writes calibration_SENSOR.json in the current folder (the packaged "
                       "sim/sensors/calibration_SENSOR.json placements use is written only when named with -o)"),
                "frames", "seed",
                opt("--save-frames", help="with --sim: also keep the capture file (JSON Lines) here (one sensor only)"),
                frames={"type": options.int_range(8, 1000), "metavar": None,
                        "help": f"with --sim: poses (one frame each) in the sweep (default {SIM_SWEEP_FRAMES}, 8..1000)"},
                seed={"default": None, "help": "with --sim: sweep and noise seed (default 0)"})

    options.command(
        sub, "recover", cmd_recover, "recover the plane of every frame of a file",
        "Recover one plane per frame, streaming the file (it is never loaded whole). With --jsonl, standard output "
        "carries exactly one JSON object per input frame, in input order, and nothing else:\n"
        '  {"index": 0, "normal": [nx, ny, nz], "offset": d_m, "albedo": a, "ms": t}\n'
        "Frames without a recoverable plane get normal/offset null and a \"reason\".",
        "the human table shows theta (angle of incidence, deg), phi (azimuth, deg) and d (mm).\n\n"
        "example:\n  place-safe recover frames.json --method diff --calibration calib.json --jsonl",
        opt("file", metavar="FILE", help="frame file (JSON list or JSON Lines)"),
        "method", "calibration", "jsonl", "mode", "batch", "quiet",
        method={"required": True, "default": None, "help": "recovery method"},
        jsonl={"help": "one JSON line per frame on stdout (machine-readable)"},
        mode={"help": "diff solver: fast (default) or the paper's Adam, 100 iterations, 2304 rays (~s per frame)"},
        batch={"default": None, "help": "frames recovered together (default 16 for diff fast, else 1); memory "
                                        "stays O(N)"},
        quiet={"help": "no progress bar or summary on stderr"})

    options.command(
        sub, "evaluate", cmd_evaluate, "score methods against ground truth",
        "Recover every frame with ground truth with each method and print angular (deg), linear (mm) and point (mm) "
        "errors as a table; plots go to --out.",
        ["place-safe evaluate sweep.json --calibration calib.json --methods diff peak --max-distance 0.3",
         "place-safe evaluate sweep.json --calibration calib.json --methods diff --no-fallback   # diff's own plane"],
        opt("file", metavar="FILE", help="frame file with ground truth"),
        "calibration",
        opt("--methods", nargs="+", choices=METHODS, default=None, metavar="METHOD",
            help=f"methods to evaluate (default: all of {', '.join(METHODS)}, less those the --calibration file has no "
                 "section for: a line says which and how to fit them)"),
        opt("--out", default="out/evaluate", metavar="DIR", help="directory for plots (default out/evaluate)"),
        opt("--min-distance", type=options.float_range(0.0, 100.0), default=None, metavar="M",
            help="skip frames whose true plane is closer than M metres (perpendicular distance d; synth's distances are z0, "
                 "along the optical axis)"),
        opt("--max-distance", type=options.float_range(0.0, 100.0, lo_open=True), default=None, metavar="M",
            help="skip frames whose true plane is farther than M metres (perpendicular distance d)"),
        opt("--no-plots", action="store_true", help="do not write plots"),
        opt("--no-fallback", action="store_true",
            help="diff's own plane on every frame it solves, never peak's (the calibration's fallback limits lifted: "
                 "how diff's own accuracy is measured)"),
        "mode", "json", "quiet",
        mode={"flags": ("--diff-mode",)}, json={"help": "also write the report as JSON"})

    options.command(
        sub, "stream", cmd_stream, "replay a file as a live sensor and recover frames as they arrive",
        "Replay a frame file at --rate frames per second on the wall clock and recover planes live (a reader thread "
        "and the estimator, with a bounded buffer; frames that arrive while the estimator is busy replace older "
        "waiting ones and count as dropped). Prints a summary: frames dropped, latency from arrival to estimate "
        "(median, p95, max) and throughput.",
        ["place-safe stream frames.json --method diff --rate 30 --jsonl > live.jsonl"],
        opt("file", metavar="FILE", help="frame file to replay"),
        "method", "calibration", "mode",
        opt("--rate", type=options.float_range(1.0, 10000.0), default=30.0, metavar="HZ",
            help="replay rate, frames per second (default 30; 1..10000)"),
        opt("--loop", action="store_true", help="start again at the end of the file (stop with --max-frames); a file "
                 "without one usable frame ends the loop with an error"),
        "max_frames",
        opt("--queue", type=options.int_range(1, 10000), default=1, metavar="N",
            help="frames that may wait for the estimator (default 1: always the newest)"),
        "jsonl", "json",
        max_frames={"help": "stop after N frames arrived"},
        jsonl={"help": "one JSON line per estimated frame on stdout (with latency_ms); summary goes to stderr"},
        json={"help": "write the summary as JSON"})


def add_recovery_bench(sub) -> None:
    """``place-safe bench recovery``: speed and accuracy of the recovery methods on the same frames."""
    options.command(
        sub, "recovery", cmd_bench, "speed and accuracy of diff (paper, fast) and peak",
        "Run diff in paper mode, diff in fast mode and peak on the same frames in one process; print per-frame "
        "latency (median, p95; ms), throughput (frames/s), mean angular (deg), linear (mm) and point (mm) errors, "
        "the paper/fast speed ratio and peak RSS. Warm-up is excluded.",
        ["place-safe bench recovery --frames 20 --paper-frames 3",
         "place-safe bench recovery tests/data/tmf8820_ur5_sweep.json --calibration calib.json",
         "place-safe bench recovery --frames 5 --paper-frames 0 --memory-file 1000"],
        opt("file", nargs="?", metavar="FILE", help="frame file with ground truth (default: synthetic frames)"),
        "calibration", "frames",
        opt("--paper-frames", type=options.int_range(0, 10000), default=None, metavar="N",
            help=f"frames for the diff-paper run, about 10 s each (default {PAPER_FRAMES}; 0 skips it)"),
        opt("--methods", nargs="+", choices=("diff-paper", "diff-fast", "peak"),
            default=["diff-paper", "diff-fast", "peak"], metavar="RUN",
            help="runs to include: diff-paper diff-fast peak (default all)"),
        opt("--memory-file", type=options.int_range(1, 1000000), default=None, metavar="N",
            help="also report the peak RSS of `recover` over an N-frame synthetic file in a fresh process"),
        "method", "seed", "json", "quiet",
        frames={"help": "frames to use (default: 20 synthetic, or all of FILE)"},
        method={"flags": ("--memory-method",), "default": None,
                "help": f"method for --memory-file (default {MEMORY_METHOD})"},
        seed={"default": None, "help": f"seed of the synthetic frames, without FILE (default {SYNTHETIC_SEED})"},
        json={"help": "write the results as JSON"})
