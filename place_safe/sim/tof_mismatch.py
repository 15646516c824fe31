"""A simulated TMF8820 that is *not* the forward model: structural differences a real sensor has.

Concept: :class:`MismatchedToF` is a :class:`~place_safe.sim.tof.SimToF` whose histograms differ
from what :class:`~place_safe.recovery.forward.ForwardModel` can express with any parameters, so
an estimator calibrated on it (``place-safe scenarios calibrate``) is measured on a sensor that its
model did not generate. The differences (all configurable in :class:`MismatchConfig`, seeded):

* **Per-zone pulse shape**: each zone's pulse gets its own extra exponential tail (weight and decay
  drawn per zone), over ``tail_lags`` bins after the pulse. The model has per-zone tails too
  (``ForwardParams.zone_tail_*``), but these lengthen as the die warms (below), which no constant parameter
  follows. Until 2026-11-28 every unit's tail stopped at 23 bins (``tail_lags=23`` reproduces the figures
  measured then): a step of up to 10 % of the tail's start (units with 8-bin decays) that no exponential and no
  physical impulse response has; it was most of units B's and 32's forward residual (docs/results.md).
* **Temperature drift**: the die warms from ``temp_start`` by ``temp_rate`` degC/s (up to
  ``temp_max``); the timing shifts by ``drift_bins_per_degc`` bins per degree and the extra tails
  lengthen by ``tail_per_degc`` per degree. A calibration taken cold cannot know the warm sensor.
* **Per-zone timing skew** beyond the model's constant zone offsets: a per-zone sub-bin skew that
  also scales with temperature (``skew_bins`` at 10 degC above the start).
* **Emitter-receiver baseline**: light leaves from an emitter ``baseline`` metres from the
  receiver along sensor +x, so a return's time of flight is ``|e - p| + |p - r|``, not ``2 |p - r|``
  (matters at close range).
* **Its own internal return and neighbour crosstalk**: each zone's cover-glass return (the true sensor's
  ``glass_gains``, measured on the real sweep) is scaled by a factor drawn log-uniformly in
  ``[1 / (1 + glass_spread), 1 + glass_spread]``, its delay moved by ``glass_delay_std`` bins (normal), and the
  unit leaks ``crosstalk_grid`` (uniform in ``[0, crosstalk_grid_max]`` per neighbour displacement) into its
  neighbours, where the true sensor has none: a calibration made on another unit does not know them.
* **Each zone's own time scale** (``zone_time_scale``, off by default): a zone's returns land ``1 + u`` times as
  far from range 0 as the model puts them (``u`` per zone, uniform in +-``zone_time_scale``), before they are binned
  (:meth:`MismatchedToF.timed`; the pulse keeps its width: stretching it too read the same, docs/results.md). The
  real sweep's zones drift against the model by -0.11 .. +0.08 bins per 10 cm (docs/results.md, the unit model,
  step 5), about +-1.5 %; on a level sweep this moves a zone's return with distance as its field of view does.
* **A sensor mounted off its nominal orientation** (``mount_tilt``, off by default): the rotation from the optical
  frame to the mount frame, a rotation vector ``(rx, ry)`` (rad) as ``ForwardParams.mount_tilt``, added to the sensor
  file's (a sum of small rotation vectors, not a composition). On a level sweep this moves the
  zones' returns with distance as their own time scales do; peak's calibration reads it that way, the forward fit as
  the tilt (docs/results.md, "A sensor mounted off its nominal orientation").
* **Varying ambient floor**: the ambient level drifts from frame to frame (``ambient_drift``
  relative, a slow sinusoid plus a random walk) and slopes across the histogram bins
  (``ambient_slope`` relative change from first to last bin); the model assumes a flat floor.

Units: metres, seconds, degrees Celsius, histogram bins. Everything else is the nominal
:class:`~place_safe.sim.tof.SimToF` (rays, materials, timing, faults, ground truth).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Annotated, Any

import numpy as np
from pydantic import Field

from place_safe.config import ConfigModel
from place_safe.recovery.forward import ForwardModel, ZoneRays
from place_safe.sensor.frame import N_BINS, N_ZONES, Frame

from place_safe.sim.tof import RayReturns, SimToF, ToFConfig


#: A fraction 0..1 and a width in histogram bins (0.01..128) for :class:`MismatchConfig` ranges.
Fraction = Annotated[float, Field(ge=0.0, le=1.0)]
Bins = Annotated[float, Field(ge=0.01, le=128.0)]
#: Bins after the pulse that each zone's extra tail reaches by default: the longest decay of any unit here (8 bins,
#: warmed 20 degC at 1 % per degC: 9.6 bins) has fallen to 5e-5 of its start by then, so the tail ends as an
#: exponential does (a config may ask for decays up to 128 bins; their tails are cut here).
TAIL_LAGS = 96


class MismatchConfig(ConfigModel):
    """How the mismatched sensor differs from the forward model (see module docstring)."""

    seed: int = Field(7, ge=0, le=2 ** 63 - 1, description="seed of the per-zone differences (not the noise)")
    tail_weight: tuple[Fraction, Fraction] = Field((0.02, 0.08), description="range of per-zone extra tail weights "
                                                   "(each 0..1)")
    tail_decay: tuple[Bins, Bins] = Field((1.5, 5.0), description="range of per-zone extra tail decays (bins, "
                                          "each 0.01..128)")
    tail_lags: int = Field(TAIL_LAGS, ge=1, le=127, description="bins after the pulse the extra tails reach "
                           "(1..127; 23 before 2026-11-28)")
    skew_bins: float = Field(0.15, ge=0, le=10, description="per-zone timing skew std (bins) at 10 degC of warming")
    temp_start: float = Field(25.0, ge=-40, le=125, description="die temperature at the start (degC, -40..125)")
    temp_rate: float = Field(0.5, ge=0, le=10, description="warming rate (degC/s, up to 10)")
    temp_max: float = Field(45.0, ge=-40, le=125, description="die temperature limit (degC, -40..125)")
    drift_bins_per_degc: float = Field(0.01, ge=-1, le=1, description="common timing drift (bins per degC of "
                                       "warming, -1..1)")
    tail_per_degc: float = Field(0.01, ge=0, le=1, description="relative lengthening of the extra tails per degC")
    baseline: float = Field(0.006, ge=0, le=0.05, description="emitter offset from the receiver along +x (m)")
    ambient_drift: float = Field(0.25, ge=0, le=1, description="relative frame-to-frame ambient variation")
    ambient_slope: float = Field(0.15, ge=-0.9, le=0.9, description="relative ambient change from first to last bin")
    glass_spread: float = Field(0.5, ge=0, le=10, description="per-zone internal-return gain factor range "
                                "[1/(1+s), 1+s] (log-uniform)")
    glass_delay_std: float = Field(0.5, ge=0, le=4, description="std of the internal return's delay shift (bins)")
    crosstalk_grid_max: float = Field(4e-5, ge=0, le=0.01, description="largest neighbour crosstalk per "
                                      "displacement (fraction)")
    zone_time_scale: float = Field(0.0, ge=0, le=0.1, description="each zone's own time scale: its returns "
                                   "land (1 + u) times as far from range 0, u uniform in +-this (0: none)")
    mount_tilt: tuple[Annotated[float, Field(ge=-0.05, le=0.05)], Annotated[float, Field(ge=-0.05, le=0.05)]] = Field(
        (0.0, 0.0), description="the sensor mounted off its nominal orientation: rotation vector (rx, ry) from the "
                                "optical frame to the mount frame (as ForwardParams.mount_tilt), rad, each -0.05..0.05 "
                                "(added to the sensor file's)")


class MismatchedToF(SimToF):
    """The simulated sensor with the structural differences of :class:`MismatchConfig`."""

    def __init__(self, scene: Any, data: Any = None, config: ToFConfig | None = None,
                 mismatch: MismatchConfig | None = None, **kw: Any) -> None:
        super().__init__(scene, data, config, **kw)
        self.mismatch = mismatch if mismatch is not None else MismatchConfig()
        mc = self.mismatch
        rng = np.random.default_rng(mc.seed)
        self._tail_w = rng.uniform(*mc.tail_weight, N_ZONES)
        self._tail_k = rng.uniform(*mc.tail_decay, N_ZONES)
        self._skew = rng.normal(0.0, mc.skew_bins, N_ZONES)
        self._amb_phase = rng.uniform(0, 2 * math.pi, N_ZONES)
        self._amb_base = self.ambient.copy()
        self._amb_walk = np.zeros(N_ZONES)
        self._time = 0.0
        # the unit's own internal return and neighbour crosstalk (drawn after the older differences, so a seed's
        # pulse tails, skews and ambient phases are what they were)
        spread = math.log1p(mc.glass_spread)
        glass = np.asarray(self.params.glass_gains) * np.exp(rng.uniform(-spread, spread, N_ZONES))
        delay = float(np.clip(self.params.glass_delay + rng.normal(0.0, mc.glass_delay_std), -8.0, 16.0))
        grid = rng.uniform(0.0, mc.crosstalk_grid_max, len(self.params.crosstalk_grid))
        # and its own mount (no draw: the seeds' differences stay), which turns its rays
        tilt = [float(a) + float(b) for a, b in zip(self.params.mount_tilt, mc.mount_tilt)]
        self.params = self.params.model_copy(update={"glass_gains": [float(g) for g in glass], "glass_delay": delay,
                                                     "crosstalk_grid": [float(g) for g in grid], "mount_tilt": tilt})
        self.forward = ForwardModel(self.params, ZoneRays.stratified(self.config.rays))
        self._dirs, self._weights = self._mounted_rays()
        self._kernel = None
        # each zone's own time scale (drawn last: the differences above stay what each seed gave them)
        self._time_scale = 1.0 + rng.uniform(-mc.zone_time_scale, mc.zone_time_scale, N_ZONES)

    # -- what differs --------------------------------------------------------------------------
    def temperature(self, t: float) -> float:
        mc = self.mismatch
        return min(mc.temp_start + mc.temp_rate * max(t, 0.0), mc.temp_max)

    def cast(self, model: Any = None, data: Any = None) -> RayReturns:
        r = super().cast(model, data)
        b = self.mismatch.baseline
        if b > 0:
            d = self.data if data is None else data
            pos, R = self.sensor_pose(d)
            emitter = pos + R[:, 0] * b
            back = np.linalg.norm(r.points - pos, axis=-1)
            out = np.linalg.norm(r.points - emitter, axis=-1)
            r.ranges = np.where(r.hit, 0.5 * (back + out), r.ranges)
        return r

    def timed(self, returns: RayReturns) -> RayReturns:
        """``returns`` as each zone's own time scale sees them: every ray's range times the zone's scale (its return
        lands that much farther from range 0 before it is binned), the albedo times the scale squared (the counts stay
        what the true range gives). The same ``returns`` where no zone has a scale of its own. The multipath echo, which
        the renderer draws from the range, would be scaled in time too and its amplitude by ``scale ** -echo_power``
        (the simulated sensors' echo gain is 0); the blinding is computed from the returns as they are.

        Before 2026-11-30 the scale resampled the binned histogram by linear interpolation about range 0, which also
        smoothed each return by where it fell between bins (two bins averaged half a bin off the grid; with a 2 %
        scale that phase turns once every 25 bins): a blur that follows the range, which no sensor's bins have and no
        model follows. Unit 43 of ``docs/figures/unit_scorecard.py`` read its tilted planes 0.53 deg off with it and
        0.15 without it (docs/results.md, "Each zone's own time scale rendered before the bins")."""
        if np.all(self._time_scale == 1.0):
            return returns
        s = self._time_scale[:, None]
        return dataclasses.replace(returns, ranges=returns.ranges * s, albedo=returns.albedo * s * s)

    def tail_taps(self, zone: int, warm: float = 0.0) -> np.ndarray:
        """Zone ``zone``'s extra tail at lags 1..``tail_lags`` bins when the die is ``warm`` degC above its start:
        an exponential whose taps sum to the zone's tail weight."""
        mc = self.mismatch
        k = np.arange(1, mc.tail_lags + 1, dtype=float)
        kern = np.exp(-k / (self._tail_k[zone] * (1.0 + mc.tail_per_degc * warm)))
        return kern * (self._tail_w[zone] / kern.sum())

    def _render(self, returns: RayReturns, reference: np.ndarray) -> np.ndarray:
        h = super()._render(self.timed(returns), reference, seen=returns)
        mc = self.mismatch
        warm = self.temperature(self._time) - mc.temp_start
        out = np.empty_like(h)
        for z in range(N_ZONES):
            tail = np.convolve(h[z], np.concatenate([[0.0], self.tail_taps(z, warm)]))[:N_BINS]
            hz = (h[z] + tail) / (1.0 + self._tail_w[z])
            shift = mc.drift_bins_per_degc * warm + self._skew[z] * (warm / 10.0)
            out[z] = _shift(hz, shift)
        # an ambient floor that slopes across the bins (the model's floor is flat); measure() adds the mean
        prof = mc.ambient_slope * (np.linspace(0.0, 1.0, N_BINS) - 0.5)
        return out + self.ambient[:, None] * prof[None, :]

    def measure(self, model: Any = None, data: Any = None, noise: bool | None = None,
                reference: np.ndarray | None = None) -> Frame:
        d = self.data if data is None else data
        self._time = float(d.time)
        mc = self.mismatch
        if mc.ambient_drift > 0:
            self._amb_walk = 0.9 * self._amb_walk + self._rng.normal(0.0, 0.3 * mc.ambient_drift, N_ZONES)
            wave = np.sin(2 * math.pi * self._time / 3.0 + self._amb_phase)
            self.ambient = self._amb_base * np.clip(1.0 + mc.ambient_drift * (0.7 * wave + self._amb_walk), 0.2, 3.0)
        f = super().measure(model, data, noise, reference)
        f.extra["sim"]["sensor"] = "mismatch"
        f.extra["sim"]["temperature"] = self.temperature(self._time)
        return f


def _shift(h: np.ndarray, s: float) -> np.ndarray:
    """``h`` delayed by ``s`` bins (linear interpolation; edge values held)."""
    if s == 0:
        return h
    x = np.arange(h.size, dtype=float) - s
    return np.interp(x, np.arange(h.size, dtype=float), h)


SENSOR_MODELS = ("nominal", "mismatch")


def make_sensor(model: str, scene: Any, data: Any = None, config: ToFConfig | None = None,
                mismatch: MismatchConfig | None = None) -> SimToF:
    """The simulated sensor called ``model`` (``nominal``: the forward model; ``mismatch``: not it)."""
    if model == "nominal":
        return SimToF(scene, data, config)
    if model == "mismatch":
        return MismatchedToF(scene, data, config, mismatch)
    raise ValueError(f"unknown simulated sensor {model!r}; expected one of {', '.join(SENSOR_MODELS)}")


__all__ = ["MismatchConfig", "MismatchedToF", "SENSOR_MODELS", "make_sensor"]
