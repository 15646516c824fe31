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
