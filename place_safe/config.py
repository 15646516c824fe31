"""Configuration as validated pydantic models, and the JSON/TOML file reading every config type shares.

Two bases: :class:`ConfigModel` for files (robot, scenario, ...) and :class:`ParamModel` for parameter sets with
physical ranges (forward-model and peak parameters, placement settings, robot limits, scene objects, ...). Each
field is declared once, with its range as ``Field(ge/gt/le/lt)`` and its unit as the description; validation,
the one-line error messages (``what: field: problem (expected lo <= value <= hi unit)``) and the file form
(``to_dict``/``from_dict``) come from that declaration. Files are read here too, so every type rejects unknown
keys and unreadable files with the same kind of message: what was wrong and what was expected.
"""

from __future__ import annotations

import json
import math
import types
import typing
from pathlib import Path
from typing import Annotated, Any, ClassVar, NamedTuple

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from place_safe.exceptions import ConfigError
from place_safe.io.json_values import DuplicateKey, unique_keys


def _read_text(path: str | Path, what: str, error: type[Exception]) -> str:
    """The UTF-8 text of ``path`` (a byte-order mark allowed); ``error`` with one line when it cannot be read.

    Every file goes through :func:`place_safe.io.input_file.read_input_bytes`: a FIFO, a device, a directory
    or a file over :data:`~place_safe.io.input_file.MAX_CONFIG_BYTES` is refused before it is opened."""
    from place_safe.io.input_file import read_input_bytes

    raw = read_input_bytes(path, what, error)  # a regular file of bounded size, or one line saying why not
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise error(f"cannot read {what} from {path}: not UTF-8 text (byte {exc.start})") from None


def read_json(path: str | Path, what: str, error: type[Exception] = ValueError) -> Any:
    """The JSON value in ``path`` (UTF-8, a byte-order mark allowed); raises ``error`` saying why it cannot be read.

    Every way a file can be unreadable (missing, not UTF-8, not JSON, nested too deeply, an integer too
    long, a key given twice in one object) is one line naming the file.
    """
    text = _read_text(path, what, error)
    try:
        return json.loads(text, object_pairs_hook=unique_keys)
    except DuplicateKey as exc:
        raise error(f"cannot read {what} from {path}: key {printable(str(exc.args[0]))[:40]!r} appears twice in one "
                    "object (which value was meant?)") from None
    except json.JSONDecodeError as exc:
        raise error(f"cannot read {what} from {path}: not JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:
        raise error(f"cannot read {what} from {path}: not JSON (nested too deeply)") from None
    except ValueError as exc:  # an integer longer than Python's digit limit
        raise error(f"cannot read {what} from {path}: not JSON ({str(exc).splitlines()[0]})") from None


def write_json(path: str | Path, value: Any) -> None:
    """Write ``value`` as indented JSON with a final newline."""
    Path(path).write_text(json.dumps(value, indent=2) + "\n", encoding="utf-8")


# ---------------------------------------------------------------------------------------------------
# Validated configuration models (pydantic v2): the one mechanism for new config and file types
# ---------------------------------------------------------------------------------------------------

class ConfigModel(BaseModel):
    """Base of every validated configuration (robot, sensor, scenario, ... files).

    Unknown keys are errors, values are validated on construction and on assignment, and every
    field documents its unit in its description. Load files with :func:`load_config`, which turns
    any problem into one :class:`~place_safe.exceptions.ConfigError` line naming the file and field.
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False,
                              str_strip_whitespace=True)

    @model_validator(mode="before")
    @classmethod
    def _numbers_are_numbers(cls, data: Any) -> Any:
        """A boolean or a text is not a number: ``max_linear_speed = true`` in a robot file read as 1.0 m/s (ten times
        real.toml's), ``"0.1"`` as 0.1. Checked for fields that hold a number, or a list of numbers, only (a strict
        model, :class:`ParamModel`, refuses them itself). Likewise a switch (a boolean field) is true or false, not
        ``"off"`` or 0."""
        if isinstance(data, dict) and not cls.model_config.get("strict"):
            for name, value in data.items():
                field = cls.model_fields.get(name)
                if field is not None and _is_switch(field.annotation) and value is not None \
                        and not isinstance(value, bool):
                    # pydantic reads "off", "no", "0" and 0 as false: a gripper's open_level = "off" loaded as the
                    # level that opens it (an adversarial round, session 74)
                    raise ValueError(f"{name} must be true or false, got {type(value).__name__} {value!r}"[:120])
                shape = None if field is None else _number_shape(field.annotation)
                if shape is not None:
                    items = value if isinstance(value, (list, tuple)) and shape == "many" else [value]
                    bad = next((v for v in items if isinstance(v, (bool, str))), None)
                    if bad is not None:
                        kind = "a boolean" if isinstance(bad, bool) else "text"
                        raise ValueError(f"{name} must be a number, not {kind} ({bad!r})")
        return data


def _is_switch(annotation: Any) -> bool:
    """Whether a field's type is a boolean (``bool`` or an optional one)."""
    if typing.get_origin(annotation) is Annotated:
        return _is_switch(typing.get_args(annotation)[0])
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        return len(args) == 1 and _is_switch(args[0])
    return annotation is bool


def _number_shape(annotation: Any) -> str | None:
    """What a field's type holds: ``"one"`` number (``float``, ``int``, optional or not), ``"many"`` (a tuple or list of
    numbers, or a choice that includes one), or None (anything else)."""
    origin = typing.get_origin(annotation)
    if origin is Annotated:
        return _number_shape(typing.get_args(annotation)[0])
    if origin in (typing.Union, types.UnionType):
        shapes = {_number_shape(a) for a in typing.get_args(annotation) if a is not type(None)}
        return None if not shapes or None in shapes else "many" if "many" in shapes else "one"
    if origin in (tuple, list):
        args = [a for a in typing.get_args(annotation) if a is not Ellipsis]
        return "many" if args and all(_number_shape(a) is not None for a in args) else None
    return "one" if annotation in (float, int) else None


def describe_validation_error(exc: ValidationError, what: str) -> str:
    """One line for a pydantic error: ``what: field.path: message`` (first error, count of the rest)."""
    errors = exc.errors()
    if not errors:
        return f"{what}: invalid"
    first = errors[0]
    loc = ".".join(printable(str(p)) for p in first.get("loc", ())) or "(top level)"
    msg = printable(first.get("msg", "invalid")).removeprefix("Value error, ")
    more = f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})" if len(errors) > 1 else ""
    return f"{what}: {loc}: {msg}{more}"


#: Unicode categories of the characters a message shows as escapes and a name may not hold: control and format
#: characters (escape sequences, newlines, tabs, bidirectional overrides, zero-width characters) and line and paragraph
#: separators.
CONTROL_CATEGORIES = ("Cc", "Cf", "Zl", "Zp")


def printable(text: str) -> str:
    """``text`` on one line with its characters of :data:`CONTROL_CATEGORIES` written as Python escapes (``\\n``,
    ``\\x1b``, ``\\u202e``; the rest as it is): a file name, a key or a value shown in an error line cannot break the
    line, recolour or rearrange the terminal."""
    import unicodedata

    return "".join(c.encode("unicode_escape").decode("ascii") if unicodedata.category(c) in CONTROL_CATEGORIES else c
                   for c in text)


def parse_config(cls: type, data: Any, what: str):
    """``cls.model_validate(data)`` with any failure as one ConfigError line."""
    try:
        return cls.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(range_message(exc, cls, what)) from None


def read_config_file(path: str | Path, what: str) -> Any:
    """The data in a JSON or TOML file (by suffix; ``.toml`` is TOML, anything else JSON).

    Raises ConfigError with one line for an unreadable file, bytes that are not UTF-8 or bad syntax.
    """
    if Path(path).suffix.lower() != ".toml":
        return read_json(path, what, ConfigError)
    text = _read_text(path, what, ConfigError)
    try:
        return toml_reader().loads(text)
    except (ValueError, RecursionError) as exc:
        raise ConfigError(f"{what} {path}: not valid TOML "
                          f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None


def toml_reader():
    """The standard TOML reader module (``tomllib``; ``tomli`` on Python 3.10)."""
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib  # type: ignore[no-redef]
    return tomllib


def load_config(cls: type, path: str | Path, what: str | None = None):
    """Read ``path`` (JSON or TOML) and validate it as ``cls`` (a :class:`ConfigModel`); one-line errors."""
    what = what or cls.__name__
    return parse_config(cls, read_config_file(path, what), f"{what} {path}")


# ---------------------------------------------------------------------------------------------------
# Parameter sets with physical ranges: pydantic models whose Field constraints are the ranges
# ---------------------------------------------------------------------------------------------------

class ParamModel(ConfigModel):
    """Base of a parameter set with physical ranges (robot limits, contact detector, simulated sensor, ...).

    Each field is declared once, as pydantic declares it: ``speed: float = Field(0.1, gt=0, le=3,
    description="m/s")`` - the range as ``ge``/``gt``/``le``/``lt`` (on the elements of a vector, declared with
    :func:`vector`, whose length is ``min_length``/``max_length``) and the unit as the description. Values are strict (a string or a
    boolean is not a number) and finite; NumPy numbers and arrays set in code are taken as plain numbers and
    lists. Every problem, on construction, :meth:`from_dict` or assignment, is one line of the class's
    :attr:`error` type: ``what: field: problem (expected lo < value <= hi unit)``. :meth:`to_dict` is the
    file form (the fields by name, as JSON values), :meth:`save`/:meth:`load` write and read it as JSON.

    As the dataclasses they replace did, a parameter set takes its first fields positionally (in declaration
    order), :meth:`replace` is ``dataclasses.replace`` (a validated copy with some fields changed) and two sets
    are equal when their fields are (caches kept in private attributes do not count).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False, strict=True)

    #: what messages call it, and the exception they raise
    what: ClassVar[str] = "settings"
    error: ClassVar[type[Exception]] = ConfigError

    def __init__(self, *args: Any, **data: Any) -> None:
        if args:
            names = list(type(self).model_fields)
            if len(args) > len(names):
                raise self.error(f"{self.what}: takes at most {len(names)} values, got {len(args)}")
            for name, value in zip(names, args):
                if name in data:
                    raise self.error(f"{self.what}: {name}: given twice")
                data[name] = value
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise self.error(range_message(exc, type(self), self.what)) from None

    # pydantic validates a parameter set nested in another model without calling this constructor, so a nested
    # problem is one error located at its path (``table.material.albedo``), not a message inside a message
    __init__.__pydantic_base_init__ = True  # type: ignore[attr-defined]

    def __setattr__(self, name: str, value: Any) -> None:
        try:
            super().__setattr__(name, _plain(value))
        except ValidationError as exc:
            raise self.error(range_message(exc, type(self), self.what)) from None

    @model_validator(mode="before")
    @classmethod
    def _plain_numbers(cls, data: Any) -> Any:
        return {k: _plain(v) for k, v in data.items()} if isinstance(data, dict) else data

    @classmethod
    def from_dict(cls, d: Any, what: str | None = None):
        """An instance from a JSON object (its keys a subset of the fields); one-line :attr:`error` otherwise."""
        what = what or cls.what
        if not isinstance(d, dict):
            raise cls.error(f"{what} must be a JSON object, got {_json_name(d)}")
        if (odd := next((k for k in d if not isinstance(k, str)), None)) is not None:
            raise cls.error(f"{what}: {printable(str(odd))}: unknown key")
        try:
            return cls(**d)
        except cls.error as exc:  # the constructor's message, under this file's name
            raise cls.error(str(exc).replace(cls.what, what, 1) if what != cls.what else str(exc)) from None

    def to_dict(self) -> dict:
        """The file form: every field by name, as plain JSON values."""
        return self.model_dump(mode="json")

    def save(self, path: str | Path) -> None:
        """Write the file form (:meth:`to_dict`) as indented JSON."""
        write_json(path, self.to_dict())

    @classmethod
    def load(cls, path: str | Path):
        """Read a JSON file written by :meth:`save`; every problem is one :attr:`error` line naming the file."""
        return cls.from_dict(read_json(path, cls.what, cls.error), f"{cls.what} {path}")

    def replace(self, **changes: Any):
        """A copy with ``changes`` applied, validated as a new instance (``dataclasses.replace`` for a model)."""
        return type(self)(**{**{k: self.__dict__[k] for k in type(self).model_fields}, **changes})

    def __eq__(self, other: Any) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return all(self.__dict__[k] == other.__dict__[k] for k in type(self).model_fields)

    __hash__ = None  # type: ignore[assignment]  # mutable, as the dataclasses were


def vector(length: int | None = None, *, min_length: int | None = None, max_length: int | None = None,
           **bounds: float) -> Any:
    """The annotation of a :class:`ParamModel` vector field: a list of finite numbers, each within ``bounds``
    (``ge``/``gt``/``le``/``lt``), of exactly ``length`` values (or ``min_length`` to ``max_length``) when given.
    The default and the unit go in the field as for a number: ``zone_offsets: vector(N_ZONES, ge=-32, le=32) =
    Field(default_factory=lambda: [0.0] * N_ZONES, description="bins")``.
    """
    if length is not None:
        min_length = max_length = length
    size = {k: v for k, v in (("min_length", min_length), ("max_length", max_length)) if v is not None}
    return Annotated[list[Annotated[float, Field(**bounds)]], Field(**size)]


def _field_parts(model: type[BaseModel], name: str) -> tuple[dict, dict, str]:
    """(constraints on the value, constraints on each element of a vector, unit) of field ``name``."""

    import annotated_types as at

    info = model.model_fields[name]

    def constraints(metadata) -> dict:
        out = {}
        for m in metadata:
            for key, cls_ in (("ge", at.Ge), ("gt", at.Gt), ("le", at.Le), ("lt", at.Lt)):
                if isinstance(m, cls_):
                    out[key] = getattr(m, key)
            for key, cls_ in (("min_length", at.MinLen), ("max_length", at.MaxLen)):
                if isinstance(m, cls_):
                    out[key] = getattr(m, key)
        return out

    def element(ann, in_list: bool) -> dict:  # the constraints on the numbers of a list[Annotated[float, ...]]
        if typing.get_origin(ann) is typing.Annotated:
            base, *meta = typing.get_args(ann)
            if in_list:
                return constraints(sum((getattr(m, "metadata", [m]) for m in meta), []))
            return element(base, False)
        for arg in typing.get_args(ann):  # list[...], or X | None
            found = element(arg, typing.get_origin(ann) in (list, tuple))
            if found:
                return found
        return {}

    value = constraints(info.metadata)
    if typing.get_origin(info.annotation) is not list:  # an optional vector: its length sits inside
        for arg in typing.get_args(info.annotation):
            if typing.get_origin(arg) is typing.Annotated:
                value = {**constraints(sum((getattr(m, "metadata", [m]) for m in typing.get_args(arg)[1:]), [])),
                         **value}
    return value, element(info.annotation, False), info.description or ""


def field_constraints(model: type[BaseModel], name: str) -> dict:
    """The range of scalar field ``name`` of ``model`` as pydantic keywords (``ge``, ``gt``, ``le``, ``lt``): for
    another model or a command-line option that takes the same quantity, so the range is written once."""
    value, _, _ = _field_parts(model, name)
    return {k: v for k, v in value.items() if k in ("ge", "gt", "le", "lt")}


class FieldRange(NamedTuple):
    """The range of one field as its ``Field`` declares it (of each element, for a vector): ``lo``/``hi``
    (``-inf``/``inf`` where unbounded), open or closed, the vector's length limits (``None``: a number, or no
    limit) and the unit. A read-only view for code and tests that draw or clamp values; the field is the source."""

    lo: float
    hi: float
    lo_open: bool
    hi_open: bool
    vector: bool
    min_length: int | None
    max_length: int | None
    unit: str


def field_range(model: type[BaseModel], name: str) -> FieldRange:
    """The :class:`FieldRange` of field ``name`` of ``model``."""

    value, each, unit = _field_parts(model, name)
    c = each or value
    vector = any(typing.get_origin(t) is list for t in _flat_args(model.model_fields[name].annotation))
    return FieldRange(float(c.get("ge", c.get("gt", -math.inf))), float(c.get("le", c.get("lt", math.inf))),
                      "gt" in c, "lt" in c, vector, value.get("min_length"), value.get("max_length"), unit)


def field_interval(model: type[BaseModel], name: str) -> tuple[float, float]:
    """``(lo, hi)``: the bounds of field ``name`` (of each element, for a vector), open or closed, with
    ``-inf``/``inf`` where it has none: for code that keeps a fitted value inside the range a file may hold."""
    r = field_range(model, name)
    return r.lo, r.hi


def field_like(model: type[BaseModel], name: str, description: str | None = None) -> Any:
    """An optional field (default ``None``: unset) that takes the range of field ``name`` of ``model``: a file
    section that overrides some of another model's settings declares each with one line, the range written once
    (numbers as written in a file: not strict). ``description`` defaults to the field's own unit."""
    return Field(None, **field_constraints(model, name),
                 description=description if description is not None else model.model_fields[name].description)


def field_range_text(model: type[BaseModel], name: str) -> str:
    """``"0 < value <= 3 m/s"``: the range and unit of field ``name`` (of each element, for a vector)."""
    value, each, unit = _field_parts(model, name)
    c = each or value
    lo = (f"{c['gt']:g} < " if "gt" in c else f"{c['ge']:g} <= " if "ge" in c else "")
    hi = (f" < {c['lt']:g}" if "lt" in c else f" <= {c['le']:g}" if "le" in c else "")
    return f"{lo}value{hi}{' ' + unit if unit else ''}"


def range_message(exc: ValidationError, model: type[BaseModel], what: str) -> str:
    """One line for a failed :class:`ParamModel`: ``what: field: problem (expected <range and unit>)``."""
    message = describe_validation_error(exc, what).replace(f"{what}: (top level): ", f"{what}: ", 1)
    errors = exc.errors()
    first = errors[0] if errors else {}
    if first.get("type") == "extra_forbidden":
        return message.replace("Extra inputs are not permitted", "unknown key")
    owner, name = _field_at(model, first.get("loc", ()))
    if name is not None and first.get("type") not in ("value_error", "frozen_instance"):
        value, each, _ = _field_parts(owner, name)
        if value or each:
            return f"{message} (expected {field_range_text(owner, name)})"
    return message


def _field_at(model: type[BaseModel], loc: tuple) -> tuple[type[BaseModel], str | None]:
    """The model and field name an error location points at, through nested models (``table.material.albedo``)
    and lists of them (``clutter.0.size.2``); ``None`` for the name where it does not end on a field."""
    owner, name = model, None
    for part in loc:
        if name is not None:  # inside field ``name``: a nested model (maybe in a list or optional) or an element
            inner = [a for a in _flat_args(owner.model_fields[name].annotation)
                     if isinstance(a, type) and issubclass(a, BaseModel)]
            if not inner:
                return owner, name  # an element of a vector
            owner, name = inner[0], None
        if isinstance(part, str) and part in owner.model_fields:
            name = part
        elif not isinstance(part, int):
            return owner, None
    return owner, name


def _flat_args(ann) -> list:
    """``ann`` and every type inside it (``list[X]``, ``X | None``, ``Annotated[X, ...]``)."""

    out = [ann]
    for arg in typing.get_args(ann):
        out += _flat_args(arg)
    return out


def _plain(value: Any) -> Any:
    """NumPy scalars and arrays (set in code, not read from files) as plain Python numbers and lists."""
    if hasattr(value, "tolist") and not isinstance(value, (list, tuple)):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [v.item() if hasattr(v, "item") and not isinstance(v, (list, tuple)) else v for v in value]
    return value


def _json_name(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null",
            int: "a number", float: "a number"}.get(type(value), type(value).__name__)


__all__ = ["ConfigModel", "ParamModel", "vector", "field_constraints", "field_range", "FieldRange", "field_interval", "field_range_text",
           "range_message", "field_like", "read_json", "write_json", "parse_config", "read_config_file", "load_config", "toml_reader",
           "describe_validation_error", "printable", "CONTROL_CATEGORIES"]
