"""The TMF8820 driver's fault property over many random fault schedules, beyond the dozen a test run draws.

    python docs/figures/driver_fault_schedules.py 0 3000        # schedules 0..2999 (about 10 minutes)

Schedule ``i`` is drawn from ``random.Random(i)``: 1-8 faults at bus transfers 150-2500, resets and bad checksums a
third as likely as the other kinds, and a frame seed 0-99. Each goes through the body of
``tests/drivers/test_tmf8820_driver.py::test_whatever_the_faults_frames_are_exact_or_the_source_says_why``; a
failing schedule is printed as the ``@example`` that pins it (docs/results.md, the sensor driver).
"""
from __future__ import annotations

import argparse
import random
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def schedule(i: int, kinds: list[str]) -> tuple[list[tuple[int, str]], int]:
    r = random.Random(i)
    weights = [1 if k in ("reset", "checksum") else 3 for k in kinds]
    events = [(r.randint(150, 2500), r.choices(kinds, weights)[0]) for _ in range(r.randint(1, 8))]
    return events, r.randint(0, 99)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("first", type=int)
    ap.add_argument("end", type=int)
    a = ap.parse_args()
    sys.path.insert(0, str(ROOT))
    import tests.drivers.test_tmf8820_driver as t
    from place_safe.drivers.tmf8820.registers import FAULT_KINDS

    body = t.test_whatever_the_faults_frames_are_exact_or_the_source_says_why.hypothesis.inner_test
    failed = 0
    for i in range(a.first, a.end):
        events, seed = schedule(i, list(FAULT_KINDS))
        try:
            body(events, seed)
        except AssertionError as exc:
            failed += 1
            print(f"schedule {i}: {exc!r}\n    @example(events={events}, seed={seed})", flush=True)
    print(f"{a.end - a.first} schedules, {failed} failed")


if __name__ == "__main__":
    main()
