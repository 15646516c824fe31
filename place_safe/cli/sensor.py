"""``place-safe sensor``: read a TMF8820 (I2C, Arduino bridge, emulator, file): info, record, stream, bench.

Sources are URIs (:func:`place_safe.sources.open_source`): ``i2c:/dev/i2c-1@0x41``, ``serial:/dev/ttyACM0``,
``serial:capture.log``, ``file:frames.json``, ``emu:file:frames.json``, ``emu:synthetic:50``,
``emu:place_level``. Frame rates are frames per second, distances millimetres and angles degrees at
this edge; standard output carries the command's result, progress and summaries go to standard error.
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import math
import os
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

from place_safe.cli import options
from place_safe.cli.common import FMT, PROG, log, refuse_overwrite
from place_safe.cli.options import float_range, fraction, int_range, opt
from place_safe.drivers.tmf8820 import bench
from place_safe.exceptions import ConfigError, SensorTimeout, UsageError
from place_safe.sources import open_source
from place_safe.calibration import mark
from place_safe.cli.common import estimator_for, load_calibration, uncalibrated_note
from place_safe.io.frame_file import WriteInterrupted, write_frames
from place_safe.io.live import run_live
from place_safe.io.replay import parse_error

#: Hz: an emulated I2C clock (standard 100 kHz .. high-speed 3.4 MHz, and slower buses down to 10 kHz).
#: s: how long a read may wait for a frame.

_URI_HELP = ("source URI: i2c:BUS[@ADDR], serial:PORT[@BAUD] or serial:LOG, file:FRAMES.json, "
             "emu:file:FRAMES.json, emu:synthetic[:N], emu:SCENARIO")


def _paragraphs(*paras: str) -> str:
    """Help text for the raw-description formatter: each paragraph wrapped at 100 columns."""
    return "\n\n".join(textwrap.fill(p, 100) for p in paras)


#: The source positional of every command that opens a source (``sensor info|record|stream``).
_SOURCE = options.opt("uri", metavar="URI", help=_URI_HELP)


def _sensor_command(sub, name: str, func, help: str, description: str, examples: list[str], *more, **changes):
    """A ``sensor`` sub-command: the source URI and the sensor options (a group of their own:
    :func:`~place_safe.cli.options.add_sensor_options`), then ``more``."""
    p = options.command(sub, name, func, help, description, examples, _SOURCE)
    options.add_sensor_options(p)
    options.add(p, *more, **changes)
    return p


def _open(args: argparse.Namespace, **extra: Any):
    """The source of ``args.uri`` with the sensor options given (one usage line for one its scheme does not take)."""
    scheme = args.uri.split(":", 1)[0]
    opts = options.sensor_options(args, args.uri, "sensor")
    if scheme == "emu":
        opts.setdefault("realtime", True)
    opts.update({k: v for k, v in extra.items() if v is not None and (scheme in ("i2c", "emu") or k != "start")})
    return open_source(args.uri, **opts)


def _no_frame(args: argparse.Namespace, ended: str, seconds: float) -> str:
    """The one error line of ``sensor record|stream`` when the source gave no frame at all (exit status 1, as a
    placement that timed out): ``ended`` "timeout" (no answer within --timeout: one read, one timeout's silence),
    "seconds" (--seconds ran out) or anything else (the source ended before its first frame); ``seconds`` waited."""
    seconds = round(seconds, 1)
    if ended == "timeout":
        seconds, why = args.timeout, f"did not answer within --timeout {args.timeout:g} s"
    elif ended == "seconds":
        why = f"sent none before --seconds {args.seconds:g} ran out"
    else:
        why = "ended before its first frame"
    return f"sensor {args.sensor_command}: no frame from the sensor in {seconds:g} s: source {args.uri!r} {why}"


# ------------------------------------------------------------------------------------------------
def cmd_info(args: argparse.Namespace) -> int:
    src = _open(args, start=False)
    with src:
        info = src.info() if hasattr(src, "info") else {"source": type(src).__name__}
        info.setdefault("clock_domain", src.clock_domain)
        if args.factory_calibrate:
            driver = getattr(src, "driver", src)
            if not hasattr(driver, "factory_calibrate"):
                raise ConfigError(f"{args.uri}: factory calibration needs an i2c: or emu: source")
            info["calibration_file"] = info["calibration"] = str(driver.factory_calibrate())
    if args.json:
        print(json.dumps(info, indent=1, default=str))
    else:
        width = max(map(len, info), default=0)
        for k, v in info.items():
            print(f"{k:>{width}}: {v}{_info_note(k, v, info)}")
    return 0


def _info_note(key: str, value: Any, info: dict) -> str:
    """What a line of ``sensor info`` means, after its value (units; '' for the self-explaining ones)."""
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        return ""
    if key == "period_ms" and value > 0:
        asked = info.get("requested_period_ms")
        longer = (f", lengthened from the {asked} ms asked to what the bus can read out"
                  if isinstance(asked, int) and 0 <= asked < value else "")
        return (f" ms (measurement period in use: one frame every {value} ms, at most {1000 / value:.1f} "
                f"frames/s{longer}; guessed from the bus timing until frames flow, then fitted to the read-out)")
    if key == "requested_period_ms":
        return " ms (the shortest measurement period asked for: --period-ms)"
    if key == "kilo_iterations":
        return " (thousands of laser pulses per measurement: --kilo-iterations)"
    if key == "bus_hz":
        return " Hz (the emulated I2C clock: --bus-hz)"
    return ""


def cmd_record(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    out = Path(args.output)
    refuse_overwrite(out, args.force)
    src = _open(args)
    bar = tqdm(total=args.frames, desc="record", unit="frame", file=sys.stderr, disable=args.quiet or None,
               leave=False)
    deadline = time.monotonic() + args.seconds if args.seconds else math.inf
    ended = "frames"
    unreadable: list[str] = []  # a file source's entries it could not parse: no frame to record

    def frames():
        nonlocal ended
        n = 0
        while n < args.frames:
            if time.monotonic() > deadline:
                ended = "seconds"
                return
            try:
                f = src.read(args.timeout)
            except StopIteration:
                ended = "source ended"
                return
            except SensorTimeout:
                ended = "timeout"
                return
            except KeyboardInterrupt:  # Ctrl-C: the recording ends here (a JSON list was left without its ']', unread)
                ended = "interrupted"
                return
            if (why := parse_error(f)) is not None:  # (it was written as a frame of NaN counts: not JSON)
                unreadable.append(why)
                continue
            n += 1
            bar.update(1)
            yield f

    t0 = time.monotonic()
    with src:
        it = frames()
        first = next(it, None)  # no frame at all: the output is not opened (an existing one stays as it was)
        try:
            n = 0 if first is None else write_frames(out, itertools.chain([first], it), jsonl=out.suffix == ".jsonl")
        except WriteInterrupted as stop:  # Ctrl-C while a frame was written: the file holds those before it, whole
            n, ended = stop.written, "interrupted"
            if not n and out.is_file():  # (none whole: no file of no frames left behind, as before the first frame)
                out.unlink()
        stats = dict(getattr(src, "stats", {}))
    bar.close()
    left_out = (f"{len(unreadable)} unreadable frame{'' if len(unreadable) == 1 else 's'} of the source left out "
                f"(the first: {unreadable[0]})" if unreadable else "")
    if not n and unreadable:
        raise ConfigError(f"sensor record: no readable frame from {args.uri!r}: {left_out}; {out} not written")
    if not n:
        if ended == "interrupted":
            raise KeyboardInterrupt  # (before the first frame: nothing written, as any interrupted command)
        log(f"{PROG}: error: {_no_frame(args, ended, time.monotonic() - t0)}; {out} not written")
        return 1
    if ended == "timeout":
        ended = f"no frame within {args.timeout:g} s"
    log(f"wrote {n} frames to {out} (stopped: {ended})" + (f"; {left_out}" if left_out else ""))
    faults = {k: v for k, v in stats.items() if isinstance(v, (int, float)) and v and k not in ("frames",)}
    if faults and not args.quiet:
        log("source statistics: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                               for k, v in faults.items()))
    return 130 if ended == "interrupted" else 0  # (an interrupted command's status; the frames read are in the file)


def cmd_stream(args: argparse.Namespace) -> int:
    from place_safe.cli.live_view import RecordingError, not_a_recording

    if args.force and not args.save:
        raise UsageError("sensor stream: --force goes with --save")
    if args.save and not args.force and not_a_recording(args.save):  # a frame file or a calibration: kept
        raise UsageError(f"sensor stream: --save {args.save} is a file that is not a rerun recording; it is kept (use "
                         "--force to replace it)")
    cal = load_calibration(args.calibration)
    est = estimator_for(args.method, cal)
    note = uncalibrated_note(args.method, cal, args.calibration)
    view = None
    if args.save or args.view:
        from place_safe.cli.live_view import RerunView

        params = cal.forward() if cal is not None and hasattr(cal, "forward") and "forward" in cal.sections else None
        if params is None and args.method == "diff":
            from place_safe.recovery.forward import ForwardParams

            params = ForwardParams()
        existed = bool(args.save) and os.path.lexists(args.save)
        view = RerunView(save=args.save, params=params)  # first: an output that cannot be written opens no sensor
    try:
        src = _open(args)
    except BaseException:
        if view is not None:  # a source that cannot be opened leaves no recording of nothing behind
            view.close()
            if args.save and not existed:
                with contextlib.suppress(OSError):
                    os.remove(args.save)
        raise
    wall = src.clock_domain == "monotonic"
    pending_note = [note] if note is not None and not args.jsonl else []  # with --jsonl every record says it

    def say(text: str) -> None:
        """Print a line of output; the note on the missing calibration goes first (only once there is output,
        so an error before the first frame still leaves standard output empty)."""
        while pending_note:
            print(pending_note.pop(), flush=True)
        print(text, flush=True)

    def on_estimate(index, frame, e, latency) -> None:
        age = time.monotonic() - frame.timestamp if wall and frame.timestamp is not None else None
        if view is not None:
            view.log(index, frame, e, latency)
        if args.jsonl:
            line = e.to_json(index)
            line["latency_ms"] = round(latency * 1e3, 3)
            if age is not None:
                line["age_ms"] = round(age * 1e3, 3)
            line["calibrated"] = note is None
            print(json.dumps(line), flush=True)
        elif e.plane is not None:
            p = e.plane
            say(mark(f"{index:>5}  tilt {math.degrees(p.theta):6.2f} deg  azimuth {math.degrees(p.phi):7.1f} deg  "
                     f"distance {p.offset * 1e3:7.1f} mm  latency {latency * 1e3:6.1f} ms"
                     + (f"  age {age * 1e3:6.1f} ms" if age is not None else ""), note is None))
        else:
            say(mark(f"{index:>5}  no plane: {e.reason}", note is None))

    try:
        with src:
            # --timeout is the silence that ends the stream: one read without a frame, not the streams' five
            stats = run_live(src, est, on_estimate, max_frames=args.max_frames, read_timeout=args.timeout,
                             max_timeouts=1)
            source_stats = dict(getattr(src, "stats", {}))
    except RecordingError:  # the recording's file refused a write (a full disk): reported below, once closed
        pass
    finally:
        if view is not None:
            view.close()
    if view is not None and view.failure is not None:  # mid-stream or at the end: one line, exit 1
        log(f"{PROG}: error: sensor stream: {view.failure.line()}")
        return 1
    if not stats.received:  # standard output stays empty (the note goes first only once there is output)
        log(f"{PROG}: error: " + _no_frame(args, "timeout" if stats.timeouts else stats.ended_by, stats.elapsed))
        return 1
    while pending_note:  # no frame was printed: the note is still the output's first line
        print(pending_note.pop(), flush=True)
    log(stats.summary())
    counted = {k: v for k, v in source_stats.items() if isinstance(v, int) and v}
    if counted:
        log("source: " + ", ".join(f"{k} {v}" for k, v in counted.items()))
    if args.save:
        log(f"wrote {args.save}")
    return 0


def cmd_bench(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    rows = []
    for wait in args.wait:
        for hz in args.bus_hz:
            for lat_us in args.latency_us:
                bar = tqdm(total=args.frames, desc=f"{wait}, bus {hz / 1e3:g} kHz, latency {lat_us:g} us",
                           unit="frame", file=sys.stderr, disable=args.quiet or None, leave=False)
                rows.append(bench.run(hz, frames=args.frames, fault_rate=args.fault_rate, seed=args.seed,
                                      period_ms=args.period_ms, kilo_iterations=args.kilo_iterations,
                                      progress=bar.update, publish_latency_s=lat_us * 1e-6, int_line=wait == "int"))
                bar.close()
    print(f"{'wait':>4} {'bus kHz':>7} {'latency us':>10} {'frames/s':>9} {'limit':>6} {'of limit':>8} "
          f"{'ceiling':>7} {'of ceil':>7} {'period ms':>9} {'ceil ms':>7} {'bytes/frame':>11} {'vs 4368':>8} "
          f"{'decode ms':>9}")
    for r in rows:
        print(f"{r['wait']:>4} {r['bus_hz'] / 1e3:>7g} {r['publish_latency_s'] * 1e6:>10g} {r['fps']:>9.2f} "
              f"{r['fps_limit']:>6.2f} {r['of_limit'] * 100:>7.1f}% {r['host_ceiling_fps']:>7.2f} "
              f"{r['of_ceiling'] * 100:>6.1f}% {r['period_ms']:>9d} {r['ceiling_period_ms']:>7d} "
              f"{r['bytes_per_frame']:>11.1f} {r['over_transfer_min'] * 100:>+7.2f}% {r['decode_ms']:>9.3f}")
        if r["faults"]:
            print(f"{'':>8} faults injected: {r['faults']}; measurements dropped: {r['dropped_frames']}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1) + "\n")
        log(f"wrote {args.json}")
    return 0


# ------------------------------------------------------------------------------------------------
def register(subparsers: argparse._SubParsersAction) -> None:
    """Add ``place-safe sensor info|record|stream``."""
    s = subparsers.add_parser(
        "sensor", formatter_class=FMT, help="read a TMF8820: info, record, stream",
        description="Talk to a TMF8820 through the I2C driver (i2c:), the Arduino bridge (serial:), the "
                    "register-level emulator (emu:) or a frame file (file:).",
        epilog="examples:\n  place-safe sensor info i2c:/dev/i2c-1@0x41\n"
               "  place-safe sensor record i2c:1 -o frames.json --frames 100\n"
               "  place-safe sensor stream emu:synthetic:50 --method peak --save run.rrd\n"
               "  place-safe bench sensor --frames 200")
    sub = s.add_subparsers(dest="sensor_command", metavar="{info,record,stream}")
    sub.required = True

    _sensor_command(
        sub, "info", cmd_info, "identity, versions, mode and configuration",
        "Bring the sensor up and print its identity (serial number), application version, mode, range and "
        "configuration without measuring. period_ms is the measurement period in use, in milliseconds (one frame "
        "per period): --period-ms (requested_period_ms, default 33) or longer, as the driver lengthens it to what "
        "the bus can read out (about 100 ms at 400 kHz, 40 ms at 1 MHz); until frames flow it is a guess from the "
        "bus timing.",
        ["place-safe sensor info i2c:/dev/i2c-1@0x41", "place-safe sensor info emu:synthetic --json",
         "place-safe sensor info i2c:1 --calibration-dir cal --factory-calibrate"],
        opt("--json", action="store_true", help="print JSON"),
        opt("--factory-calibrate", action="store_true",
            help="run the sensor's factory calibration (nothing within 40 cm, dark) and save it in --calibration-dir, "
                 "keyed by serial number; every command given that --calibration-dir (sensor record|stream, place, "
                 "capture) loads it at start"))
    _sensor_command(
        sub, "record", cmd_record, "record frames to a frame file",
        "Read frames from a source and write them to a frame file (JSON list, or JSON Lines for a .jsonl name), "
        "with a progress bar.",
        ["place-safe sensor record i2c:1 -o sweep.json --frames 200",
         "place-safe sensor record serial:/dev/ttyACM0 -o bridge.jsonl --seconds 30",
         "place-safe sensor record serial:capture.log -o frames.json"],
        "output", "frames", "seconds", "timeout", "force", "quiet",
        output={"required": True, "help": "frame file to write"},
        frames={"type": int_range(1, 1_000_000), "default": 100, "help": "frames to record (default 100, at most 1000000)"},
        seconds={"type": float_range(0.0, 86400.0, lo_open=True), "help": "stop after S seconds"},
        timeout={"help": "stop when no frame arrives for S seconds (default 2, at most 60); no frame at all is an "
                         "error (exit status 1, the output not written)"},
        quiet={"help": "no progress bar"})
    _sensor_command(
        sub, "stream", cmd_stream, "live plane readout (and rerun view)",
        "Recover the plane from every frame as it arrives and print tilt, distance and latency (age: from the "
        "measurement to the estimate, on monotonic-clock sources). --save writes a rerun recording (histograms, model "
        "fit, plane in 3D, latency, frame rate); --view opens a viewer.",
        ["place-safe sensor stream i2c:/dev/i2c-1 --method peak",
         "place-safe sensor stream emu:place_level --max-frames 30 --save run.rrd",
         "place-safe sensor stream serial:/dev/ttyACM0 --jsonl > planes.jsonl"],
        "method", "calibration", "max_frames", "timeout", "jsonl",
        opt("--save", metavar="RUN.rrd", help="write a rerun recording (headless)"),
        opt("--view", action="store_true", help="open a rerun viewer (needs a display)"),
        "force",
        method={"default": "peak", "help": "plane recovery (default peak)"},
        max_frames={"help": "stop after N frames"},
        timeout={"help": "stop when no frame arrives for S seconds (default 2, at most 60); no frame at all is an "
                         "error (exit status 1)"},
        force={"help": "with --save: replace a file that is not a rerun recording (a recording is replaced as ever)"})



def add_sensor_bench(sub) -> None:
    """``place-safe bench sensor``: the I2C driver over the register-level emulator with its bus timing."""
    options.command(
        sub, "sensor", cmd_bench, "bus frame rate, bytes per frame, decode CPU (emulator)",
        _paragraphs(
            "Stream frames through the I2C driver over the register-level emulator with "
            "its bus timing, for each way of waiting (INT line, polling INT_STATUS), bus "
            "clock and publish latency (how long the chip takes, after the host cleared a "
            "packet's interrupt, to put the next packet in its 0x20 window), and print: "
            "frames/s of emulated time; the bus limit (clock / (9 x 4182 payload bytes): "
            "10.63 frames/s at 400 kHz, 26.57 at 1 MHz) and frames/s as a share of it; the "
            "ceiling no host keeping the protocol's discipline can pass on that chip, and "
            "frames/s as a share of it; the measurement period the driver fitted to its "
            "read-out (the chip overwrites a measurement not read out within one period) "
            "and the ceiling's period; bytes moved per frame against the 4368-byte "
            "transfer minimum; host CPU to decode a frame.",
            "The ceiling: the chip publishes a packet only after the host released the "
            "previous one by clearing its interrupt, plus the publish latency L, and the "
            "host may clear it only once it has read and checked it. Per measurement the "
            "bus carries 31 x (one write-register/read transaction + one interrupt clear) "
            "= 4368 bytes of 9 clocks, plus 5 START/STOP clocks a packet, plus 31 x L of "
            "idle bus (a late read-out delays the next packet 0 by one L, so a period "
            "below all 31 never drains a backlog); polling adds one 4-byte INT_STATUS poll "
            "a packet (39 clocks, of which the 19 before its status byte can overlap L). "
            "The period is whole ms and at least the measurement time (41 ms at 4000 "
            "kilo-iterations in the emulator). E.g. 400 kHz, 200 us: 98.67 + 6.2 ms -> "
            "105 ms, 9.52 frames/s, 89.6 % of the limit; 1 MHz, 50 us: 39.47 + 1.55 ms "
            "-> 42 ms, 23.81 frames/s, 89.6 %. Clearing in the same transaction as the "
            "read would save 31 clocks but releases the packet before it is checked "
            "(an open-bus cut shows only as a 0xFF tail); reading after the clear races "
            "the next packet."),
        ["place-safe bench sensor", "place-safe bench sensor --bus-hz 1000000 --latency-us 0 20 --frames 500",
         "place-safe bench sensor --fault-rate 0.001 --json bench.json"],
        "bus_hz",
        opt("--wait", nargs="+", choices=["int", "poll"], default=["int", "poll"],
            help="how the driver waits for a packet: the emulator's INT line, polling INT_STATUS (default both)"),
        opt("--latency-us", type=float_range(0.0, 10000.0), nargs="+", default=[0.0, 50.0, 200.0], metavar="US",
            help="publish latencies of the emulated chip, microseconds, 0-10000 (default 0 50 200)"),
        "frames", "period_ms", "kilo_iterations",
        opt("--fault-rate", type=fraction, default=0.0, metavar="P",
            help="probability per bus transfer of an injected fault (default 0)"),
        "seed", "json", "quiet",
        bus_hz={"nargs": "+", "default": [400e3, 1e6], "help": "bus clocks (default 400000 1000000)"},
        frames={"default": 200, "help": "frames per clock and latency (default 200)"},
        period_ms={"default": 33, "help": "shortest period wanted (default 33; the driver lengthens it to what the "
                                          "bus can read out)"},
        kilo_iterations={"default": 4000, "help": "pulses in thousands (default 4000)"},
        seed={"help": "seed of frames and faults"}, json={"help": "write the figures as JSON"})


__all__ = ["register", "add_sensor_bench"]
