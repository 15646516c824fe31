"""Config helpers: files read with one-line errors, and the parameter models (ParamModel) declared once with their
ranges: validation, the one-line messages naming field and range, and the file form (to_dict / from_dict)."""

from __future__ import annotations

import math
import typing
from typing import ClassVar, Optional

import pytest
from hypothesis import HealthCheck, assume, given, settings, strategies as st
from pydantic import Field, model_validator

from place_safe.config import (ParamModel, _field_parts, _flat_args, field_interval, field_range_text, read_json,
                               vector, write_json)
from place_safe.exceptions import CalibrationError, ConfigError


def test_unreadable_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read sample"):
        read_json(tmp_path / "missing.json", "sample")
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(CalibrationError, match="not JSON"):
        read_json(tmp_path / "bad.json", "sample", CalibrationError)


# -- a parameter model, declared once -------------------------------------------------------------------
class _Inner(ParamModel):
    what: ClassVar[str] = "inner"

    size: vector(3, gt=0.0, le=5.0) = Field(default_factory=lambda: [1.0, 1.0, 1.0], description="m")


class _Params(ParamModel):
    what: ClassVar[str] = "params"

    gain: float = Field(1.0, gt=0.0, le=10.0, description="(ratio)")
    count: int = Field(3, ge=1, le=9, description="frames")
    offsets: vector(2, ge=-1.0, le=1.0) = Field(default_factory=lambda: [0.0, 0.0], description="m")
    label: Optional[str] = None
    new_field: float = 0.5  # no range: still must be a finite number
    inner: _Inner = Field(default_factory=_Inner)
    items: list[_Inner] = Field(default_factory=list)

    @model_validator(mode="after")
    def _gain_over_count(self) -> "_Params":
        if self.gain > 3 * self.count:
            raise ValueError("gain must not exceed 3 * count")
        return self


def test_round_trip(tmp_path):
    p = _Params(gain=2, offsets=(0.5, -0.5), label="x", items=[_Inner(size=[1, 2, 3])])
    write_json(tmp_path / "s.json", p.to_dict())
    back = _Params.from_dict(read_json(tmp_path / "s.json", "params"))
    assert back == p and back.to_dict() == p.to_dict() and back.offsets == [0.5, -0.5]


@pytest.mark.parametrize("d, words", [
    ({"gain": 0.0}, "params: gain: Input should be greater than 0 (expected 0 < value <= 10 (ratio))"),
    ({"gain": True}, "params: gain: Input should be a valid number"),
    ({"gain": "2"}, "params: gain: Input should be a valid number"),
    ({"count": 2.5}, "params: count: Input should be a valid integer (expected 1 <= value <= 9 frames)"),
    ({"offsets": [0.0]}, "params: offsets: List should have at least 2 items"),
    ({"offsets": [0.0, 2.0]}, "params: offsets.1: Input should be less than or equal to 1 (expected -1 <= value <= 1 m)"),
    ({"new_field": float("nan")}, "params: new_field: Input should be a finite number"),
    ({"label": 3}, "params: label: Input should be a valid string"),
    ({"gian": 1.0}, "params: gian: unknown key"),
    ({"inner": {"size": [1, 1, 9]}}, "params: inner.size.2: Input should be less than or equal to 5 (expected 0 < value"),
    ({"items": [{}, {"sise": 1}]}, "params: items.1.sise: unknown key"),
    ({"gain": 10.0, "count": 1}, "params: gain must not exceed 3 * count"),
    ([1], "params must be a JSON object, got a list"),
    ({3: 1}, "params: 3: unknown key"),
])
def test_one_line_naming_the_field_and_range(d, words):
    with pytest.raises(ConfigError) as info:
        _Params.from_dict(d)
    assert words in str(info.value) and "\n" not in str(info.value)


def test_file_name_in_messages_and_error_type():
    with pytest.raises(ConfigError, match=r"^params p\.json: gain: "):
        _Params.from_dict({"gain": -1}, "params p.json")

    class Cal(_Params):
        error: ClassVar[type[Exception]] = CalibrationError

    with pytest.raises(CalibrationError, match="count"):
        Cal(count=0)


def test_dataclass_manners_positional_replace_equality_assignment():
    import numpy as np

    p = _Params(2.0, 4)
    assert (p.gain, p.count) == (2.0, 4)
    with pytest.raises(ConfigError, match="gain: given twice"):
        _Params(2.0, gain=3.0)
    q = p.replace(count=5)
    assert q.count == 5 and p.count == 4 and q != p and p.replace() == p
    with pytest.raises(ConfigError, match="count"):
        p.replace(count=0)
    p.offsets = np.array([0.25, -0.25])  # NumPy set in code: plain numbers
    assert p.offsets == [0.25, -0.25] and type(p.offsets[0]) is float
    with pytest.raises(ConfigError, match=r"params: gain: .*expected 0 < value <= 10"):
        p.gain = 11.0
    assert p.gain == 2.0


def test_field_ranges_are_readable():
    assert field_interval(_Params, "gain") == (0.0, 10.0)
    assert field_interval(_Params, "offsets") == (-1.0, 1.0)
    assert field_interval(_Params, "new_field") == (-math.inf, math.inf)
    assert field_range_text(_Params, "count") == "1 <= value <= 9 frames"


# -- every converted model: round trip, and one line naming the field for an out-of-range value ---------------
def _models() -> list[type[ParamModel]]:
    from place_safe.calibration.capture import SweepPlan
    from place_safe.placement.config import PlacementConfig
    from place_safe.recovery.differentiable import RangeCorrection
    from place_safe.recovery.estimator import Uncertainty
    from place_safe.recovery.forward import ForwardParams
    from place_safe.recovery.points import PeakParams
    from place_safe.robot.contact_detector import DetectorSettings
    from place_safe.robot.interface import RobotLimits

    out = [PlacementConfig, ForwardParams, PeakParams, RangeCorrection, Uncertainty, SweepPlan, RobotLimits,
           DetectorSettings]
    try:
        from place_safe.sim.scene import ClutterItem, Material, SceneConfig, TableConfig
        from place_safe.sim.tof import DistanceMap, ToFConfig
    except ImportError:  # without the [sim] extra
        return out
    return out + [Material, TableConfig, ClutterItem, SceneConfig, DistanceMap, ToFConfig]


MODELS = _models()


def _default(model: type[ParamModel]) -> ParamModel:
    return model.default_peak() if model.__name__ == "PeakParams" else model()


def _numeric_fields(model: type[ParamModel]) -> list[str]:
    """Fields holding numbers or lists of numbers (not nested models, strings or flags)."""
    out = []
    for name, info in model.model_fields.items():
        types = _flat_args(info.annotation)
        if bool in types or str in types or any(isinstance(t, type) and issubclass(t, ParamModel) for t in types):
            continue
        if float in types or int in types:
            out.append(name)
    return out


def _is_vector(model, name) -> bool:
    return any(typing.get_origin(t) is list for t in _flat_args(model.model_fields[name].annotation))


def _is_int(model, name) -> bool:
    types = _flat_args(model.model_fields[name].annotation)
    return int in types and float not in types


def _value(draw, model, name):
    """A value of field ``name`` inside its range (a list of the allowed length for a vector)."""
    value, each, _ = _field_parts(model, name)
    c = each or value
    lo = c.get("ge", c.get("gt", -1e6))
    hi = c.get("le", c.get("lt", 1e6))
    lo, hi = max(lo, -1e6), min(hi, 1e6)
    if _is_int(model, name):
        number = st.integers(int(math.ceil(lo)) + ("gt" in c), int(math.floor(hi)) - ("lt" in c))
    else:
        number = st.floats(lo, hi, exclude_min="gt" in c, exclude_max="lt" in c, allow_nan=False)
    if _is_vector(model, name):
        n_lo, n_hi = value.get("min_length", 0), value.get("max_length", 12)
        return draw(st.lists(number, min_size=n_lo, max_size=min(n_hi, n_lo + 12)))
    return draw(number)


@st.composite
def _changed(draw, model):
    """A valid instance of ``model``: its default with one numeric field drawn inside its range."""
    name = draw(st.sampled_from(_numeric_fields(model)))
    d = _default(model).to_dict()
    d[name] = _value(draw, model, name)
    try:
        return model.from_dict(d)
    except model.error:  # a cross-field rule (ordering, table shape) the one change broke
        assume(False)


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.__name__)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.filter_too_much])
@given(data=st.data())
def test_every_model_round_trips(model, data):
    p = data.draw(_changed(model))
    back = model.from_dict(p.to_dict())
    assert back == p and back.to_dict() == p.to_dict()


@pytest.mark.parametrize("model", MODELS, ids=lambda m: m.__name__)
@settings(max_examples=25, deadline=None)
@given(data=st.data())
def test_every_model_rejects_out_of_range_in_one_line(model, data):
    bounded = [n for n in _numeric_fields(model) if any(k in (_field_parts(model, n)[1] or _field_parts(model, n)[0])
                                                        for k in ("ge", "gt", "le", "lt"))]
    name = data.draw(st.sampled_from(bounded))
    lo, hi = field_interval(model, name)
    beyond = data.draw(st.sampled_from([v for v in (lo, hi) if math.isfinite(v)]))
    bad = beyond + (1.0 + abs(beyond)) * (1 if beyond == hi else -1) * data.draw(st.floats(0.01, 10.0))
    if _is_int(model, name):
        bad = int(math.floor(bad)) if beyond == lo else int(math.ceil(bad))
    d = _default(model).to_dict()
    if _is_vector(model, name):
        n = max(_field_parts(model, name)[0].get("min_length", 1), 1)
        d[name] = [bad] * n
    else:
        d[name] = bad
    with pytest.raises(model.error) as info:
        model.from_dict(d)
    message = str(info.value)
    assert "\n" not in message and message.startswith(f"{model.what}: {name}") and "expected" in message


def test_a_robot_file_may_not_give_a_limit_as_a_boolean_or_text(tmp_path):
    """max_linear_speed = true read as 1.0 m/s (ten times real.toml's 0.1, the most allowed), "0.1" as 0.1: a
    configuration's numbers are numbers (a list of them too); booleans stay booleans."""
    import re
    from pathlib import Path

    from place_safe.drivers.ur5 import URConfig

    real = (Path(__file__).resolve().parents[1] / "robots" / "ur5" / "real.toml").read_text()
    assert URConfig.load(Path(__file__).resolve().parents[1] / "robots" / "ur5" / "real.toml")
    for value, kind in (("true", "a boolean"), ('"0.1"', "text")):
        f = tmp_path / "r.toml"
        f.write_text(re.sub(r"(?m)^max_linear_speed = .*$", f"max_linear_speed = {value}", real, count=1))
        with pytest.raises(ConfigError, match=f"max_linear_speed must be a number, not {kind}"):
            URConfig.load(f)
    f.write_text(re.sub(r"(?m)^workspace_min = \[(.*?),", r"workspace_min = [true,", real, count=1))
    with pytest.raises(ConfigError, match="workspace_min must be a number, not a boolean"):
        URConfig.load(f)


@pytest.mark.parametrize("value", ['"off"', '"no"', '"0"', "0", "1", '"yes"', '"low"'])
def test_a_switch_is_true_or_false_not_a_word_or_a_number(tmp_path, value):
    """pydantic read ``open_level = "off"`` (and "no", "0", 0) as false and "yes" as true: the gripper's output level
    that opens it, from a word (an adversarial round, session 74). A boolean field takes true or false only."""
    import re
    from pathlib import Path

    from place_safe.drivers.ur5 import URConfig

    sim = (Path(__file__).resolve().parents[1] / "robots" / "ur5" / "sim.toml").read_text()
    f = tmp_path / "r.toml"
    f.write_text(re.sub(r"(?m)^open_level = .*$", f"open_level = {value}", sim, count=1))
    assert f.read_text() != sim
    with pytest.raises(ConfigError, match="open_level must be true or false") as info:
        URConfig.load(f)
    assert "\n" not in str(info.value)
