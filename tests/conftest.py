"""Shared fixtures (the real sweep shipped in tests/data, small synthetic frame sets) and test tiers.

Tiers (markers, registered in pyproject.toml): every test is ``fast`` unless it is marked ``sim``
(needs MuJoCo; every test under ``tests/sim`` is) or ``slow`` (more than a few seconds).
``python -m pytest -q -n auto --maxprocesses 4`` (the README's command: pytest-xdist, a worker per core up to 4,
each loading torch; without ``-n`` in one process)
runs all tiers; ``-m fast`` or ``-m "not slow"`` pick a quick subset.
Torch's intra-op threads are pinned (``PLACE_SAFE_TEST_THREADS``, default 1) so results and run
time do not depend on how busy the machine is. No test asserts a speed: speeds belong to
``place-safe bench recovery`` / ``place-safe bench sim``.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path

import pytest

#: Test doubles shared by several test folders (``from placement_fakes import ...``).
sys.path.insert(0, str(Path(__file__).resolve().parent / "support"))

os.environ.setdefault("MUJOCO_GL", "egl")


def pytest_configure(config) -> None:
    import torch
    from hypothesis import settings

    # No per-example deadline anywhere: the machines are shared, and a slow example is not a failure of the
    # code (tests assert behaviour, benchmarks measure time). CI (CI=true) searches the same examples on every
    # run, so a red build is reproducible; a developer's run explores new ones (and keeps failures in .hypothesis/).
    settings.register_profile("default", deadline=None)
    settings.register_profile("ci", deadline=None, derandomize=True, print_blob=True)
    settings.load_profile("ci" if os.environ.get("CI", "").lower() in ("1", "true", "yes") else "default")

    torch.set_num_threads(int(os.environ.get("PLACE_SAFE_TEST_THREADS", "1")))


def pytest_collection_modifyitems(config, items) -> None:
    for item in items:
        path = Path(str(item.fspath))
        if "sim" in path.parts[-2:-1] and not item.get_closest_marker("sim"):
            item.add_marker(pytest.mark.sim)
        if not (item.get_closest_marker("sim") or item.get_closest_marker("slow")):
            item.add_marker(pytest.mark.fast)

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
    from place_safe.evaluation.synthetic import make_frames

    return make_frames(8, seed=1)


@pytest.fixture()
def synthetic_file(tmp_path, synthetic_frames) -> Path:
    """The synthetic frames written as a JSON-list frame file."""
    from place_safe.io.frame_file import write_frames

    path = tmp_path / "synthetic.json"
    write_frames(path, synthetic_frames)
    return path


@pytest.fixture()
def sigint_raises():
    """SIGINT raises KeyboardInterrupt for the test, as in a command run from a terminal: a test run in the background
    (``nohup``, a CI job started with ``&``) inherits SIGINT ignored, and Python then keeps it ignored."""
    import signal

    before = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, before)
