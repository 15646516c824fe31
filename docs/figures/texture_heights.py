"""Can a frame tell a patterned table from a plain one by its zones' return heights? (Tried for a texture term in the
planes' covariance; not landed.)

    python docs/figures/texture_heights.py --frames 300      # about a minute

The nominal simulated sensor (its packaged calibration, the peak method) over a level table, plain or a checker
(albedo 1.0 / 0.2, 3 cm squares), from 3-40 cm (log-uniform) at random places, straight down. For each frame: the
plane's tilt error against the simulator's truth, the tilt standard deviation it states, and the zones' return
heights (counts above the floor) times their range squared, divided by each zone's own factor (the median over the
plain table's frames of its share of the frame's median): a per-zone albedo up to one scale. Prints, per range band,
the mean error, the median stated deviation, mean (error / stated)^2 / 2, and the correlation of the error with the
zones' spread (the coefficient of variation of those albedos), and the spread's percentiles on each table.
docs/results.md, "The calibration's reference".
"""
from __future__ import annotations

import argparse
import math

import numpy as np
from scipy.spatial.transform import Rotation

BANDS = ((0.03, 0.08), (0.08, 0.15), (0.15, 0.4))  # m, sensor to table


def frames_of(pattern: str, n: int, seed: int) -> dict[str, np.ndarray]:
    """Per frame: height (m), tilt error and stated std (deg), zone heights x range^2 and the valid mask."""
    from place_safe.calibration import Calibration
    from place_safe.recovery import make_estimator
    from place_safe.sensor.histogram import find_returns
    from place_safe.sim.scene import Material, SceneConfig, TableConfig, build_scene
    from place_safe.sim.tof import ToFConfig, calibration_file
    from place_safe.sim.tof_mismatch import make_sensor

    mat = Material(albedo=1.0, pattern="checker", square=0.03, albedo2=0.2) if pattern == "checker" else Material()
    cfg = SceneConfig(table=TableConfig(material=mat))
    scene = build_scene(cfg)
    data = scene.make_data()
    tof = make_sensor("nominal", scene, data, ToFConfig(seed=seed), None)
    peak = make_estimator("peak", Calibration.load(calibration_file("nominal")))
    p = peak.params
    rng = np.random.default_rng(seed)
    down = Rotation.from_euler("xyz", cfg.rig_euler).as_matrix()
    cx, cy = cfg.table.center
    out: dict[str, list] = {"h": [], "err": [], "std": [], "amp": [], "valid": []}
    for h in np.exp(rng.uniform(math.log(0.03), math.log(0.4), n)):
        scene.set_sensor_pose(data, np.array([cx + rng.uniform(-0.1, 0.1), cy + rng.uniform(-0.1, 0.1),
                                              cfg.table.height + h]), down)
        data.time += 1.0 / 30.0
        f = tof.measure()
        e = peak.estimate(f)
        if e.plane is None or f.truth is None:
            continue
        pos, _, valid, _, heights = find_returns(np.asarray(f.hists, float), p.pileup, p.subbin, p.subbin_half_width,
                                                 heights=True)
        r = np.linalg.norm(p.points(pos), axis=1)
        out["h"].append(h)
        out["err"].append(math.degrees(math.acos(min(1.0, float(e.plane.normal @ f.truth.normal)))))
        out["std"].append(math.degrees(e.tilt_std()))
        out["amp"].append(heights * r ** 2)
        out["valid"].append(valid)
    return {k: np.asarray(v) for k, v in out.items()}


def spread(d: dict[str, np.ndarray], factor: np.ndarray) -> np.ndarray:
    """The coefficient of variation of each frame's per-zone albedos (valid zones)."""
    a = np.where(d["valid"], d["amp"] / factor, np.nan)
    a = a / np.nanmedian(a, axis=1, keepdims=True)
    return np.nanstd(a, axis=1)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per table (default 300)")
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args()
    plain, checker = frames_of("uniform", a.frames, a.seed), frames_of("checker", a.frames, a.seed)
    share = np.where(plain["valid"], plain["amp"], np.nan)
    factor = np.nanmedian(share / np.nanmedian(share, axis=1, keepdims=True), axis=0)
    for name, d in (("plain", plain), ("checker", checker)):
        cv = spread(d, factor)
        print(f"{name}: zones' albedo spread (CV) 5/50/95 %: {np.round(np.percentile(cv, [5, 50, 95]), 3).tolist()}")
        for lo, hi in BANDS:
            m = (d["h"] >= lo) & (d["h"] < hi)
            e, s = d["err"][m], d["std"][m]
            print(f"  {lo * 100:2.0f}-{hi * 100:2.0f} cm: {int(m.sum()):3d} frames, error {e.mean():.3f} deg, stated "
                  f"{np.median(s):.3f}, (error / stated)^2 / 2 = {np.mean((e / s) ** 2) / 2:.1f}, correlation of the "
                  f"error with the spread {np.corrcoef(e, cv[m])[0, 1]:.2f}")


if __name__ == "__main__":
    main()
