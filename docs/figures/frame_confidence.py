"""Each frame's plane in a simulated placement against the simulator's truth: error against stated uncertainty.

    python docs/figures/frame_confidence.py scenarios/set/level_20cm.toml scenarios/set/checker_table.toml

Runs each scenario file once (seed 0, as ``place-safe scenarios`` runs the set) and records every plane the loop
offers the fusion (``PlaneFilter.update``), in the base frame. For a level table (``tilt = 0``) a plane's tilt is its
error. Prints, by the frame's range (the plane's distance along the optical axis), the number of planes, their mean
tilt error (deg), the median tilt standard deviation they state (deg, the worst axis of their covariance) and
the mean of (error / stated)^2 / 2, a normalised error per degree of freedom (about 1 when honest; taken
on the worst axis, so a lower bound); then the same with the calibration's reference error added to each plane's
(``PlaneFilter.reference_tilt_std``: the table the calibration was captured against was touched, and every plane
shares the touch's error; fusion adds it once). docs/results.md, "A zone that saw two surfaces stays out from about
the same pose", "The calibration's reference".
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from place_safe.fusion import plane_filter
from place_safe.sim.placement_run import run_placement
from place_safe.sim.scenario import load_scenario

BANDS = ((0.15, 0.5), (0.08, 0.15), (0.0, 0.08))  # m, ranges along the optical axis


def planes_offered(path: str) -> tuple[str, np.ndarray]:
    """(decision, rows of (range m, tilt deg, stated tilt std deg, the reference's tilt std deg)) of one run of a
    scenario file."""
    rows: list[tuple[float, float, float, float]] = []
    update = plane_filter.PlaneFilter.update

    def recording(self, estimate, base_T_sensor, stamp):
        plane = getattr(estimate, "plane", None)
        std = getattr(estimate, "tilt_std", None)
        s = std() if callable(std) else None
        if plane is not None and s is not None:
            n, _, _ = plane_filter.plane_to_base(plane, base_T_sensor)
            rows.append((float(plane.z0), math.degrees(math.acos(min(1.0, abs(float(n[2]))))), math.degrees(s),
                         math.degrees(self.reference_tilt_std)))
        return update(self, estimate, base_T_sensor, stamp)

    plane_filter.PlaneFilter.update = recording
    try:
        res = run_placement(load_scenario(path), seed=0, seconds=30.0, log_frames=False)
    finally:
        plane_filter.PlaneFilter.update = update
    return f"{res.outcome}: {res.reason[:90]}", np.asarray(rows, dtype=float).reshape(-1, 4)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scenarios", nargs="+", help="scenario files of level tables (tilt 0)")
    for path in ap.parse_args().scenarios:
        if load_scenario(path).scene.get("table", {}).get("tilt", 0.0) not in (0, 0.0):
            print(f"{path}: not a level table; the tilt read is not the error")
            continue
        decision, rows = planes_offered(path)
        print(f"{path}: {decision}")
        for lo, hi in BANDS:
            m = (rows[:, 0] >= lo) & (rows[:, 0] < hi)
            if m.any():
                err, std, ref = rows[m, 1], rows[m, 2], rows[m, 3]
                both = np.hypot(std, ref)
                print(f"  {lo * 100:2.0f}-{hi * 100:2.0f} cm: {int(m.sum()):3d} planes, error {err.mean():.2f} deg, "
                      f"stated {np.median(std):.3f} deg, (error / stated)^2 / 2 = {np.mean((err / std) ** 2) / 2:.1f}; "
                      f"with the reference's {np.median(ref):.3f} deg: {np.mean((err / both) ** 2) / 2:.2f}")


if __name__ == "__main__":
    main()
