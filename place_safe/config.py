"""Configuration dataclasses as JSON: key checking and file reading shared by every config type.

Each config (forward-model parameters, peak parameters, robot limits, placement and scene settings)
is a plain dataclass with ``to_dict``/``from_dict``/``save``/``load``. The parts that are the same
for all of them live here, so every one rejects unknown keys and unreadable files with the same
kind of message: what was wrong and what was expected.
"""

from __future__ import annotations

import json
from dataclasses import fields
from pathlib import Path
from typing import Any


def check_keys(cls: type, d: Any, what: str, error: type[Exception] = ValueError) -> dict:
    """``d`` as a dict whose keys are all fields of dataclass ``cls``; raises ``error`` otherwise.

    ``what`` names the thing in the message (e.g. ``"placement config"``).
    """
    if not isinstance(d, dict):
        raise error(f"{what} must be a JSON object, got {type(d).__name__}")
    known = {f.name for f in fields(cls)}
    unknown = set(d) - known
    if unknown:
        raise error(f"{what}: unknown keys {sorted(unknown)}; expected some of {sorted(known)}")
    return d


def read_json(path: str | Path, what: str, error: type[Exception] = ValueError) -> Any:
    """The JSON value in ``path``; raises ``error`` saying why it cannot be read."""
    try:
        return json.loads(Path(path).read_text(encoding="utf-8"))
    except OSError as exc:
        raise error(f"cannot read {what} from {path}: {exc.strerror}") from None
    except json.JSONDecodeError as exc:
        raise error(f"cannot read {what} from {path}: not JSON ({exc.msg} at line {exc.lineno})") from None


def write_json(path: str | Path, value: Any) -> None:
    """Write ``value`` as indented JSON with a final newline."""
    Path(path).write_text(json.dumps(value, indent=2) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------------
# Validated configuration models (pydantic v2): the one mechanism for new config and file types
# ---------------------------------------------------------------------------------------------------
from pydantic import BaseModel, ConfigDict, ValidationError  # noqa: E402

from place_safe.exceptions import ConfigError  # noqa: E402


class ConfigModel(BaseModel):
    """Base of every validated configuration (robot, sensor, scenario, ... files).

    Unknown keys are errors, values are validated on construction and on assignment, and every
    field documents its unit in its description. Load files with :func:`load_config`, which turns
    any problem into one :class:`~place_safe.exceptions.ConfigError` line naming the file and field.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False,
                              str_strip_whitespace=True)


def describe_validation_error(exc: ValidationError, what: str) -> str:
    """One line for a pydantic error: ``what: field.path: message`` (first error, count of the rest)."""
    errors = exc.errors()
    if not errors:
        return f"{what}: invalid"
    first = errors[0]
    loc = ".".join(str(p) for p in first.get("loc", ())) or "(top level)"
    msg = first.get("msg", "invalid").replace("\n", " ")
    more = f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})" if len(errors) > 1 else ""
    return f"{what}: {loc}: {msg}{more}"


def parse_config(cls: type, data: Any, what: str):
    """``cls.model_validate(data)`` with any failure as one ConfigError line."""
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(describe_validation_error(exc, what)) from None


def read_config_file(path: str | Path, what: str) -> Any:
    """The data in a JSON or TOML file (by suffix; ``.toml`` is TOML, anything else JSON).

    Raises ConfigError with one line for an unreadable file, bytes that are not UTF-8 or bad syntax.
    """
    p = Path(path)
    try:
        raw = p.read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read {what} {p}: {exc.strerror or exc}") from None
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{what} {p}: not UTF-8 text (byte {exc.start})") from None
    try:
        if p.suffix.lower() == ".toml":
            try:
                import tomllib
            except ModuleNotFoundError:  # Python 3.10
                import tomli as tomllib  # type: ignore[no-redef]
            return tomllib.loads(text)
        return json.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ConfigError(f"{what} {p}: not valid {'TOML' if p.suffix.lower() == '.toml' else 'JSON'} "
                          f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None


def load_config(cls: type, path: str | Path, what: str | None = None):
    """Read ``path`` (JSON or TOML) and validate it as ``cls`` (a :class:`ConfigModel`); one-line errors."""
    what = what or cls.__name__
    return parse_config(cls, read_config_file(path, what), f"{what} {path}")
