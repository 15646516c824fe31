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
