"""Does surface texture within the zones' footprints scatter diff's tilt more than peak's?

A real calibration's forward model, with 20 x 20 rays a zone (the solver's are 6 x 6), renders a level table swept
5-40 cm below the sensor over one spot (60 frames, each with a real frame's reference histogram, Poisson noise
added), its albedo flat or textured: a smooth random field fixed on the table (40 plane waves of wavelengths 5-50
mm, unit variance, scaled to the given std). Diff's own plane (the same forward parameters and solver options, no
fallback: a model that fits but for the texture) and peak's (calibrated on an untextured level sweep of the same
model) are compared by their tilt's scatter about a cubic in 1 / z, deg per slope axis (docs/results.md, the unit
model, step 11).

    python docs/figures/texture_scatter.py CAL FRAMES STD [STD ...]      # e.g. cal_even.json odd.json 0 0.1 0.3
"""
from __future__ import annotations

import argparse
import copy
import math

import numpy as np
import torch

from place_safe.calibration import Calibration
from place_safe.calibration.fit import fit_method
from place_safe.geometry import Plane
from place_safe.io.frame_file import load_frames
from place_safe.recovery.differentiable import DifferentiableEstimator
from place_safe.recovery.estimator import Uncertainty, tilt_offset
from place_safe.recovery.forward import ForwardModel, ZoneRays
from place_safe.recovery.peak import PeakEstimator

#: rays per axis and zone of the rendering (the solver's: SolverOptions.rays)
RENDER_RAYS = 20
#: plane waves of the texture, and their wavelengths (m)
WAVES, WAVELENGTHS = 40, (0.005, 0.05)
#: frames of a sweep and its distances (m)
FRAMES, DISTANCES = 60, (0.05, 0.40)


class TexturedSweep:
    """Level-table sweeps of one sensor model over one textured spot."""

    def __init__(self, cal: Calibration, references: list, seed: int = 1) -> None:
        self.params = cal.forward()
        self.references = references
        self.model = ForwardModel(self.params, ZoneRays.stratified(RENDER_RAYS, dtype=torch.float64),
                                  dtype=torch.float64)
        self.dirs = self.model.ray_geometry()[0]
        rng = np.random.default_rng(seed)
        k = rng.normal(size=(WAVES, 2))
        k /= np.linalg.norm(k, axis=1, keepdims=True)
        self.k = k * (2 * math.pi / rng.uniform(*WAVELENGTHS, WAVES))[:, None]
        self.phase = rng.uniform(0, 2 * math.pi, WAVES)

    def texture(self, xy: np.ndarray, std: float) -> np.ndarray:
        """Albedo factor at table points ``xy`` (..., 2; m): mean 1, the given std, at least 0.05."""
        field = np.cos(xy @ self.k.T + self.phase).sum(-1) * math.sqrt(2.0 / WAVES)
        return np.clip(1.0 + std * field, 0.05, None)

    def frames(self, std: float, seed: int) -> list:
        rng = np.random.default_rng(seed)
        out = []
        for i, z in enumerate(np.linspace(*DISTANCES, FRAMES)):
            n = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
            d = torch.tensor([z], dtype=torch.float64)
            ranges, cos, hit = self.model.plane_returns(n, d)
            points = (ranges[0, ..., None] * self.dirs).numpy()  # (9, R, 3), sensor frame
            albedo = torch.as_tensor(self.params.albedo * self.texture(points[..., :2], std))[None]
            src = self.references[i % len(self.references)]
            ref = torch.as_tensor(np.asarray(src.reference, dtype=float))[None]
            with torch.no_grad():
                h = self.model.render_returns(ranges, cos, albedo, ref, hit=hit,
                                              light=self.model.plane_light(n, d, ranges, hit))[0].numpy()
            f = copy.deepcopy(src)
            f.hists = rng.poisson(np.maximum(h, 0.0)).astype(float)
            f.truth = Plane(np.array([0.0, 0.0, 1.0]), float(z))
            out.append(f)
        return out


def scatter(frames: list, estimator) -> tuple[np.ndarray, int]:
    """The tilt's scatter (deg per slope axis) about a cubic in 1 / z, and the number of planes."""
    z, t = [], []
    for f in frames:
        e = estimator.estimate(f)
        if e.ok:
            z.append(f.truth.offset)
            t.append(tilt_offset(e.plane)[:2])
    z, t = np.array(z), np.array(t)
    x = np.vander(1.0 / z, 4)
    rest = t - x @ np.linalg.lstsq(x, t, rcond=None)[0]
    return np.degrees(rest.std(axis=0)), len(z)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("calibration", help="calibration with forward, peak and diff sections")
    ap.add_argument("frames", help="real frames whose reference histograms the sweeps use")
    ap.add_argument("stds", type=float, nargs="+", help="texture std(s) (0: a flat albedo)")
    a = ap.parse_args()
    torch.set_num_threads(1)
    cal = Calibration.load(a.calibration)
    sweep = TexturedSweep(cal, [f for f in load_frames(a.frames) if f.reference is not None])
    own = cal.without_fallback()
    diff = DifferentiableEstimator(own.forward(), own.peak(), options=own.diff_options(), uncertainty=Uncertainty())
    flat = Calibration()
    fit_method(flat, sweep.frames(0.0, 3), "peak", progress=False, log=None)
    peak = PeakEstimator(flat.peak())
    for std in a.stds:
        frames = sweep.frames(std, 7)
        sd, nd = scatter(frames, diff)
        sp, n_p = scatter(frames, peak)
        print(f"texture std {std:.2f}: diff own a/b {sd.round(3)} (n {nd}); peak a/b {sp.round(3)} (n {n_p})",
              flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
