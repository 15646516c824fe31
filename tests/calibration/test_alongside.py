"""A computation alongside the caller: the child's value is the inline one, its exception comes back, an unwanted or
orphaned child is stopped and leaves nothing behind, and whatever keeps a child from giving the outcome runs the call
inline."""

import math
import os
import threading
import time
from pathlib import Path

import pytest

from place_safe.calibration.alongside import Alongside, spare_cores


def _exit_if_alongside(code: int) -> str:
    """Ends the process with ``code`` when it is the child alongside; inline, says so."""
    import __main__
    if getattr(getattr(__main__, "__spec__", None), "name", "") == "place_safe.calibration.alongside":
        os._exit(code)
    return "inline"


def test_the_child_returns_what_the_call_inline_returns():
    with Alongside(math.comb, 40, 20, parallel=True) as job:
        assert job._proc is not None  # a child runs
        assert job.result() == math.comb(40, 20) and job.result() == math.comb(40, 20)
        assert job._proc is None and job.why_inline is None  # and is done
    with Alongside(math.comb, 40, 20, parallel=False) as job:
        assert job._proc is None and job.result() == math.comb(40, 20) and job.why_inline == "no spare core"


@pytest.mark.parametrize("parallel", [True, False])
def test_the_functions_exception_is_raised_again(parallel):
    with Alongside(math.sqrt, -1.0, parallel=parallel) as job:
        with pytest.raises(ValueError, match="math domain error") as info:
            job.result()
    if parallel:  # with the child's traceback
        assert any("in the process alongside" in n for n in getattr(info.value, "__notes__", []))


def test_an_unwanted_child_is_stopped_and_its_files_removed():
    t0 = time.perf_counter()
    with Alongside(time.sleep, 60.0, parallel=True) as job:
        proc, where = job._proc, job._dir
        assert proc.poll() is None and where.is_dir()
    assert proc.poll() is not None and not where.exists() and time.perf_counter() - t0 < 30.0


def test_a_child_whose_caller_is_gone_ends_and_removes_its_files():
    job = Alongside(time.sleep, 60.0, parallel=True).__enter__()
    proc, where = job._proc, job._dir
    time.sleep(0.5)
    proc.stdin.close()  # what the caller's end does when it is killed
    for _ in range(100):
        if proc.poll() is not None and not where.exists():
            break
        time.sleep(0.1)
    assert proc.poll() is not None and not where.exists()
    job._proc = None
    job.__exit__(None, None, None)


def test_what_cannot_go_to_a_child_runs_inline():
    with Alongside(lambda x: x + 1, 41, parallel=True) as job:  # not picklable
        assert job._proc is None and "not picklable" in job.why_inline and job.result() == 42
    with Alongside(_exit_if_alongside, 3, parallel=True) as job:  # the child dies
        assert job.result() == "inline" and "exit code 3" in job.why_inline
    with Alongside(threading.Lock, parallel=True) as job:  # its value cannot come back
        assert isinstance(job.result(), type(threading.Lock())) and "without a usable result" in job.why_inline


def test_no_temporary_directory_or_interpreter_runs_inline(monkeypatch):
    import sys
    import tempfile

    def no_dir(**kw):
        raise PermissionError("read-only")

    monkeypatch.setattr(tempfile, "mkdtemp", no_dir)
    with Alongside(math.comb, 10, 3, parallel=True) as job:
        assert job._proc is None and "PermissionError" in job.why_inline and job.result() == 120
    monkeypatch.undo()
    monkeypatch.setattr(sys, "executable", "")
    with Alongside(math.comb, 10, 3, parallel=True) as job:
        assert job._proc is None and "interpreter" in job.why_inline and job.result() == 120


def test_spare_cores_is_the_cores_less_one():
    n = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    assert spare_cores() == max(n - 1, 0)
