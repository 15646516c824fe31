"""Validation of the simulated sensor against a real sweep: same geometry, compare histograms zone by zone.

For every real frame with ground truth at ``z0 >= min_distance``, a sensor rig is placed over a
level table (relative albedo 1 and the true sensor's specular lobe: the real sweep's table) so that the table is at the frame's
ground-truth plane in the sensor frame, the frame is simulated without noise (with the real frame's
reference histogram and floor), and per zone two figures are taken:

* ``peak_diff``: simulated minus real peak position in bins, both sub-bin (parabola through the
  largest bin of the floor-subtracted histogram and its neighbours);
* ``corr``: Pearson correlation of the peak-normalised histograms over the window
  ``[peak - before, peak + after]`` bins around the real peak;
* ``amp_ratio``: simulated over real peak height above the floor (informative, no target: the
  per-frame albedo of the real table is not known, the simulation uses the fitted median).

Targets (per zone): mean ``|peak_diff|`` <= 0.5 bin and mean ``corr`` >= 0.95; the worst frame of
each zone is reported too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from place_safe.recovery.forward import ForwardParams
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame

from place_safe.sim.scene import Material, SceneConfig, TableConfig, build_scene
from place_safe.sensor.histogram import FLOOR_BINS
from place_safe.sim.tof import SimToF, ToFConfig, true_params

PEAK_TARGET = 0.5  # bins
CORR_TARGET = 0.95
TABLE_HEIGHT = 0.75  # m; any height works, the rig is placed relative to it


def subbin_peak(hists: np.ndarray) -> np.ndarray:
    """Sub-bin position (..., ) of the largest bin of floor-subtracted histograms (..., 128), by a parabola."""
    h = np.asarray(hists, dtype=float)
    h = h - np.median(h[..., FLOOR_BINS], axis=-1, keepdims=True)
    k = np.clip(np.argmax(h, axis=-1), 1, N_BINS - 2)
    y0 = np.take_along_axis(h, (k - 1)[..., None], -1)[..., 0]
    y1 = np.take_along_axis(h, k[..., None], -1)[..., 0]
    y2 = np.take_along_axis(h, (k + 1)[..., None], -1)[..., 0]
    den = y0 - 2 * y1 + y2
    frac = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / np.where(den == 0, 1.0, den), 0.0)
    return k + np.clip(frac, -0.5, 0.5)


def shape_correlation(sim: np.ndarray, real: np.ndarray, before: int = 4, after: int = 8) -> np.ndarray:
    """Pearson correlation per zone of peak-normalised histograms (Z, 128) in a window around the real peak."""
    s = np.asarray(sim, dtype=float)
    r = np.asarray(real, dtype=float)
    s = s - np.median(s[:, FLOOR_BINS], axis=1, keepdims=True)
    r = r - np.median(r[:, FLOOR_BINS], axis=1, keepdims=True)
    s = s / np.maximum(s.max(axis=1, keepdims=True), 1e-12)
    r = r / np.maximum(r.max(axis=1, keepdims=True), 1e-12)
    k = np.argmax(r, axis=1)
    idx = np.clip(k[:, None] + np.arange(-before, after + 1)[None], 0, N_BINS - 1)
    sw = np.take_along_axis(s, idx, 1)
    rw = np.take_along_axis(r, idx, 1)
    sw = sw - sw.mean(axis=1, keepdims=True)
    rw = rw - rw.mean(axis=1, keepdims=True)
    return (sw * rw).sum(1) / np.maximum(np.sqrt((sw * sw).sum(1) * (rw * rw).sum(1)), 1e-12)


@dataclass
class ValidationReport:
    distances: np.ndarray  # (F,) ground-truth z0 (m)
    peak_diff: np.ndarray  # (F, 9) bins, sim - real
    corr: np.ndarray  # (F, 9)
    amp_ratio: np.ndarray  # (F, 9)
    sim_hists: np.ndarray = field(repr=False, default_factory=lambda: np.zeros((0, N_ZONES, N_BINS)))

    def zone_table(self) -> dict[str, np.ndarray]:
        a = np.abs(self.peak_diff)
        return {"peak_mean": a.mean(0), "peak_worst": a.max(0), "peak_bias": self.peak_diff.mean(0),
                "corr_mean": self.corr.mean(0), "corr_worst": self.corr.min(0),
                "amp_ratio_median": np.median(self.amp_ratio, 0)}

    @property
    def passed(self) -> bool:
        t = self.zone_table()
        return bool(np.all(t["peak_mean"] <= PEAK_TARGET) and np.all(t["corr_mean"] >= CORR_TARGET))

    def format(self) -> str:
        t = self.zone_table()
        lines = [f"{len(self.distances)} frames, z0 {self.distances.min() * 100:.1f}..{self.distances.max() * 100:.1f} cm"
                 if len(self.distances) else "0 frames",
                 "zone  |peak diff| mean  worst   bias (bins)   corr mean  worst   amplitude sim/real (median)",
                 ]
        for z in range(N_ZONES):
            lines.append(f"{z + 1:>4}  {t['peak_mean'][z]:>15.3f} {t['peak_worst'][z]:>6.3f} {t['peak_bias'][z]:>+7.3f}"
                         f"        {t['corr_mean'][z]:>9.4f} {t['corr_worst'][z]:>6.4f}"
                         f"   {t['amp_ratio_median'][z]:>6.2f}")
        lines.append(f"all   {np.abs(self.peak_diff).mean():>15.3f} {np.abs(self.peak_diff).max():>6.3f} "
                     f"{self.peak_diff.mean():>+7.3f}        {self.corr.mean():>9.4f} {self.corr.min():>6.4f}"
                     f"   {np.median(self.amp_ratio):>6.2f}")
        lines.append(f"targets: mean |peak diff| <= {PEAK_TARGET} bin and mean corr >= {CORR_TARGET} in every zone: "
                     + ("PASS" if self.passed else "FAIL"))
        return "\n".join(lines)


def validate(frames: list[Frame], params: ForwardParams | None = None, rays: int = 8,
             min_distance: float = 0.05, before: int = 4, after: int = 8) -> ValidationReport:
    """Simulate every real frame with ground truth at ``z0 >= min_distance`` and compare (see module docstring)."""
    from scipy.spatial.transform import Rotation

    use = [f for f in frames if f.truth is not None and f.truth.z0 >= min_distance]
    tof = _rig_sensor(params, rays)
    sims, diffs, corrs, amps, dist = [], [], [], [], []
    for f in use:
        n = f.truth.normal
        # any rotation taking the plane normal (sensor frame) to straight down works on a level uniform table
        R = Rotation.align_vectors([[0.0, 0.0, -1.0]], [n])[0].as_matrix()
        table_xy = np.array(tof.scene.config.table.center)
        tof.scene.set_sensor_pose(tof.data, np.array([*table_xy, TABLE_HEIGHT + f.truth.offset]), R)
        tof.ambient = np.median(f.hists[:, FLOOR_BINS], axis=1)
        ref = f.reference if f.reference is not None else None
        sim = tof.measure(noise=False, reference=ref).hists
        sims.append(sim)
        diffs.append(subbin_peak(sim) - subbin_peak(f.hists))
        corrs.append(shape_correlation(sim, f.hists, before, after))
        amps.append(_height(sim) / np.maximum(_height(f.hists), 1e-9))
        dist.append(f.truth.z0)
    return ValidationReport(np.array(dist), np.array(diffs).reshape(-1, N_ZONES),
                            np.array(corrs).reshape(-1, N_ZONES), np.array(amps).reshape(-1, N_ZONES), np.array(sims))


def _height(h: np.ndarray) -> np.ndarray:
    return (h - np.median(h[:, FLOOR_BINS], axis=1, keepdims=True)).max(axis=1)


def _rig_sensor(params: ForwardParams | None, rays: int) -> SimToF:
    p = params if params is not None else true_params()
    table = TableConfig(height=TABLE_HEIGHT, center=(0.0, 0.0), size=(2.0, 2.0, 0.04),
                        material=Material(albedo=1.0))
    scene = build_scene(SceneConfig(table=table, rig_pos=(0.0, 0.0, TABLE_HEIGHT + 0.2)))
    return SimToF(scene, config=ToFConfig(rays=rays, noise=False), params=p)
