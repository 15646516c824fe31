"""A computation alongside the caller: the child's value is the inline one, its exception comes back, an unwanted
child is stopped and leaves nothing behind, and what cannot go to a child runs inline."""

import math
import os
import time
from pathlib import Path

import pytest

from place_safe.calibration.alongside import Alongside, spare_cores


def test_the_child_returns_what_the_call_inline_returns():
    with Alongside(math.comb, 40, 20, parallel=True) as job:
        assert job._proc is not None  # a child runs
        assert job.result() == math.comb(40, 20) and job.result() == math.comb(40, 20)
        assert job._proc is None  # and is done
    with Alongside(math.comb, 40, 20, parallel=False) as job:
        assert job._proc is None and job.result() == math.comb(40, 20)


@pytest.mark.parametrize("parallel", [True, False])
def test_the_functions_exception_is_raised_again(parallel):
    with Alongside(math.sqrt, -1.0, parallel=parallel) as job:
        with pytest.raises(ValueError, match="math domain error"):
            job.result()


def test_an_unwanted_child_is_stopped_and_its_files_removed():
    t0 = time.perf_counter()
    with Alongside(time.sleep, 60.0, parallel=True) as job:
        proc, where = job._proc, Path(job._dir.name)
        assert proc.poll() is None and where.is_dir()
    assert proc.poll() is not None and not where.exists() and time.perf_counter() - t0 < 30.0


def test_what_cannot_be_pickled_runs_inline():
    with Alongside(lambda x: x + 1, 41, parallel=True) as job:
        assert not job.parallel and job._proc is None and job.result() == 42


def test_a_child_that_ends_without_a_result_is_said(monkeypatch):
    with Alongside(os._exit, 3, parallel=True) as job:
        with pytest.raises(RuntimeError, match="without a result .exit code 3"):
            job.result()


def test_spare_cores_is_the_cores_less_one():
    assert spare_cores() == max(len(os.sched_getaffinity(0)) - 1, 0)
