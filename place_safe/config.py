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
    long) is one line naming the file.
    """
    text = _read_text(path, what, error)
    try:
        return json.loads(text)
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
    loc = ".".join(_printable(str(p)) for p in first.get("loc", ())) or "(top level)"
    msg = _printable(first.get("msg", "invalid")).removeprefix("Value error, ")
    more = f" (and {len(errors) - 1} more problem{'s' if len(errors) > 2 else ''})" if len(errors) > 1 else ""
    return f"{what}: {loc}: {msg}{more}"


def _printable(text: str) -> str:
    """``text`` on one line: control characters (newlines in a key, say) shown as escapes."""
    return text if text.isprintable() else text.encode("unicode_escape").decode("ascii")


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
    if Path(path).suffix.lower() != ".toml":
        return read_json(path, what, ConfigError)
    text = _read_text(path, what, ConfigError)
    try:
        try:
            import tomllib
        except ModuleNotFoundError:  # Python 3.10
            import tomli as tomllib  # type: ignore[no-redef]
        return tomllib.loads(text)
    except (ValueError, RecursionError) as exc:
        raise ConfigError(f"{what} {path}: not valid TOML "
                          f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None


def load_config(cls: type, path: str | Path, what: str | None = None):
    """Read ``path`` (JSON or TOML) and validate it as ``cls`` (a :class:`ConfigModel`); one-line errors."""
    what = what or cls.__name__
    return parse_config(cls, read_config_file(path, what), f"{what} {path}")


# ---------------------------------------------------------------------------------------------------
# Parameter sets with physical ranges: pydantic models whose Field constraints are the ranges
# ---------------------------------------------------------------------------------------------------
from typing import ClassVar  # noqa: E402

from pydantic import model_validator  # noqa: E402


class ParamModel(ConfigModel):
    """Base of a parameter set with physical ranges (robot limits, contact detector, simulated sensor, ...).

    Each field is declared once, as pydantic declares it: ``Annotated[float, Field(gt=0, le=3,
    description="m/s")]`` - the range as ``ge``/``gt``/``le``/``lt`` (on the elements of a vector, whose length
    is ``min_length``/``max_length``) and the unit as the description. Values are strict (a string or a
    boolean is not a number) and finite; NumPy numbers and arrays set in code are taken as plain numbers and
    lists. Every problem, on construction, :meth:`from_dict` or assignment, is one line of the class's
    :attr:`error` type: ``what: field: problem (expected lo < value <= hi unit)``. :meth:`to_dict` is the
    file form (the fields by name, as JSON values).
    """

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False, strict=True)

    #: what messages call it, and the exception they raise
    what: ClassVar[str] = "settings"
    error: ClassVar[type[Exception]] = ConfigError

    def __init__(self, **data: Any) -> None:  # pydantic calls it from model_validate too
        try:
            super().__init__(**data)
        except ValidationError as exc:
            raise self.error(range_message(exc, type(self), self.what)) from None

    def __setattr__(self, name: str, value: Any) -> None:
        try:
            super().__setattr__(name, value)
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
            raise cls.error(f"{what}: {_printable(str(odd))}: unknown key")
        try:
            return cls(**d)
        except cls.error as exc:  # the constructor's message, under this file's name
            raise cls.error(str(exc).replace(cls.what, what, 1) if what != cls.what else str(exc)) from None

    def to_dict(self) -> dict:
        """The file form: every field by name, as plain JSON values."""
        return self.model_dump(mode="json")


def _field_parts(model: type[BaseModel], name: str) -> tuple[dict, dict, str]:
    """(constraints on the value, constraints on each element of a vector, unit) of field ``name``."""
    import typing

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

    each: dict = {}
    ann = info.annotation
    for arg in typing.get_args(ann) or ():  # list[Annotated[float, Field(...)]] (optionally | None)
        inner = typing.get_args(arg) if typing.get_origin(arg) in (list, tuple) else (arg,)
        for el in inner:
            if typing.get_origin(el) is typing.Annotated:
                each = constraints(sum((getattr(m, "metadata", [m]) for m in typing.get_args(el)[1:]), []))
    return constraints(info.metadata), each, info.description or ""


def field_constraints(model: type[BaseModel], name: str) -> dict:
    """The range of scalar field ``name`` of ``model`` as pydantic keywords (``ge``, ``gt``, ``le``, ``lt``): for
    another model or a command-line option that takes the same quantity, so the range is written once."""
    value, _, _ = _field_parts(model, name)
    return {k: v for k, v in value.items() if k in ("ge", "gt", "le", "lt")}


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
    loc = first.get("loc", ())
    if loc and loc[0] in model.model_fields and first.get("type") not in ("value_error", "frozen_instance"):
        value, each, _ = _field_parts(model, str(loc[0]))
        if value or each:
            return f"{message} (expected {field_range_text(model, str(loc[0]))})"
    return message


# ---------------------------------------------------------------------------------------------------
# Physical ranges for the parameter dataclasses (forward model, peak mapping, placement, robot, scene)
# ---------------------------------------------------------------------------------------------------
from dataclasses import MISSING, dataclass  # noqa: E402
from functools import lru_cache  # noqa: E402
from typing import Annotated, Mapping  # noqa: E402

from pydantic import Field, create_model  # noqa: E402


@dataclass(frozen=True)
class Bound:
    """The physical range of one parameter: ``lo <= v <= hi`` (strict where ``lo_open``/``hi_open``).

    ``unit`` documents it (shown in messages); ``length`` fixes the number of values of a list
    parameter, whose every value must then be in the range. ``None`` for ``lo``/``hi`` is unbounded.
    """

    lo: float | None = None
    hi: float | None = None
    unit: str = ""
    lo_open: bool = False
    hi_open: bool = False
    length: int | None = None

    def describe(self) -> str:
        lo = "" if self.lo is None else f"{self.lo:g} {'<' if self.lo_open else '<='} "
        hi = "" if self.hi is None else f" {'<' if self.hi_open else '<='} {self.hi:g}"
        return f"{lo}value{hi}{' ' + self.unit if self.unit else ''}"

    def constraints(self) -> dict:
        c: dict = {"strict": True}
        if self.lo is not None:
            c["gt" if self.lo_open else "ge"] = self.lo
        if self.hi is not None:
            c["lt" if self.hi_open else "le"] = self.hi
        return c


def _field_spec(f, bound: Bound | None):
    """(annotation, FieldInfo) of a pydantic field for dataclass field ``f`` with its bound.

    The kind comes from the annotation (``float``, ``int``, ``bool``, ``str``, lists and tuples of
    numbers, each optionally ``| None``); other annotations (nested configs) are not checked here.
    """
    from typing import Any as _Any, Optional

    if f.default is not MISSING:
        default = f.default
    elif f.default_factory is not MISSING:  # type: ignore[misc]
        default = f.default_factory()  # type: ignore[misc]
    else:
        default = ...
    b = bound or Bound()
    desc = b.describe()
    t = f.type
    kind = (t if isinstance(t, str) else t.__name__ if isinstance(t, type) else str(t)).replace(" ", "")
    kind = kind.replace("typing.", "")
    optional = "None" in kind or default is None
    base = kind.replace("|None", "").replace("None|", "").replace("Optional[", "").rstrip("]") if optional else kind
    numeric_list = base.startswith(("list[float", "list[int", "tuple[float", "tuple[int"))
    if numeric_list:
        ann: _Any = list[Annotated[float, Field(**b.constraints())]]
        extra = {"min_length": b.length, "max_length": b.length} if b.length is not None else {}
        dflt = list(default) if isinstance(default, (list, tuple)) else default
        return (Optional[ann] if optional else ann), Field(default=dflt, description=desc, **extra)
    if base == "bool":
        ann = Annotated[bool, Field(strict=True)]
    elif base == "int":
        ann = Annotated[int, Field(**b.constraints())]
    elif base == "float":
        ann = Annotated[float, Field(**b.constraints())]
    elif base == "str":
        ann = Annotated[str, Field(strict=True)]
    else:
        ann = _Any
    return (Optional[ann] if optional else ann), Field(default=default, description=desc)


@lru_cache(maxsize=None)
def _model_for(cls: type, bounds_items: tuple) -> type[ConfigModel]:
    from dataclasses import fields as dc_fields

    bounds = dict(bounds_items)
    specs = {f.name: _field_spec(f, bounds.get(f.name)) for f in dc_fields(cls) if f.init}
    # nested configs (annotations that are other dataclasses) are validated by their own classes
    return create_model(f"{cls.__name__}Model", __base__=ConfigModel, **specs)  # type: ignore[call-overload]


def dataclass_model(cls: type, bounds: Mapping[str, Bound]) -> type[ConfigModel]:
    """The pydantic model that validates dataclass ``cls``: its fields, with ``bounds`` as constraints.

    Fields without a bound must still be finite numbers (or lists of them); new fields of ``cls``
    are picked up automatically, so adding a parameter means adding one line to its bounds table.
    """
    return _model_for(cls, tuple(sorted(bounds.items())))


def check_dataclass(obj: Any, bounds: Mapping[str, Bound], what: str, error: type[Exception] = ConfigError) -> None:
    """Raise ``error`` (one line naming ``what`` and the field) unless every field of ``obj`` is in range."""
    model = dataclass_model(type(obj), bounds)
    try:
        model.model_validate({f: _plain(getattr(obj, f)) for f in model.model_fields})
    except ValidationError as exc:
        raise error(_with_bounds(describe_validation_error(exc, what), exc, bounds)) from None


def dataclass_from_dict(cls: type, d: Any, bounds: Mapping[str, Bound], what: str,
                        error: type[Exception] = ConfigError):
    """An instance of dataclass ``cls`` from a JSON object, validated (unknown keys, types, ranges).

    Raises ``error`` with one line: ``what: field: problem (range)``.
    """
    if not isinstance(d, dict):
        raise error(f"{what} must be a JSON object, got {_json_name(d)}")
    model = dataclass_model(cls, bounds)
    try:
        values = model.model_validate(d)
    except ValidationError as exc:
        raise error(_with_bounds(describe_validation_error(exc, what), exc, bounds)) from None
    return cls(**{k: getattr(values, k) for k in d})


def _plain(value: Any) -> Any:
    """NumPy scalars and arrays (set in code, not read from files) as plain Python numbers and lists."""
    if hasattr(value, "tolist") and not isinstance(value, (list, tuple)):
        return value.tolist()
    if isinstance(value, (list, tuple)):
        return [v.item() if hasattr(v, "item") and not isinstance(v, (list, tuple)) else v for v in value]
    return value


def _with_bounds(message: str, exc: ValidationError, bounds: Mapping[str, Bound]) -> str:
    errors = exc.errors()
    loc = errors[0].get("loc", ()) if errors else ()
    name = loc[0] if loc else None
    if name in bounds and errors[0].get("type") != "extra_forbidden":
        return f"{message} (expected {bounds[name].describe()})"
    if errors and errors[0].get("type") == "extra_forbidden":
        return message.replace("Extra inputs are not permitted", "unknown key")
    return message


def _json_name(value: Any) -> str:
    return {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null",
            int: "a number", float: "a number"}.get(type(value), type(value).__name__)


__all__ = ["ConfigModel", "ParamModel", "field_constraints", "field_range_text", "range_message", "Bound", "check_keys", "read_json", "write_json", "parse_config", "read_config_file",
           "load_config", "describe_validation_error", "dataclass_model", "check_dataclass", "dataclass_from_dict"]
