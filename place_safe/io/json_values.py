"""Plain JSON values from what fits and runs report (NumPy arrays and scalars, dataclasses, objects with
``to_dict``): one conversion for every JSON file and JSON line place_safe writes from such reports."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np


def jsonable(obj: Any) -> Any:
    """``obj`` as plain JSON values: dicts (keys as strings), lists, numbers, strings, booleans and None.

    NumPy arrays and scalars become lists and numbers, dataclasses and objects with ``to_dict`` their dicts,
    non-finite floats None (JSON has no NaN), anything else its ``str``."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return jsonable(obj.item())
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj))
    if hasattr(obj, "to_dict"):
        return jsonable(obj.to_dict())
    if obj is None or isinstance(obj, (str, int, bool)):
        return obj
    return str(obj)



class DuplicateKey(ValueError):
    """A key given twice in one JSON object (``args[0]``: the key)."""


def unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """A JSON object's dict, refusing a key given twice (``object_pairs_hook`` of :func:`json.loads`): Python's reader
    keeps the last value silently, so a file edited by hand with ``"chi2_limit"`` twice would use whichever came last,
    unseen, and a frame with ``"hists"`` twice another frame's histograms."""
    out: dict[str, Any] = {}
    for key, value in pairs:
        if key in out:
            raise DuplicateKey(key)
        out[key] = value
    return out


__all__ = ["jsonable", "DuplicateKey", "unique_keys"]
