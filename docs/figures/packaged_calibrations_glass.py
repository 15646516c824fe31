"""Do the packaged simulated calibrations (made before the simulator rendered the internal return) still suit it?

    MUJOCO_GL=egl python docs/figures/packaged_calibrations_glass.py [N]

Each simulated sensor (nominal; mismatched, seed 7 as in the scenarios) looks at a level or tilted table from N
(default 24) poses, 5-40 cm and 0-12 deg (seeded), once with the simulator's true parameters (internal return
rendered) and once with its glass gains set to 0 (as before), the same noise seed. Each frame is read by peak and
diff with the packaged user calibration (``sim/sensors/calibration_<sensor>.json``). Prints per sensor and method the
mean and 95th percentile tilt error (deg), the mean NEES per degree of freedom (tilt and offset, 3) and that of the
tilt alone (2), the mean offset error (mm) and the share of frames diff answered with peak's plane.
"""

import math
import sys

import numpy as np

from place_safe.evaluation.metrics import angular_error, nees
from place_safe.recovery import make_estimator
from place_safe.recovery.estimator import tilt_offset
from place_safe.sim.scene import SceneConfig, TableConfig, build_scene
from place_safe.sim.tof import SimToF, ToFConfig, simulated_calibration, true_params
from place_safe.sim.tof_mismatch import MismatchConfig, MismatchedToF

H = 0.75


def frames(sensor: str, glass: bool, n: int) -> list:
    rng = np.random.default_rng(5)
    p = true_params()
    if not glass:
        p = p.model_copy(update={"glass_gains": [0.0] * 9})
    out = []
    for i in range(n):
        gap = float(rng.uniform(0.05, 0.40))
        tilt = float(rng.uniform(0.0, 12.0)) if i % 2 else 0.0
        table = TableConfig(height=H, center=(0.0, 0.0), size=(1.5, 1.5, 0.04), tilt=math.radians(tilt),
                            tilt_direction=float(rng.uniform(0, 2 * math.pi)))
        scene = build_scene(SceneConfig(table=table, rig_pos=(0.0, 0.0, H + gap), rig_euler=(math.pi, 0.0, 0.0)))
        cfg = ToFConfig(seed=100 + i)
        tof = (SimToF(scene, config=cfg, params=p) if sensor == "nominal"
               else MismatchedToF(scene, config=cfg, mismatch=MismatchConfig(), params=p))
        f = tof.measure()
        if f.truth is not None:
            out.append(f)
    return out


def main(n: int = 24) -> None:
    print("sensor    glass  method  frames  tilt err mean  p95 (deg)  NEES/dof (3)  tilt NEES/dof (2)  offset err (mm)"
          "  answered by peak")
    for sensor in ("nominal", "mismatch"):
        cal = simulated_calibration(sensor)
        for glass in (False, True):
            fr = frames(sensor, glass, n)
            for method in ("peak", "diff"):
                est = make_estimator(method, cal)
                es = [est.estimate(f) for f in fr]
                err = np.array([math.degrees(angular_error(e.plane, f.truth)) if e.ok else np.nan
                                for e, f in zip(es, fr)])
                ne = nees(es, [f.truth for f in fr])
                dev = np.array([tilt_offset(e.plane) - tilt_offset(f.truth) for e, f in zip(es, fr)])
                tilt = np.mean([d[:2] @ np.linalg.solve(e.covariance[:2, :2], d[:2]) / 2.0 for d, e in zip(dev, es)])
                by_peak = np.mean([(e.method_used or method) == "peak" for e in es])
                print(f"{sensor:9s} {'on' if glass else 'off':5s}  {method:6s} {len(fr):6d}  {np.nanmean(err):13.3f}"
                      f"  {np.nanpercentile(err, 95):9.3f}  {np.nanmean(ne):12.2f}  {tilt:16.2f}"
                      f"  {1000 * np.mean(dev[:, 2]):+15.2f}  {by_peak:16.2f}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:2]))
