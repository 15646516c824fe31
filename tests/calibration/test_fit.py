"""fit_method: the unit model is a choice of the diff fit only, and only a known one."""

import pytest

from place_safe.calibration import UNIT_MODELS, Calibration
from place_safe.calibration.fit import fit_method


def test_the_unit_models_offered():
    assert UNIT_MODELS[0] == "default" and "staged" in UNIT_MODELS


@pytest.mark.parametrize("method, unit_model", [("diff", "learned"), ("peak", "staged"), ("proprietary", "staged")])
def test_an_unknown_unit_model_or_one_for_another_method_is_refused_before_any_fit(method, unit_model):
    cal = Calibration()
    with pytest.raises(ValueError, match="unit model"):
        fit_method(cal, [], method, unit_model=unit_model)
    assert not cal.sections
