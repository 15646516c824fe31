"""Typed command-line values: one validator per kind, used as argparse ``type=`` by every command.

Each raises :class:`argparse.ArgumentTypeError` with what was expected, so a bad value gives the
usual one-line usage error (exit 2). Units: metres, seconds, hertz (SI) unless the name says otherwise.
"""

from __future__ import annotations

import argparse
import math


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

        from place_safe.config import field_constraints, field_range_text

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


__all__ = ["field_option", "int_range", "float_range", "finite_float", "positive_float", "nonnegative_float", "positive_int", "nonnegative_int", "fraction"]
