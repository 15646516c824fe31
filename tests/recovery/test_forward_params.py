"""The forward model's parameters (``recovery.forward_params``): round trips, refusals, and that they need no torch."""

from __future__ import annotations

import math
import subprocess
import sys

import pytest

from place_safe.exceptions import CalibrationError
from place_safe.recovery.forward_params import ForwardParams


def test_the_parameters_load_without_torch_and_are_the_models():
    """A ``forward`` section is read and checked without importing torch, and ``recovery.forward`` names the same
    class."""
    code = ("import sys; from place_safe.recovery.forward_params import ForwardParams; "
            "ForwardParams.from_dict({'albedo': 2.0, 'zone_offsets': [0.1] * 9}); print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=300)
    assert out.stdout.strip() == "False", out.stderr
    from place_safe.recovery import forward

    assert forward.ForwardParams is ForwardParams


def test_params_round_trip(tmp_path):
    from place_safe.recovery.forward import params_to_tensors

    p = ForwardParams(albedo=2.0, zone_offsets=[0.1] * 9, pileup=1e-7)
    p.save(tmp_path / "p.json")
    assert ForwardParams.load(tmp_path / "p.json") == p
    assert set(params_to_tensors(p)) >= {"albedo", "zone_offsets", "pileup"}


def test_params_reject_bad_values(tmp_path):
    with pytest.raises(CalibrationError):
        ForwardParams(bin_size=-1.0)
    with pytest.raises(CalibrationError):
        ForwardParams(zone_offsets=[0.0] * 3)
    with pytest.raises(CalibrationError):
        ForwardParams.from_dict({"albedo": 1.0, "nonsense": 2})
    with pytest.raises(CalibrationError):
        ForwardParams(albedo=math.nan)
    (tmp_path / "bad.json").write_text("{not json")
    with pytest.raises(CalibrationError):
        ForwardParams.load(tmp_path / "bad.json")
