"""Config helpers: unknown keys and unreadable files give clear errors of the caller's type."""

from dataclasses import dataclass

import pytest

from place_safe.config import check_keys, read_json, write_json
from place_safe.exceptions import CalibrationError


@dataclass
class Sample:
    speed: float = 0.1
    count: int = 3


def test_round_trip(tmp_path):
    write_json(tmp_path / "s.json", {"speed": 0.2})
    d = check_keys(Sample, read_json(tmp_path / "s.json", "sample"), "sample")
    assert Sample(**d) == Sample(speed=0.2)


def test_unknown_keys_name_the_expected_ones():
    with pytest.raises(ValueError, match=r"sample: unknown keys \['sped'\]; expected some of \['count', 'speed'\]"):
        check_keys(Sample, {"sped": 1}, "sample")


def test_not_an_object_and_error_type():
    with pytest.raises(CalibrationError, match="must be a JSON object, got list"):
        check_keys(Sample, [1], "sample", CalibrationError)


def test_unreadable_files(tmp_path):
    with pytest.raises(ValueError, match="cannot read sample"):
        read_json(tmp_path / "missing.json", "sample")
    (tmp_path / "bad.json").write_text("{nope")
    with pytest.raises(CalibrationError, match="not JSON"):
        read_json(tmp_path / "bad.json", "sample", CalibrationError)


# -- range tables (Bound) for the parameter dataclasses ------------------------------------------------
from dataclasses import dataclass, field  # noqa: E402

from place_safe.config import Bound, check_dataclass, dataclass_from_dict  # noqa: E402
from place_safe.exceptions import ConfigError  # noqa: E402


@dataclass
class _Params:
    gain: float = 1.0
    count: int = 3
    offsets: list[float] = field(default_factory=lambda: [0.0, 0.0])
    label: str | None = None
    new_field: float = 0.5  # no bound: still must be a finite number


_BOUNDS = {"gain": Bound(0.0, 10.0, "(ratio)", lo_open=True), "count": Bound(1, 9, "frames"),
           "offsets": Bound(-1.0, 1.0, "m", length=2)}


@pytest.mark.parametrize("d, words", [
    ({"gain": 0.0}, "gain: Input should be greater than 0 (expected 0 < value <= 10 (ratio))"),
    ({"gain": True}, "gain: Input should be a valid number"),
    ({"gain": "2"}, "gain: Input should be a valid number"),
    ({"count": 2.5}, "count: Input should be a valid integer"),
    ({"offsets": [0.0]}, "offsets: List should have at least 2 items"),
    ({"offsets": [0.0, 2.0]}, "offsets.1: Input should be less than or equal to 1"),
    ({"new_field": float("nan")}, "new_field: Input should be a finite number"),
    ({"label": 3}, "label: Input should be a valid string"),
    ({"gian": 1.0}, "gian: unknown key"),
])
def test_range_tables_give_one_line_naming_the_field(d, words):
    with pytest.raises(ConfigError) as info:
        dataclass_from_dict(_Params, d, _BOUNDS, "params")
    assert str(info.value).startswith("params: ") and words in str(info.value) and "\n" not in str(info.value)


def test_range_tables_accept_good_values_and_check_instances():
    p = dataclass_from_dict(_Params, {"gain": 2, "offsets": [0.5, -0.5], "label": "x"}, _BOUNDS, "params")
    assert (p.gain, p.count, p.offsets, p.label) == (2, 3, [0.5, -0.5], "x")
    check_dataclass(p, _BOUNDS, "params")
    p.gain = -1.0
    with pytest.raises(ConfigError, match="gain"):
        check_dataclass(p, _BOUNDS, "params")
