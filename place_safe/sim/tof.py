"""The simulated TMF8820: rays cast in a MuJoCo scene, histograms from the forward model, sensor timing and faults.

Conventions
-----------
* The sensor sits at the ``tof_sensor`` site; its +z is the optical axis, x/y as in the zone table.
* Per zone ``R = rays**2`` stratified rays (:meth:`place_safe.recovery.forward.ZoneRays.stratified`), bent by the
  true sensor's field-of-view scales, are cast with ``mujoco.mj_multiRay`` against geom group
  :data:`~place_safe.sim.scene.SENSED_GROUP` only (the robot, the held cup and the rig are not seen).
* Each hit carries its range (m), cosine of incidence, and the reflectance of the geom's material at
  the hit point (checkerboards evaluated in the geom's local x-y). Histograms are
  ``ForwardModel(true_params).render_returns`` of those returns, so several surfaces in a zone mix.
  Material albedo is relative: the ray's albedo is ``material.albedo * true_params.albedo``; a
  material without its own specular lobe uses the true sensor's (as the real sweep's table).
* Internal return and crosstalk: the true parameters carry the real sweep's zero-range (cover-glass) return,
  ``glass_gains`` / ``glass_delay``, measured on its frames at >= 15 cm (26-44 counts at the peak, bins 13-14;
  ``sim/make_real_sensor.py``), rendered by the forward model in every frame whatever the scene (a ray that
  misses adds nothing; the glass is still there), and the scalar ``crosstalk`` fitted at >= 4 cm. A surface
  closer than about 2 cm returns inside the internal return's bins: the overlap is rendered, not special-cased.
  The real sweep's dark zones close up (a zone 1e3-1e6 times darker than its neighbours at 5-20 mm) are rendered
  only with ``ToFConfig.blinding`` (off by default; the packaged calibrations and scenarios were made without
  it): a zone keeps ``exp(-(g / g0)^power)`` of its histogram, ``g`` its glint measure (:func:`glint_measure`:
  where the emitter's mirror image in the surface falls, weakening with range), parameters
  ``sim/sensors/tmf8820_real_blinding.json`` fitted to the real frames closer than 7 cm
  (``sim/make_real_sensor.py``). A fitted pattern, not a measured mechanism (see ``docs/results.md``, Near range).
* Noise: Poisson shot noise on the histogram plus a per-zone ambient floor drawn once per sensor
  in ``ambient_range`` counts; the reference histogram is the shipped real one with Poisson noise.
* Timing: measurement ``k`` is taken when the sim clock passes ``k / rate_hz`` and stamped with the
  sim time at which it was taken (``Frame.timestamp``, s). It becomes readable ``latency`` s later,
  the time to move ``transfer_bytes`` over the bus (``transfer_bytes * bits_per_byte / bus_hz``;
  4182 bytes at 400 kHz with 9 bits per byte is 94 ms). Transfers are pipelined, so the frame rate
  stays ``rate_hz``.
* Faults on demand: a frame is dropped with ``drop_prob`` (never delivered) or corrupted with
  ``corrupt_prob`` (NaN counts or a truncated histogram); corrupted frames are still delivered
  and fail :meth:`place_safe.sensor.frame.Frame.validate` downstream.
* On-sensor distances: per zone, the first peak above the noise is located (sub-bin, parabolic) and
  mapped to millimetres by the per-zone linear map fitted to the real sensor's reported distances
  (``sim/sensors/tmf8820_real_distance.json``); no return gives distance 0 with confidence 0.
* Ground truth: when every ray hits the table top, ``Frame.truth`` is the table plane in the
  sensor frame.
"""

from __future__ import annotations


import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, ClassVar

import numpy as np
import torch

from pydantic import Field

from place_safe.config import ParamModel, read_json, vector
from place_safe.calibration import Calibration
from place_safe.exceptions import CalibrationError, NoPlaneError, SensorTimeout
from place_safe.recovery.forward import ForwardModel, ForwardParams, ZoneRays, mount_rotation
from place_safe.geometry import Plane
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame
from place_safe.sensor.histogram import COUNT_MAX, first_return
from place_safe.io.source import FrameSource
from place_safe.evaluation.synthetic import default_reference

from place_safe.sim.scene import Scene, SceneError
from place_safe.assets import sim_sensors_dir



def sensor_file(name: str) -> Path:
    """Path of a simulated-sensor file in ``sim/sensors`` (see :mod:`place_safe.assets`)."""
    return sim_sensors_dir() / name


def calibration_name(sensor: str = "nominal") -> str:
    """The file name of the simulated user calibration of the simulated sensor ``sensor``: the packaged file's
    (:func:`calibration_file`), and what ``calibrate --sim`` writes in the current folder unless told where."""
    return f"calibration_{sensor}.json"


def calibration_file(sensor: str = "nominal") -> Path:
    """Path of the packaged simulated user calibration of the simulated sensor ``sensor`` (``nominal`` or
    ``mismatch``; made by :func:`place_safe.sim.calibration_capture.calibrate_sim`, written there only when named)."""
    return sensor_file(calibration_name(sensor))


def simulated_calibration(sensor: str = "nominal") -> Calibration:
    """The packaged simulated user calibration of the simulated sensor ``sensor`` (``nominal`` or ``mismatch``):
    what a user's ``place-safe capture`` + ``place-safe calibrate`` give, made in simulation (never the
    simulator's own parameters; see :mod:`place_safe.sim.calibration_capture`)."""
    return Calibration.load(calibration_file(sensor))


def true_params() -> ForwardParams:
    """The simulated sensor's own forward parameters (fitted to the real sweep; not the estimators' defaults)."""
    return ForwardParams.load(sensor_file("tmf8820_real.json"))


class DistanceMap(ParamModel):
    """On-sensor distance emulation: ``mm = slope[z] * peak_bin + intercept[z]`` per zone."""

    what: ClassVar[str] = "on-sensor distance map"
    error: ClassVar[type[Exception]] = CalibrationError

    slope: vector(N_ZONES, gt=0.0, le=1e4) = Field(default_factory=lambda: [1000 * 0.014131] * N_ZONES,
                                                   description="mm per bin")
    intercept: vector(N_ZONES, ge=-1e5, le=1e5) = Field(default_factory=lambda: [-1000 * 0.014131 * 13.2] * N_ZONES,
                                                        description="mm")
    noise_mm: float = Field(1.0, ge=0.0, le=1e3, description="mm")  # std of the reported distance

    @classmethod
    def load(cls, path: str | Path | None = None) -> "DistanceMap":
        """The map in ``path`` (default the packaged one); keys other than the fields (its fit report) are skipped."""
        p = Path(path) if path is not None else sensor_file("tmf8820_real_distance.json")
        d = read_json(p, "on-sensor distance map", CalibrationError)
        if not isinstance(d, dict):
            raise CalibrationError(f"on-sensor distance map {p} must be a JSON object")
        return cls.from_dict({k: v for k, v in d.items() if k in cls.model_fields}, f"on-sensor distance map {p}")


class ToFConfig(ParamModel):
    """Settings of the simulated sensor; each field's range and unit are its Field's (a scenario's ``sensor``
    section is checked against them: a bad value is one :class:`~place_safe.sim.scene.SceneError` line)."""

    what: ClassVar[str] = "sensor settings"
    error: ClassVar[type[Exception]] = SceneError

    rays: Annotated[int, Field(ge=1, le=64, description="rays per axis and zone")] = 8  # R = rays**2 per zone
    # the TMF8820 measures at most a few tens of frames a second
    rate_hz: Annotated[float, Field(ge=1.0, le=200.0, description="Hz")] = 30.0
    # 30 x 135 histogram packets + 132 result bytes
    transfer_bytes: Annotated[int, Field(ge=1, le=1 << 20, description="bytes")] = 4182
    bus_hz: Annotated[float, Field(gt=0.0, le=1e8, description="Hz")] = 400e3  # I2C clock
    bits_per_byte: Annotated[int, Field(ge=1, le=64, description="bits")] = 9  # 8 data bits + ACK
    noise: bool = True
    # per zone and bin; the sensor's bins hold 24-bit counts
    ambient_range: Annotated[list[Annotated[float, Field(ge=0.0, le=1e6)]],
                             Field(min_length=2, max_length=2, description="counts")] = \
        Field(default_factory=lambda: [60.0, 180.0])
    drop_prob: Annotated[float, Field(ge=0.0, le=1.0, description="(probability)")] = 0.0
    corrupt_prob: Annotated[float, Field(ge=0.0, le=1.0, description="(probability)")] = 0.0
    # probability that a frame's transfer stalls (latency spike)
    spike_prob: Annotated[float, Field(ge=0.0, le=1.0, description="(probability)")] = 0.0
    # extra latency of a stalled transfer (later frames queue behind it)
    spike_seconds: Annotated[float, Field(ge=0.0, le=10.0, description="s")] = 0.25
    seed: Annotated[int, Field(ge=0, le=2 ** 63 - 1, description="(seed)")] = 0
    max_range: Annotated[float, Field(gt=0.0, le=100.0, description="m")] = 5.0  # farther surfaces are not seen
    # the real sensor's dark zones close up (see the module doc); off: the packaged calibrations were made without
    blinding: bool = False
    blinding_file: str | None = None  # Blinding JSON; default sim/sensors/tmf8820_real_blinding.json
    params_file: str | None = None  # ForwardParams JSON; default sim/sensors/tmf8820_real.json
    distance_file: str | None = None  # DistanceMap JSON; default sim/sensors/tmf8820_real_distance.json

    @property
    def latency(self) -> float:
        """Seconds from the end of a measurement until its data has crossed the bus."""
        return self.transfer_bytes * self.bits_per_byte / self.bus_hz


@dataclass
class RayReturns:
    """What the rays of one measurement saw, each (9, R): in metres, cosines, relative reflectance."""

    ranges: np.ndarray
    cos_inc: np.ndarray
    albedo: np.ndarray  # absolute (times the sensor's albedo)
    specular_weight: np.ndarray
    specular_exponent: np.ndarray
    hit: np.ndarray
    geom: np.ndarray
    points: np.ndarray  # (9, R, 3) world hit points (NaN on misses)
    normals: np.ndarray  # (9, R, 3) world surface normals (NaN on misses)
    sensor_points: np.ndarray | None = None  # (9, R, 3) hit points in the sensor frame (m; NaN on misses)
    sensor_normals: np.ndarray | None = None  # (9, R, 3) surface normals in the sensor frame (NaN on misses)


class Blinding(ParamModel):
    """The real sensor's dark zones close up (module doc): emitter position (m, sensor x, y), glint angular width
    (rad), the glint measure ``g0`` at which a zone keeps 1/e of its light, and the power of the fall."""

    what: ClassVar[str] = "sensor blinding"
    error: ClassVar[type[Exception]] = CalibrationError

    emitter: vector(2, ge=-0.02, le=0.02) = Field(default_factory=lambda: [0.0, 0.002], description="m")
    glint_width: float = Field(0.052, gt=0.0, le=1.0, description="rad")
    g0: float = Field(126.0, gt=0.0, le=1e12, description="1/m^2")
    power: float = Field(2.0, gt=0.0, le=10.0, description="(exponent)")

    @classmethod
    def load(cls, path: str | Path | None = None) -> "Blinding":
        """The parameters in ``path`` (default the packaged ones); keys other than the fields (the fit's report)
        are skipped."""
        p = Path(path) if path is not None else sensor_file("tmf8820_real_blinding.json")
        d = read_json(p, "sensor blinding", CalibrationError)
        if not isinstance(d, dict):
            raise CalibrationError(f"sensor blinding {p} must be a JSON object")
        return cls.from_dict({k: v for k, v in d.items() if k in cls.model_fields}, f"sensor blinding {p}")


def glint_measure(points: np.ndarray, normals: np.ndarray, weights: np.ndarray, hit: np.ndarray, emitter,
                  width: float) -> np.ndarray:
    """Per-zone glint measure (9,) (1/m^2): the quadrature mean over the zone's rays of
    ``exp(-a^2 / 2 width^2) / (r + r_e)^2``, ``a`` the angle between the surface normal and the half vector of the
    directions from the hit point to the emitter ``(ex, ey, 0)`` and to the receiver (the origin), ``r`` and ``r_e``
    the point's distances to them. points, normals: (9, R, 3) in the sensor frame (m); weights (9, R) summing to 1
    per zone; hit (9, R) bool (misses add nothing)."""
    e = np.array([float(emitter[0]), float(emitter[1]), 0.0])
    p = np.nan_to_num(np.asarray(points, dtype=float))
    n = np.nan_to_num(np.asarray(normals, dtype=float))
    to_e = e - p
    r_e = np.maximum(np.linalg.norm(to_e, axis=-1), 1e-6)
    r = np.maximum(np.linalg.norm(p, axis=-1), 1e-6)
    half = to_e / r_e[..., None] - p / r[..., None]
    half /= np.maximum(np.linalg.norm(half, axis=-1, keepdims=True), 1e-12)
    cos = np.clip(np.abs(np.einsum("zrk,zrk->zr", half, n)), 0.0, 1.0)
    a = np.arccos(cos)
    g = np.exp(-0.5 * (a / width) ** 2) / (r + r_e) ** 2
    return (np.asarray(weights, dtype=float) * np.where(np.asarray(hit, dtype=bool), g, 0.0)).sum(axis=-1)


class SimToF(FrameSource):
    clock_domain = "robot"  # frames are stamped with the simulation's time (the SimRobot's clock)
    """A TMF8820 in a MuJoCo :class:`~place_safe.sim.scene.Scene` (see module docstring)."""

    def __init__(self, scene: Scene, data: Any = None, config: ToFConfig | None = None,
                 params: ForwardParams | None = None, distance_map: DistanceMap | None = None) -> None:
        import mujoco

        self._mj = mujoco
        self.scene = scene
        self.model = scene.model
        self.data = data if data is not None else scene.make_data()
        self.config = config if config is not None else ToFConfig()
        cfg = self.config
        self.params = params if params is not None else (
            ForwardParams.load(cfg.params_file) if cfg.params_file else true_params())
        self.distance_map = distance_map if distance_map is not None else DistanceMap.load(cfg.distance_file)
        self.blinding = Blinding.load(cfg.blinding_file) if cfg.blinding else None
        self.rate_hz = cfg.rate_hz
        self.forward = ForwardModel(self.params, ZoneRays.stratified(cfg.rays))
        self._dirs, self._weights = self._mounted_rays()
        self._kernel_ref = default_reference()
        self._kernel: torch.Tensor | None = None
        self._rng = np.random.default_rng(cfg.seed)
        lo, hi = cfg.ambient_range
        self.ambient = self._rng.uniform(lo, hi, N_ZONES)  # counts, per zone
        self._nray = self._dirs.shape[0]
        self._geomid = np.zeros(self._nray, dtype=np.int32)
        self._dist = np.zeros(self._nray)
        self._normal = np.zeros(3 * self._nray)
        self._pending: deque[tuple[float, Frame]] = deque()
        self._next_index = 0
        self._t0: float | None = None
        self._lockstep = False
        self.dropped = 0
        self.corrupted = 0
        self.overruns = 0

    def _mounted_rays(self) -> tuple[np.ndarray, torch.Tensor]:
        """The rays' directions (9R, 3) in the sensor (mount) frame and their weights, from ``self.forward``: a sensor
        mounted off its nominal orientation has its optical frame rotated from the mount frame by the true mount tilt
        (``params.mount_tilt``; identity for a perfect mount)."""
        with torch.no_grad():
            dirs, w = self.forward.ray_geometry()
            dirs = dirs @ mount_rotation(self.params.mount_tilt).T
        return dirs.numpy().reshape(-1, 3), w

    # -- ray casting ---------------------------------------------------------------------------
    @property
    def directions(self) -> np.ndarray:
        """Unit ray directions (9, R, 3) in the sensor frame (after the true sensor's field-of-view scales)."""
        return self._dirs.reshape(N_ZONES, -1, 3).copy()

    def sensor_pose(self, data: Any = None) -> tuple[np.ndarray, np.ndarray]:
        """Position (3,) and rotation (3, 3) world <- sensor of the ``tof_sensor`` site."""
        d = self.data if data is None else data
        s = self.scene.sensor_site
        return d.site_xpos[s].copy(), d.site_xmat[s].reshape(3, 3).copy()

    def cast(self, model: Any = None, data: Any = None) -> RayReturns:
        """Cast every ray from the current sensor pose; vectorised over rays."""
        m = self.model if model is None else model
        d = self.data if data is None else data
        pos, R = self.sensor_pose(d)
        vec = self._dirs @ R.T  # (N, 3) world directions (unit)
        self._mj.mj_multiRay(m, d, pos, vec.reshape(-1), self.scene.sensed_groups, 1, -1, self._geomid,
                             self._dist, self._normal, self._nray, self.config.max_range)
        gid = self._geomid.copy()
        hit = (gid >= 0) & (self._dist >= 0)
        dist = np.where(hit, self._dist, np.nan)
        normals = np.where(hit[:, None], self._normal.reshape(-1, 3), np.nan)
        pts = pos + vec * dist[:, None]
        gi = np.where(hit, gid, 0)
        Rg = d.geom_xmat[gi].reshape(-1, 3, 3)
        local = np.einsum("nji,nj->ni", Rg, pts - d.geom_xpos[gi])
        rel, ks, alpha = self.scene.materials.lookup(np.where(hit, gid, -1), np.nan_to_num(local[:, :2]))
        ks = np.where(np.isnan(ks), self.params.specular_weight, ks)
        alpha = np.where(np.isnan(alpha), self.params.specular_exponent, alpha)
        cos = np.where(hit, np.abs(np.einsum("nk,nk->n", vec, np.nan_to_num(normals))), 0.0)
        shape = (N_ZONES, -1)
        return RayReturns(np.where(hit, dist, 1.0).reshape(shape), cos.reshape(shape),
                          (rel * self.params.albedo).reshape(shape), ks.reshape(shape), alpha.reshape(shape),
                          hit.reshape(shape), gid.reshape(shape), pts.reshape(N_ZONES, -1, 3),
                          normals.reshape(N_ZONES, -1, 3),
                          ((pts - pos) @ R).reshape(N_ZONES, -1, 3), (normals @ R).reshape(N_ZONES, -1, 3))

    # -- measurement ---------------------------------------------------------------------------
    def render(self, returns: RayReturns, reference: np.ndarray) -> np.ndarray:
        """Noise-free histograms (9, 128) of ``returns`` (floor not included).

        Runs torch single-threaded: these tensors are small, and on a busy machine thread hand-offs
        cost 20x the arithmetic (measured: 89 ms vs 3.7 ms per frame at load 9 on 2 cores).
        """
        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            return self._render(returns, reference)
        finally:
            torch.set_num_threads(threads)

    def _render(self, returns: RayReturns, reference: np.ndarray, seen: RayReturns | None = None) -> np.ndarray:
        """:meth:`render` on the calling thread. ``seen``: the returns the blinding is computed from (default
        ``returns``; a unit whose zones keep their own time renders returns moved in range, which the glint does not
        see)."""
        with torch.no_grad():
            kernel = None
            if reference is self._kernel_ref:  # the usual case: the pulse of the shipped reference, cached
                if self._kernel is None:
                    self._kernel = self.forward.pulse(torch.as_tensor(reference)[None])
                kernel = self._kernel
            h = self.forward.render_returns(
                torch.as_tensor(returns.ranges[None]), torch.as_tensor(returns.cos_inc[None]),
                torch.as_tensor(returns.albedo[None]), torch.as_tensor(reference[None]),
                weights=self._weights, specular_weight=torch.as_tensor(returns.specular_weight[None]),
                specular_exponent=torch.as_tensor(returns.specular_exponent[None]),
                hit=torch.as_tensor(returns.hit[None]), kernel=kernel)
        out = h[0].numpy() - self.params.floor
        seen = returns if seen is None else seen
        if self.blinding is not None and seen.sensor_points is not None:
            out = out * self.blinding_factors(seen)[:, None]
        return out

    def blinding_factors(self, returns: RayReturns) -> np.ndarray:
        """Per zone the share (9,) of its histogram the real sensor's dark zones close up leave (module doc; 1
        without ``ToFConfig.blinding``). The glint scales with the material's reflectance and specular weight
        relative to the real sweep's table."""
        b = self.blinding
        if b is None or returns.sensor_points is None:
            return np.ones(N_ZONES)
        rel = (returns.albedo / self.params.albedo) * (returns.specular_weight / max(self.params.specular_weight,
                                                                                       1e-12))
        w = np.asarray(self._weights, dtype=float) * np.where(returns.hit, rel, 0.0)
        g = glint_measure(returns.sensor_points, returns.sensor_normals, w, returns.hit, b.emitter, b.glint_width)
        return np.exp(-np.power(np.maximum(g, 0.0) / b.g0, b.power))

    def measure(self, model: Any = None, data: Any = None, noise: bool | None = None,
                reference: np.ndarray | None = None) -> Frame:
        """One frame at the current state (no timing, no faults). ``noise`` overrides the config."""
        d = self.data if data is None else data
        noisy = self.config.noise if noise is None else noise
        ref_clean = self._kernel_ref if reference is None else np.asarray(reference, dtype=float)
        returns = self.cast(model, d)
        h = self.render(returns, ref_clean) + self.ambient[:, None]
        if noisy:
            h = self._rng.poisson(np.clip(h, 0, None)).astype(float)
            ref = self._rng.poisson(np.clip(ref_clean, 0, None)).astype(float)
        else:
            ref = ref_clean.copy()
        h = np.minimum(h, COUNT_MAX)
        dist, conf = self.on_sensor_distances(h, noisy)
        truth = self.truth(returns, d)
        meta = {"hit_fraction": float(returns.hit.mean()),
                "table_fraction": float((returns.geom == self.scene.table_geom).mean())}
        return Frame(h, ref, distances=dist, confidences=conf, timestamp=float(d.time), truth=truth,
                     extra={"sim": meta})

    def truth(self, returns: RayReturns, data: Any = None) -> Plane | None:
        """The table plane in the sensor frame if every ray hit the table top, else None."""
        d = self.data if data is None else data
        if not np.all(returns.geom == self.scene.table_geom):
            return None
        n_w, p_w = self.scene.table_plane_world(d)
        if not np.allclose(returns.normals.reshape(-1, 3) @ n_w, 1.0, atol=1e-6):
            return None  # some ray hit a side of the slab
        pos, R = self.sensor_pose(d)
        n_s = R.T @ n_w
        try:
            return Plane(n_s, float(n_s @ (R.T @ (p_w - pos))))
        except NoPlaneError:
            return None

    def on_sensor_distances(self, hists: np.ndarray, noisy: bool = True) -> tuple[np.ndarray, np.ndarray]:
        """First-object distance (m) and confidence (0..255) per zone, as the sensor reports them."""
        peak, found, snr = first_return(hists)
        dm = self.distance_map
        mm = np.asarray(dm.slope) * peak + np.asarray(dm.intercept)
        if noisy and dm.noise_mm > 0:
            mm = mm + self._rng.normal(0.0, dm.noise_mm, N_ZONES)
        # confidence saturates at 255 for a peak 60 floor sigmas high (the real sensor reports 255 for the table)
        conf = np.clip(np.round(255.0 * np.clip(snr / 60.0, 0.0, 1.0)), 0, 255)
        ok = found & (mm > 0)
        return np.where(ok, np.round(mm) / 1000.0, 0.0), np.where(ok, conf, 0.0)

    # -- streaming -----------------------------------------------------------------------------
    def attach(self, robot: Any) -> "SimToF":
        """Run in lockstep with a SimRobot: measure from its step callback on its model/data."""
        self._lockstep = True
        robot.add_step_callback(self.on_step)
        return self

    def on_step(self, *_: Any) -> None:
        """Step callback: take every measurement whose time has come (call after each mj_step)."""
        t = float(self.data.time)
        if self._t0 is None:
            self._t0 = t
        period = 1.0 / self.config.rate_hz
        while t + 1e-12 >= self._t0 + self._next_index * period:
            self._take(t)

    def _take(self, t: float) -> None:
        k = self._next_index
        self._next_index += 1
        cfg = self.config
        if cfg.drop_prob > 0 and self._rng.random() < cfg.drop_prob:
            self.dropped += 1
            return
        frame = self.measure()
        frame.timestamp = t
        frame.extra["sim"]["index"] = k
        if cfg.corrupt_prob > 0 and self._rng.random() < cfg.corrupt_prob:
            self._corrupt(frame)
        ready = t + cfg.latency
        if cfg.spike_prob > 0 and self._rng.random() < cfg.spike_prob:
            ready += cfg.spike_seconds
            frame.extra["sim"]["latency_spike"] = cfg.spike_seconds
        if self._pending:  # the bus is serial: a stalled transfer delays the ones behind it
            ready = max(ready, self._pending[-1][0])
        self._pending.append((ready, frame))

    def _corrupt(self, frame: Frame) -> None:
        self.corrupted += 1
        kind = int(self._rng.integers(3))
        if kind == 0:  # bins lost in transfer
            z = int(self._rng.integers(N_ZONES))
            frame.hists[z, self._rng.integers(N_BINS, size=8)] = np.nan
            frame.extra["sim"]["corrupted"] = "nan"
        elif kind == 1:  # transfer cut short: last packets missing
            frame.hists = frame.hists[:, : int(self._rng.integers(16, N_BINS))]
            frame.extra["sim"]["corrupted"] = "truncated_hists"
        else:
            frame.reference = frame.reference[: int(self._rng.integers(16, N_BINS))]
            frame.extra["sim"]["corrupted"] = "truncated_reference"

    def _pop_ready(self) -> Frame | None:
        now = float(self.data.time)
        ready = None
        while self._pending and self._pending[0][0] <= now + 1e-12:
            if ready is not None:
                self.overruns += 1
            ready = self._pending.popleft()[1]
        return ready

    def read(self, timeout: float = 1.0) -> Frame:
        """The next frame.

        In lockstep (after :meth:`attach`) the robot advances the clock: the newest frame whose
        transfer has finished is returned (older unread ones are counted in ``overruns``), waiting
        up to ``timeout`` wall-clock seconds for one. Free-running, the scene is stepped with
        ``mj_step`` until the next frame is readable; ``timeout`` is then in sim seconds.
        """
        if self._lockstep:
            deadline = time.monotonic() + max(timeout, 0.0)
            while True:
                f = self._pop_ready()
                if f is not None:
                    return f
                if time.monotonic() >= deadline:
                    raise SensorTimeout(f"no simulated ToF frame ready at sim time {self.data.time:.4f} s "
                                        f"within {timeout} s; is the robot stepping?")
                time.sleep(0.0005)
        t_end = float(self.data.time) + timeout
        if self._t0 is None:
            self.on_step()
        while True:
            f = self._pop_ready()
            if f is not None:
                return f
            if self.data.time >= t_end:
                raise SensorTimeout(f"no simulated ToF frame within {timeout} s of sim time "
                                    f"(drop_prob={self.config.drop_prob})")
            self._mj.mj_step(self.model, self.data)
            self.on_step()

    def close(self) -> None:
        self._pending.clear()


def zone_rays_world(tof: SimToF, data: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """Origin (3,) and unit directions (9, R, 3) of the sensor's rays in the world (for drawing)."""
    pos, R = tof.sensor_pose(data)
    return pos, (tof._dirs @ R.T).reshape(N_ZONES, -1, 3)


__all__ = ["SimToF", "ToFConfig", "DistanceMap", "RayReturns", "Blinding", "glint_measure", "true_params", "sensor_file", "zone_rays_world",
           "COUNT_MAX"]

