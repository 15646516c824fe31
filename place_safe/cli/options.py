"""The command line's options, declared once: typed values (one validator per kind), the options several
commands share (:data:`SHARED`, added to a parser by name with :func:`add`) and the declaration of a command
(:func:`command`).

Each validator raises :class:`argparse.ArgumentTypeError` with what was expected, so a bad value gives the
usual one-line usage error (exit 2). Units: metres, seconds, hertz (SI) unless the name says otherwise. An
option that is a field of a parameter model (:class:`~place_safe.config.ParamModel`) takes its kind and range
from the model's ``Field`` (:func:`field_option`), so the range is written in one place.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from place_safe.cli.common import FMT
from place_safe.recovery import METHODS
from place_safe.config import field_constraints, field_range_text


def _number(text: str, kind: type = float):
    try:
        value = kind(text.strip())
    except (TypeError, ValueError, OverflowError, AttributeError):
        raise argparse.ArgumentTypeError(f"expected a {'whole number' if kind is int else 'number'}, "
                                         f"got {text!r}") from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
    return value


def finite_float(text: str) -> float:
    """Any finite number."""
    return _number(text)


def positive_float(text: str) -> float:
    """A finite number > 0 (rates, durations, distances)."""
    v = _number(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}")
    return v


def nonnegative_float(text: str) -> float:
    """A finite number >= 0."""
    v = _number(text)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a number >= 0, got {text!r}")
    return v


#: Worker processes one command may start (each loads MuJoCo and torch: ~0.5 GB).
MAX_JOBS = 64
#: Noise cycles ``--cycles`` may ask for (2 million take about 2 s; this many, a couple of minutes).
MAX_CYCLES = 100_000_000


def positive_int(text: str) -> int:
    """A whole number >= 1 (counts of frames, jobs, iterations)."""
    v = _number(text, int)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 1, got {text!r}")
    return v


def nonnegative_int(text: str) -> int:
    """A whole number >= 0 (seeds, optional counts where 0 means none)."""
    v = _number(text, int)
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected a whole number >= 0, got {text!r}")
    return v


def fraction(text: str) -> float:
    """A number in [0, 1] (probabilities, fractions)."""
    v = _number(text)
    if not 0.0 <= v <= 1.0:
        raise argparse.ArgumentTypeError(f"expected a number between 0 and 1, got {text!r}")
    return v


def int_range(lo: int, hi: int):
    """A validator for whole numbers in ``[lo, hi]`` (counts with a sane upper bound, image sizes)."""
    def check(text: str) -> int:
        v = _number(text, int)
        if not lo <= v <= hi:
            raise argparse.ArgumentTypeError(f"expected a whole number from {lo} to {hi}, got {text!r}")
        return v
    check.__name__ = f"whole number in [{lo}, {hi}]"
    return check


def float_range(lo: float, hi: float, lo_open: bool = False):
    """A validator for finite numbers in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``)."""
    def check(text: str) -> float:
        v = _number(text)
        if not ((lo < v if lo_open else lo <= v) and v <= hi):
            raise argparse.ArgumentTypeError(f"expected a number {'>' if lo_open else '>='} {lo:g} and <= {hi:g}, "
                                             f"got {text!r}")
        return v
    check.__name__ = f"number in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    return check


def field_option(model: str, name: str, what: str):
    """The validator of a command-line value that is field ``name`` of parameter model ``model``
    (``"package.module:Class"``, a :class:`~place_safe.config.ParamModel`): the field's kind (whole number or
    number) and range, declared once in the model. The model's module is imported when a value is checked
    or the help is shown, not when the parser is built (it may import torch). Its ``help`` attribute is
    ``what`` followed by the range and unit, for the option's help text."""
    def resolve():
        import importlib
        import typing

        module, _, cls = model.partition(":")
        m = getattr(importlib.import_module(module), cls)
        c = field_constraints(m, name)
        ann = m.model_fields[name].annotation
        lo, hi = c.get("ge", c.get("gt", -math.inf)), c.get("le", c.get("lt", math.inf))
        if int in (ann, *typing.get_args(ann)):
            return int_range(int(lo), int(hi)), field_range_text(m, name)
        return float_range(lo, hi, lo_open="gt" in c), field_range_text(m, name)

    def check(text: str):
        return resolve()[0](text)

    check.__name__ = name
    check.help = _LazyHelp(what, lambda: f"{what}; {resolve()[1].replace('value', name)}")  # type: ignore[attr-defined]
    return check


class _LazyHelp(str):
    """Help text computed when argparse formats it (``help % params``), so building a parser stays cheap."""

    def __new__(cls, text: str, make):
        obj = super().__new__(cls, text)
        obj.make = make
        return obj

    def __mod__(self, params):
        return self.make() % params


# ------------------------------------------------------------------------------------------------
# the shared options
# ------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Option:
    """One command-line option or positional: its flags (or name) and argparse keywords. ``field`` names the
    parameter-model field (``"package.module:Class.field"``) that gives the value's kind and range; ``what``
    is then the help text before the range and unit."""

    flags: tuple[str, ...]
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    field: str | None = None
    what: str = ""

    def but(self, **changes: Any) -> "Option":
        """This option with some argparse keywords changed (a command's own default or help text); ``flags``
        renames it (``--diff-mode`` for a command where ``--mode`` means something else)."""
        flags = tuple(changes.pop("flags", self.flags))
        what = changes.pop("what", self.what)
        return replace(self, flags=flags, what=what, kwargs={**self.kwargs, **changes})

    def add_to(self, parser: Any) -> argparse.Action:
        kwargs = dict(self.kwargs)
        if self.field is not None:
            model, _, name = self.field.rpartition(".")
            check = field_option(model, name, self.what)
            kwargs.setdefault("type", check)
            kwargs.setdefault("help", check.help)  # type: ignore[attr-defined]
        return parser.add_argument(*self.flags, **kwargs)


def opt(*flags: str, field: str | None = None, what: str = "", **kwargs: Any) -> Option:
    """An :class:`Option` from argparse's own spelling (``opt("--rate", type=..., help=...)``)."""
    return Option(flags, kwargs, field, what)


DIFF_MODES = ("fast", "paper")
CONTROLLERS = ("cb3", "e-series")

#: The options that mean the same in every command that has them, by name. A command adds them with
#: :func:`add` and may change a keyword (``add(p, "method", method={"default": "peak"})``).
SHARED: dict[str, Option] = {}


def _shared() -> dict[str, Option]:
    seed = int_range(0, 2 ** 32 - 1)
    return {
        "method": opt("--method", default="diff", choices=METHODS, help="plane recovery method (default diff)"),
        "calibration": opt("--calibration", metavar="CALIB.json",
                           help="calibration file (default: built-in parameters; the output says UNCALIBRATED)"),
        "mode": opt("--mode", choices=DIFF_MODES, default=None, help="diff solver (default fast)"),
        "batch": opt("--batch", type=int_range(1, 4096), metavar="N", default=1,
                     help="frames recovered together (memory stays O(N))"),
        "jsonl": opt("--jsonl", action="store_true", help="one JSON line per frame on stdout"),
        "json": opt("--json", metavar="FILE", help="also write the results as JSON"),
        "quiet": opt("-q", "--quiet", action="store_true", help="no progress bars"),
        "seed": opt("--seed", type=seed, default=0, help="seed (default 0)"),
        "frames": opt("--frames", type=int_range(1, 100_000), default=None, metavar="N", help="frames to use"),
        "max_frames": opt("--max-frames", type=int_range(1, 10_000_000), default=None, metavar="N",
                          help="stop after N frames arrived"),
        "timeout": opt("--timeout", type=float_range(0.0, 60.0, lo_open=True), default=2.0, metavar="S",
                       help="stop when no frame arrives for S seconds (default 2, at most 60)"),
        "seconds": opt("--seconds", type=float_range(0.0, 3600.0, lo_open=True), metavar="S",
                       help="seconds to run (at most 3600)"),
        "jobs": opt("--jobs", type=int_range(1, MAX_JOBS), default=1, metavar="N",
                    help=f"worker processes (default 1, at most {MAX_JOBS})"),
        "force": opt("--force", action="store_true", help="overwrite the output file"),
        "output": opt("-o", "--output", metavar="FILE", help="file to write"),
        "controller": opt("--controller", choices=CONTROLLERS, default="cb3",
                          help="controller generation: its force-sensing defaults (default cb3)"),
        "cycles": opt("--cycles", type=int_range(1, MAX_CYCLES), default=2_000_000,
                      help=f"noise cycles for the false-alarm rate (default 2000000, at most {MAX_CYCLES}: 2 million "
                           "take about 2 s)"),
        "robot_file": opt("--robot-file", dest="robot_file", metavar="ROBOT.toml",
                          help="with --sim: the robot file whose tool frames are used (default the packaged sim.toml)"),
        "table_height": opt("--table-height", type=float_range(-REACH, REACH), metavar="Z",
                            help="the table top's known z in the base frame (m)"),
        "bus_hz": opt("--bus-hz", type=float_range(1e4, 3.4e6), metavar="HZ",
                      help="emulated bus clock (10 kHz..3.4 MHz, the I2C range)"),
        "period_ms": opt("--period-ms", type=int_range(0, 0xFFFF), metavar="MS",
                         help="shortest measurement period wanted, ms: the sensor measures (one frame) once per "
                              "period; the driver lengthens it to what the bus can read out (default 33, 0-65535)"),
        "kilo_iterations": opt("--kilo-iterations", type=int_range(1, 0xFFFF), metavar="K",
                               help="laser pulses in thousands (default 4000)"),
        "patch": opt("--patch", metavar="FILE.hex", help="Intel HEX RAM patch to download (default: ROM application)"),
        "calibration_dir": opt("--calibration-dir", metavar="DIR",
                               help="folder of the sensor's factory calibration (tmf8820-<serial>.json, written by "
                                    "'place-safe sensor info URI --calibration-dir DIR --factory-calibrate'): loaded "
                                    "at start when this unit's file is there"),
        "int_line": opt("--int-line", metavar="CHIP:OFFSET",
                        help="i2c: the INT pin as a GPIO line, e.g. /dev/gpiochip0:17 (needs gpiod: pip install "
                             "\"place-safe[hw]\"; default: poll INT_STATUS over the bus)"),
        "rays": opt("--rays", field="place_safe.sim.tof:ToFConfig.rays", default=8,
                    what="stratified rays per axis and zone, default 8"),
        "rate_hz": opt("--rate", field="place_safe.sim.tof:ToFConfig.rate_hz", default=30.0,
                       what="sensor frame rate, default 30"),
        "noise": opt("--noise", field="place_safe.robot.contact_detector:DetectorSettings.noise_std",
                     what="the detector's noise floor (default: the controller's)"),
    }


#: m, a length no UR5-class arm's base frame exceeds (heights and offsets on the command line)
REACH = 2.0

#: The options of a live TMF8820 (:data:`SHARED` names) and the source schemes that take each: every command that
#: opens a sensor by URI adds them with :func:`add_sensor_options` and passes :func:`sensor_options` to
#: :func:`place_safe.sources.open_source`.
SENSOR_OPTIONS: dict[str, tuple[str, ...]] = {
    "patch": ("i2c", "emu"), "period_ms": ("i2c", "emu"), "kilo_iterations": ("i2c", "emu"),
    "calibration_dir": ("i2c", "emu"), "int_line": ("i2c",), "bus_hz": ("emu",)}
#: The title of their group in a command's ``--help``.
SENSOR_GROUP = "sensor options (i2c: and emu: sources)"


def add_sensor_options(parser: Any, **changes: Mapping[str, Any]) -> Any:
    """Add :data:`SENSOR_OPTIONS` to ``parser`` in a group of their own (``changes`` as for :func:`add`); returns
    the group."""
    group = parser.add_argument_group(SENSOR_GROUP)
    add(group, *SENSOR_OPTIONS, **{"bus_hz": {"help": "emu: emulated bus clock, Hz (default 400000; 10 kHz..3.4 MHz, "
                                                     "the I2C range)"}, **changes})
    return group


def sensor_options(args: argparse.Namespace, uri: str, command: str) -> dict[str, Any]:
    """The :func:`~place_safe.sources.open_source` options of :data:`SENSOR_OPTIONS` given on the command line for
    the source ``uri``; an option its scheme does not take is a one-line usage error naming ``command``."""
    from place_safe.exceptions import UsageError

    scheme = uri.split(":", 1)[0] if isinstance(uri, str) else ""
    opts: dict[str, Any] = {}
    for name, schemes in SENSOR_OPTIONS.items():
        value = getattr(args, name, None)
        if value is None:
            continue
        if scheme not in schemes:
            raise UsageError(f"{command}: --{name.replace('_', '-')} does not apply to {scheme}: sources (only to "
                             f"{' and '.join(s + ':' for s in schemes)})")
        opts[name] = value
    return opts


def shared_default(name: str) -> Any:
    """The default of the shared option ``name`` (:data:`SHARED`), for a command that takes the option with no default
    (None: not given) and fills it in where it reads it."""
    if not SHARED:
        SHARED.update(_shared())
    return SHARED[name].kwargs.get("default")


def add(parser: Any, *items: str | Option, **changes: Mapping[str, Any]) -> None:
    """Add options to ``parser`` in order: a name of :data:`SHARED` (with ``changes[name]`` applied, e.g.
    ``method={"default": "peak"}``) or a command's own :class:`Option`."""
    if not SHARED:
        SHARED.update(_shared())
    unknown = set(changes) - {i for i in items if isinstance(i, str)}
    if unknown:
        raise KeyError(f"changes to options not added: {sorted(unknown)}")
    for item in items:
        option = item if isinstance(item, Option) else SHARED[item].but(**changes.get(item, {}))
        option.add_to(parser)


def command(sub: Any, name: str, func: Callable[[argparse.Namespace], int], help: str, description: str = "",
            examples: str | list[str] = "", *options: str | Option, **changes: Mapping[str, Any]):
    """Declare a command: the sub-parser ``name`` on ``sub`` running ``func``, its one-line ``help``, the
    ``description`` of its ``--help`` and an epilog of ``examples`` (a string is the whole epilog), with
    ``options`` added by :func:`add`. Returns the parser (for options that do not fit a table)."""
    epilog = examples if isinstance(examples, str) else \
        ("example" if len(examples) == 1 else "examples") + ":\n" + "\n".join(f"  {e}" for e in examples)
    p = sub.add_parser(name, formatter_class=FMT, help=help, description=description or None, epilog=epilog or None)
    add(p, *options, **changes)
    p.set_defaults(func=func)
    return p


__all__ = ["add", "command", "opt", "Option", "SHARED", "REACH", "SENSOR_OPTIONS", "SENSOR_GROUP",
           "add_sensor_options", "sensor_options", "field_option", "int_range", "float_range",
           "finite_float", "positive_float", "nonnegative_float", "positive_int", "nonnegative_int", "fraction"]
