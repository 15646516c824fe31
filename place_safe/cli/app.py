"""The ``place-safe`` command line: the root parser, the lazily loaded ``sim`` commands and ``main``.

Each command group lives in its own module (``COMMAND_MODULES``): ``sensing`` (calibrate, recover,
evaluate, stream; docs/interfaces.md), ``demo``, ``sensor``, ``robot`` (place, capture,
calibrate-mount), ``bench`` (every benchmark as a sub-command), ``synth`` and ``scenarios``; shared
helpers are in ``common``.

Conventions at this edge: distances on the command line are metres unless an option says otherwise,
angles are printed in degrees, planes in files and JSON lines use the sensor-frame convention
(``n . x = d``, unit ``n`` with ``n_z > 0``, ``d`` in metres). Standard output carries only the
command's result (for ``recover --jsonl`` and ``stream --jsonl``: only JSON lines); progress bars,
logs and summaries go to standard error.

Exit status: 0 on success, 2 for a usage or input error (one line on standard error, no traceback),
1 for an unexpected internal failure, 130 when interrupted.
"""

from __future__ import annotations

import argparse
import errno
import importlib.util
import os
import sys
from pathlib import Path
from collections.abc import Sequence

from place_safe.cli.common import FMT, PROG, Parser, UsageError, log
from place_safe.exceptions import PlaceSafeError
from place_safe import __version__
from place_safe.io.input_file import output_file_problem, output_open_problem

#: Command groups, each a module exposing ``register(subparsers) -> None``, which adds its sub-parser(s)
#: (``parser_class=Parser`` is inherited) with ``set_defaults(func=...)``. Modules import heavy packages
#: (torch, MuJoCo, ur-rtde, smbus2) inside their command functions, not at import time.
COMMAND_MODULES: tuple[str, ...] = ("place_safe.cli.sensing", "place_safe.cli.demo", "place_safe.cli.sensor",
                                   "place_safe.cli.robot", "place_safe.cli.bench", "place_safe.cli.synth",
                                   "place_safe.cli.scenarios")


# ------------------------------------------------------------------------------------------------
# sim (optional extra)
# ------------------------------------------------------------------------------------------------
def _add_sim(sub, load: bool) -> None:
    """The ``sim`` commands; imported only when asked for (MuJoCo is slow to import and optional)."""
    reason = None
    if not load:
        p = sub.add_parser("sim", help="MuJoCo: validate the simulated TMF8820, render scenes (needs the [sim] "
                                       "extra; see 'place-safe sim --help')", add_help=False)
        p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)
        return
    if importlib.util.find_spec("mujoco") is None:
        reason = ("the simulation needs MuJoCo, which is not installed: install the [sim] extra, "
                  "e.g. pip install -e \".[sim]\"")
    else:
        try:
            from place_safe.sim.cli import add_sim_commands
        except ImportError as exc:
            if (getattr(exc, "name", "") or "").startswith("place_safe"):
                reason = f"the simulation commands are not available in this build ({exc})"
            else:
                reason = f"the simulation needs {exc.name or 'a package'} ({exc}): install the [sim] extra"
        except Exception as exc:  # a broken optional module must not take the whole CLI down
            reason = _mujoco_gl_problem(exc) or f"the simulation commands failed to load: {type(exc).__name__}: {exc}"
        else:
            add_sim_commands(sub)
            return
    p = sub.add_parser("sim", help="MuJoCo: validate the simulated TMF8820, render scenes (needs the [sim] extra)",
                       description=reason, add_help=True)
    p.add_argument("rest", nargs=argparse.REMAINDER, help=argparse.SUPPRESS)

    def unavailable(_args) -> int:
        raise UsageError(f"sim: {reason}")

    p.set_defaults(func=unavailable)



MAIN_EPILOG = """\
conventions: distances in metres (mm where a column says so), angles printed in degrees; planes are
n . x = d in the sensor frame (unit normal n with n_z > 0, d > 0 the perpendicular distance).
Frame files: a JSON list of frames or JSON Lines (see docs/interfaces.md).

examples:
  place-safe demo
  place-safe calibrate tests/data/tmf8820_ur5_sweep.json --method peak -o calib.json
  place-safe calibrate tests/data/tmf8820_ur5_sweep.json --method diff -o calib.json
  place-safe recover frames.json --method diff --calibration calib.json --jsonl > planes.jsonl
  place-safe evaluate tests/data/tmf8820_ur5_sweep.json --calibration calib.json
  place-safe stream frames.json --method diff --rate 30
  place-safe bench recovery --frames 20 --paper-frames 3
  place-safe sensor stream emu:synthetic --method peak --max-frames 30
  place-safe place --sim place_level
  place-safe place --robot robots/ur5/real.toml --sensor i2c:/dev/i2c-1@0x41 --calibration cal.json --dry-run
  place-safe scenarios --jobs 2 --json set.json
"""


def build_parser(load_sim: bool = True) -> argparse.ArgumentParser:
    """The argument parser; with ``load_sim`` False the ``sim`` commands are a placeholder (fast start)."""
    p = Parser(prog=PROG, formatter_class=FMT, epilog=MAIN_EPILOG,
                description="Put a held cup down safely with a UR5 and the TMF8820 on its gripper: recover the "
                            "plane below from transient histograms, calibrate and evaluate the methods, read the "
                            "sensor, drive the arm or its MuJoCo twin, and run scenario suites.")

    p.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = p.add_subparsers(dest="command", metavar="COMMAND", parser_class=Parser)

    import importlib

    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    _add_sim(sub, load_sim)
    return p


def _commands(parser: argparse.ArgumentParser) -> list[str]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return list(action.choices)
    return []


#: Options that name a file a command writes (checked before it starts: see :func:`_check_outputs`).
OUTPUT_OPTIONS = ("output", "json", "log", "write", "plot", "render", "gif", "save_frames", "save")


def _check_outputs(args: argparse.Namespace) -> None:
    """One line (exit 2) before anything runs when an output option names a directory or a FIFO nobody reads
    (opening it would block for ever), or a file in a folder that cannot be made; a missing folder is made here, as
    synth and calibrate always did for theirs (evaluate --json into one failed after the whole evaluation). Two
    outputs may not name one file (``place --json R --log R`` wrote the log over the result); a device such as
    ``/dev/null`` may take several."""
    named: dict[str, str] = {}
    for name in OUTPUT_OPTIONS:
        value = getattr(args, name, None)
        if isinstance(value, str) and value and (os.path.isfile(value) or not os.path.exists(value)):
            if (other := named.setdefault(os.path.realpath(value), name)) != name:
                raise UsageError(f"{args.command}: --{name.replace('_', '-')} {value} is also its "
                                 f"--{other.replace('_', '-')}: one output would overwrite the other; choose another "
                                 "file")
        if value == "":
            raise UsageError(f"{args.command}: --{name.replace('_', '-')} needs a file name "
                             "(it was given an empty one)")
        if not isinstance(value, str):
            continue
        if (why := output_file_problem(value)) is not None:
            raise UsageError(f"{args.command}: --{name.replace('_', '-')} {value} {why}")
        if (given := _input_named(args, name, value)) is not None:
            raise UsageError(f"{args.command}: --{name.replace('_', '-')} {value} is also its input ({given}): writing "
                             "it would destroy what the command reads; choose another file")
        try:
            Path(value).parent.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise UsageError(f"{args.command}: --{name.replace('_', '-')} {value}: cannot make its folder "
                             f"({exc.strerror or exc})") from None
        if (why := output_open_problem(value)) is not None:
            raise UsageError(f"{args.command}: --{name.replace('_', '-')} {value}: cannot be written ({why})")


#: (output option, input option) pairs where writing the input is the point: ``--write`` rewrites the robot file
#: with the fitted mount or measured noise and keeps the rest of it (``calibrate-mount``, ``bench robot``)
IN_PLACE = {("write", "robot")}


def _input_named(args: argparse.Namespace, output: str, value: str) -> str | None:
    """The input (an option's or a positional's file) that is the same file as the output ``value``, as
    ``"NAME PATH"``, or None. ``evaluate F.json --json F.json`` replaced the frames with the report, ``latency X
    --json X`` and ``evaluate --calibration C --json C`` alike (an adversarial round, session 74); only an existing
    file can be one."""

    if not os.path.isfile(value):
        return None
    for name, given in vars(args).items():
        if name in OUTPUT_OPTIONS or name in ("func", "command") or (output, name) in IN_PLACE:
            continue
        for original in given if isinstance(given, (list, tuple)) else [given]:
            for item in _files_named(original):
                try:
                    same = os.path.isfile(item) and os.path.samefile(item, value)
                except OSError:
                    continue
                if same:
                    return f"{name.replace('_', '-').upper()} {original}"
    return None


def _files_named(value: object) -> list[str]:
    """The file paths an argument may name: itself, and the path of a source URI that reads a file (``file:PATH``,
    ``emu:file:PATH``, ``serial:PATH`` for a recorded bridge log; :mod:`place_safe.sources`): ``sensor record
    file:rec.json -o rec.json --force`` replaced the recording it read (a review, session 74)."""
    if not isinstance(value, (str, Path)) or not str(value):
        return []
    text = str(value)
    inner = next((text[len(p):] for p in ("emu:file:", "file:", "serial:") if text.startswith(p)), None)
    return [text] + ([inner] if inner else [])


def mujoco_gl_backends() -> list[str]:
    """The ``MUJOCO_GL`` values MuJoCo can render with on this machine: ``egl`` where libEGL is installed (offscreen,
    no display needed: what ``place_safe.sim`` picks when MUJOCO_GL is unset and there is no display), ``glfw`` and
    ``glx`` only with a display (``DISPLAY``), ``osmesa`` only where libOSMesa is installed."""
    import ctypes.util

    found = ctypes.util.find_library
    return ((["egl"] if found("EGL") else []) + (["glfw", "glx"] if os.environ.get("DISPLAY") else [])
            + (["osmesa"] if found("OSMesa") else []))


def _mujoco_gl_problem(exc: BaseException) -> str | None:
    """The one line (a usage error, exit 2) for a failure of MuJoCo's OpenGL set-up under a ``MUJOCO_GL`` that cannot
    work here -- a value MuJoCo rejects when imported, osmesa without libOSMesa, glfw without a display at the first
    render -- naming the values that do (:func:`mujoco_gl_backends`); None when MUJOCO_GL is unset or one of them,
    or ``exc`` was not raised in MuJoCo or PyOpenGL."""

    value = os.environ.get("MUJOCO_GL")
    if value is None:
        return None
    works = mujoco_gl_backends()
    if value.strip().lower() in works:
        return None
    tb, ours = exc.__traceback__, type(exc).__module__.startswith("mujoco")
    while tb is not None and not ours:
        ours = str(tb.tb_frame.f_globals.get("__name__", "")).startswith(("mujoco", "OpenGL"))
        tb = tb.tb_next
    if not ours:
        return None
    lacking = [why for name, why in (("egl", "egl: no libEGL"), ("osmesa", "osmesa: no libOSMesa"),
                                     ("glfw", "glfw, glx: no display")) if name not in works]
    use = f"use MUJOCO_GL={' or '.join(works)}" if works else "MuJoCo cannot render here"
    return f"MUJOCO_GL={value!r} does not work on this machine: {use}" + (f" ({'; '.join(lacking)})" if lacking else "")


def _one_line(exc: BaseException) -> str:
    """The first line of an exception's message (its type name when empty), at most 400 characters, its control
    characters escaped (:func:`place_safe.config.printable`)."""
    from place_safe.config import printable

    text = str(exc).strip()
    line = printable(text.splitlines()[0] if text else type(exc).__name__)
    return line if len(line) <= 400 else line[:397] + "..."


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``place-safe`` console script; returns the exit status.

    Every input problem ends here as exit status 2 and exactly one line on standard error: the
    library's own errors, and also what bad input can make Python raise (OSError, ValueError with
    UnicodeDecodeError and overflow, RecursionError). Warnings (e.g. NumPy's on odd data) are
    silenced at this edge so they never add lines.
    """
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return _main(argv)


#: errno values of a write whose error names no file: no room (a full disk or quota, a file too large) or an I/O error
#: (``--json /proc/version``); other errors without a file (a refused connection) are no write
UNNAMED_WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO)


def _unnamed_write_where(args: argparse.Namespace | None) -> str:
    """Where a write whose error names no file (a full disk or quota, a file too large, an I/O error) may have gone:
    the output options the command was given and standard output, e.g. ``writing --json out.json or standard
    output``."""
    named = [] if args is None else [f"--{name.replace('_', '-')} {value}" for name in OUTPUT_OPTIONS
                                     if isinstance(value := getattr(args, name, None), str) and value]
    return "writing " + " or ".join(named + ["standard output"])


def _main(argv: Sequence[str] | None) -> int:
    args = None
    try:
        argv = list(sys.argv[1:] if argv is None else argv)
        command = next((a for a in argv if not a.startswith("-")), None)
        parser = build_parser(load_sim=command == "sim")
        args = parser.parse_args(argv)
        if not getattr(args, "command", None):
            raise UsageError("a command is required: " + ", ".join(sorted(_commands(parser)))
                             + f" (see '{PROG} --help')")
        _check_outputs(args)
        return int(args.func(args) or 0)
    except PlaceSafeError as exc:
        log(f"{PROG}: error: {_one_line(exc)}")
        return 2
    except BrokenPipeError:
        # stdout closed early (e.g. piped into head): not an error of ours
        try:
            sys.stdout = open("/dev/null", "w")  # noqa: SIM115 - silence the interpreter's flush at exit
        except OSError:
            pass
        return 0
    except KeyboardInterrupt:
        log(f"{PROG}: interrupted")
        return 130
    except OSError as exc:  # e.g. an output directory that cannot be written
        from place_safe.config import printable

        where = printable(str(exc.filename)) if exc.filename else (_unnamed_write_where(args)
                                                                     if exc.errno in UNNAMED_WRITE_ERRORS else "")
        log(f"{PROG}: error: {exc.strerror or _one_line(exc)}: {where}".rstrip(": "))
        return 2
    except (ValueError, RecursionError, OverflowError, MemoryError) as exc:  # bad input Python noticed first
        log(f"{PROG}: error: invalid input: {_one_line(exc)}")
        return 2
    except Exception as exc:  # noqa: BLE001 - an internal failure: one line, exit 1 (traceback on request)

        if (why := _mujoco_gl_problem(exc)) is not None:  # the environment's error, not ours
            log(f"{PROG}: error: {why}")
            return 2
        if os.environ.get("PLACE_SAFE_DEBUG"):
            raise
        log(f"{PROG}: internal error: {type(exc).__name__}: {_one_line(exc)} (set PLACE_SAFE_DEBUG=1 "
             "for the traceback)")
        return 1


if __name__ == "__main__":
    sys.exit(main())


__all__ = ["main", "build_parser", "COMMAND_MODULES"]
