"""Shared fixtures: the real sweep shipped in tests/data and small synthetic frame sets."""

from __future__ import annotations

from pathlib import Path

import pytest

DATA = Path(__file__).parent / "data"
SWEEP = DATA / "tmf8820_ur5_sweep.json"


@pytest.fixture(scope="session")
def sweep_path() -> Path:
    """The 53-frame real TMF8820/UR5 sweep (MIT licence, see tests/data)."""
    assert SWEEP.is_file(), f"test data missing: {SWEEP}"
    return SWEEP


@pytest.fixture(scope="session")
def synthetic_frames():
    """Eight noisy synthetic frames with ground truth (forward model, published parameters)."""
    from place_safe.synthetic import make_frames

    return make_frames(8, seed=1)


@pytest.fixture()
def synthetic_file(tmp_path, synthetic_frames) -> Path:
    """The synthetic frames written as a JSON-list frame file."""
    from place_safe.frames import write_frames

    path = tmp_path / "synthetic.json"
    write_frames(path, synthetic_frames)
    return path
