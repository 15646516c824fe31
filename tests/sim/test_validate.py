"""Simulated frames against the real sweep (place_safe.sim.validate and ``place-safe sim validate``)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("mujoco")

from place_safe.cli import main  # noqa: E402
from place_safe.sim.validate import CORR_TARGET, PEAK_TARGET, shape_correlation, subbin_peak  # noqa: E402

SWEEP = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"


def test_subbin_peak_and_correlation_on_known_shapes():
    bins = np.arange(128)
    g = np.exp(-0.5 * ((bins - 40.3) / 1.5) ** 2)
    h = np.stack([100 + 1e4 * g, 100 + 1e4 * np.roll(g, 5)])
    np.testing.assert_allclose(subbin_peak(h), [40.3, 45.3], atol=0.05)
    assert shape_correlation(h, h).min() == pytest.approx(1.0)
    assert shape_correlation(h[[1, 0]], h).max() < 0.5


def test_simulated_frames_match_the_real_sweep(capsys):
    assert main(["sim", "validate", str(SWEEP), "--json", "--strict"]) == 0
    out = json.loads(capsys.readouterr().out)
    zones = out["zones"]
    assert out["frames"] >= 40 and out["passed"]
    assert max(zones["peak_mean"]) <= PEAK_TARGET
    assert min(zones["corr_mean"]) >= CORR_TARGET


def test_validate_rejects_a_file_without_usable_frames(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("[]")
    assert main(["sim", "validate", str(bad)]) == 2
