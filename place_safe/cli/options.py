"""Typed command-line values: one validator per kind, used as argparse ``type=`` by every command.

Each raises :class:`argparse.ArgumentTypeError` with what was expected, so a bad value gives the
usual one-line usage error (exit 2). Units: metres, seconds, hertz (SI) unless the name says otherwise.
"""

from __future__ import annotations

import argparse
import math


def _number(text: str, kind: type = float):
    try:
        value = kind(text)
    except (TypeError, ValueError):
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


__all__ = ["finite_float", "positive_float", "nonnegative_float", "positive_int", "nonnegative_int", "fraction"]
