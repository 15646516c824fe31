"""An independent generator of TMF8820 frames for testing: the same physics as the paper, a different code path.

Concept
-------
Every accuracy figure that renders frames with :mod:`place_safe.recovery.forward` and recovers them with
the same model only checks conventions. This module draws frames from a *separately written*
simulation of the sensor (it imports neither the forward model nor the plane renderer) that also
covers the structural choices real implementations of the paper's model make differently, and
physics the project's model leaves out, so a method can be measured on data it did not generate.

A *sensor* (:class:`SensorSpec`, drawn once per ``sensor_seed``) fixes the hardware; *frames* then vary
the plane, reflectance and noise. Calibrate on frames of one seed, test on frames of another seed
with the same sensor.

How a frame is made (SI units; bins are 128 zone bins of one-way range):

1. **Dense per-zone quadrature over SPAD pixels.** Each zone is its grid of SPAD pixels (5 x 2 at the
   sides, 4 x 2 in the middle column; pitch 0.042 x 0.097 on ``z = 1``). Each pixel has an active
   area (``fill_factor`` of its width and height, centred) sampled by ``samples x samples``
   midpoints, a fixed random gain (``pixel_gain_spread``), and the lens's ``cos^4`` fall-off.
2. **Emitter-receiver baseline.** The receiver is at the origin, the emitter at
   ``(bx, by, 0)``; a sample direction ``v`` meets the plane at ``P``; the light travels
   ``|P - E| + |P|`` (the bin position uses half of it), the irradiance is
   ``beam(angle from +z at E) * cos_light / |P - E|^2`` with ``beam = cos^beam_power``.
3. **Shading.** Lambert plus a Phong lobe about the mirror direction of the *light* ray, evaluated
   towards the receiver: ``shade = cos_light + ks * max(R . V, 0)^alpha``.
4. **SPAD saturation**, a structural choice (``saturation_mode``): ``"shaded"`` (the paper's equation,
   ``p = s (1 - exp(-g rho beam shade / (s |P-E|^2)))``) or ``"unshaded"`` (the published code:
   saturate the unshaded inverse-square term of a unit-albedo surface and multiply by the relative
   albedo and ``shade`` afterwards).
5. **Time.** Returns are deposited on a fine time grid (``FINE`` sub-bins per bin, linear split
   between neighbours), convolved with the zone's pulse and with a Gaussian timing jitter
   (``jitter`` bins), then integrated over each bin (box, not point-sampled).
6. **Pulse**, a structural choice (``pulse_mode``): the zone pulse is derived from the noise-free
   reference histogram (a three-exponential pulse integrated over reference bins, floor removed,
   time scale ``ref_time_scale``) by ``"linear"`` interpolation, ``"gaussian"`` soft-binning of every
   reference bin (sigma ``pulse_sigma`` zone bins, as the paper describes) or ``"exact"``
   integration of the continuous pulse. Each zone adds its own exponential tail
   (``zone_tail_weight``, ``zone_tail_decay``) and timing offset (``zone_offsets``, bins).
7. **Crosstalk**, a structural choice (``crosstalk_mode``): every zone receives ``crosstalk`` of the
   sum of the ``"others"`` or of ``"all"`` zones (itself included).
8. **Pile-up** (Coates, ``pileup`` per count), a flat per-zone **floor** (ambient, 60-180 counts),
   **Poisson** noise on every bin and on the reference, 24-bit clipping.

The ground truth is the plane in the receiver's frame (the sensor frame of the project).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np
from place_safe.geometry import Plane
from place_safe.sensor.frame import Frame, reported_distances
from place_safe.sensor.histogram import COUNT_MAX
from place_safe.sensor.zones import N_BINS, N_ZONES, ZONE_DIRECTIONS, ZONE_RECTS

#: Sub-bins per zone bin of the fine time grid.
FINE = 8
#: SPAD pixel pitch on the tangent plane z = 1 (16.8 um and 38.8 um behind a 400 um lens).
PIXEL_PITCH = (16.8 / 400.0, 38.8 / 400.0)
#: Reference-histogram bin (fine reference bins) where the laser pulse starts rising.
REF_PULSE_START = 13.3
#: Peak counts of the reference histogram (real sensors: about 5.7e4).
REF_PEAK_COUNTS = 5.7e4
PULSE_MODES = ("linear", "gaussian", "exact")
SATURATION_MODES = ("shaded", "unshaded")
CROSSTALK_MODES = ("others", "all")


@dataclass
class SensorSpec:
    """One simulated sensor. Units: m, bins (zone bins of one-way range), counts; see the module doc."""

    bin_size: float = 0.0141          # m of one-way range per bin
    bin_offset: float = 9.6           # bin of a zero-range return, before the pulse delay
    ref_time_scale: float = 0.279     # zone bins per reference bin
    albedo_scale: float = 3.4         # counts scale of a unit-albedo surface (model units)
    saturation: float = 320.0         # SPAD saturation level per sample (model units)
    samples: int = 5                  # samples x samples per SPAD pixel
    fill_factor: float = 0.8          # active fraction of a pixel's width and height
    pixel_gain_spread: float = 0.05   # std of the per-pixel gain (relative)
    baseline: tuple[float, float] = (0.003, 0.0)  # emitter position (x, y), m
    beam_power: float = 1.5           # emitter profile cos^beam_power
    jitter: float = 0.45              # timing jitter std, bins
    pulse_sigma: float = 0.5          # Gaussian soft-binning of the reference, bins ("gaussian" mode)
    pulse_tails: tuple[tuple[float, float], ...] = ((1.0, 1.2), (0.25, 4.5), (0.03, 20.0))  # (weight, decay in ref bins)
    pulse_rise: float = 0.45          # std of the pulse's Gaussian rise, reference bins
    zone_offsets: list[float] = field(default_factory=lambda: [0.0] * N_ZONES)     # bins
    zone_tail_weight: list[float] = field(default_factory=lambda: [0.0] * N_ZONES)  # per bin of tail
    zone_tail_decay: list[float] = field(default_factory=lambda: [2.0] * N_ZONES)   # bins
    crosstalk: float = 0.01
    pileup: float = 2e-8              # 1 / counts (Coates); 0 turns it off
    ref_floor: float = 3.0            # counts per reference bin
    pulse_mode: str = "gaussian"
    saturation_mode: str = "unshaded"
    crosstalk_mode: str = "all"
    pixel_seed: int = 0               # seed of the per-pixel gains

    def __post_init__(self) -> None:
        if self.pulse_mode not in PULSE_MODES:
            raise ValueError(f"pulse_mode must be one of {PULSE_MODES}, got {self.pulse_mode!r}")
        if self.saturation_mode not in SATURATION_MODES:
            raise ValueError(f"saturation_mode must be one of {SATURATION_MODES}, got {self.saturation_mode!r}")
        if self.crosstalk_mode not in CROSSTALK_MODES:
            raise ValueError(f"crosstalk_mode must be one of {CROSSTALK_MODES}, got {self.crosstalk_mode!r}")

    @classmethod
    def draw(cls, seed: int = 0, **overrides) -> "SensorSpec":
        """A random sensor of the family (parameters about the published ones); ``overrides`` win."""
        rng = np.random.default_rng(seed)
        ang = rng.uniform(-math.pi, math.pi)
        base = rng.uniform(0.0015, 0.004)
        spec = dict(
            bin_size=0.014131 * rng.uniform(0.98, 1.02),
            bin_offset=9.5235 + rng.uniform(-0.3, 0.3),
            ref_time_scale=0.27887 * rng.uniform(0.97, 1.03),
            albedo_scale=3.441 * rng.uniform(0.8, 1.2),
            saturation=315.85 * rng.uniform(0.8, 1.2),
            baseline=(base * math.cos(ang), base * math.sin(ang)),
            beam_power=rng.uniform(0.5, 2.5),
            jitter=rng.uniform(0.3, 0.6),
            zone_offsets=list(rng.normal(0.0, 0.1, N_ZONES)),
            zone_tail_weight=list(rng.uniform(0.0, 0.08, N_ZONES)),
            zone_tail_decay=list(rng.uniform(1.5, 3.5, N_ZONES)),
            crosstalk=rng.uniform(0.005, 0.015),
            pileup=rng.uniform(1e-8, 4e-8),
            pixel_seed=int(rng.integers(0, 2**31)),
        )
        spec.update(overrides)
        return cls(**spec)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["baseline"] = list(self.baseline)
        d["pulse_tails"] = [list(t) for t in self.pulse_tails]
        return d


@dataclass
class SceneSpec:
    """What frames to draw: planes ``z0`` uniform in ``z_range`` (m), incidence uniform in
    ``theta_range`` (rad), azimuth uniform; albedo (relative), specular weight and exponent per frame."""

    z_range: tuple[float, float] = (0.02, 0.30)
    theta_range: tuple[float, float] = (0.0, math.radians(30.0))
    albedo_range: tuple[float, float] = (0.5, 1.5)
    specular_weight_range: tuple[float, float] = (0.0, 0.3)
    specular_exponent_range: tuple[float, float] = (1.0, 4.0)
    floor_range: tuple[float, float] = (60.0, 180.0)  # counts per bin
    noise: bool = True


# ---------------------------------------------------------------------------------------------
# Sensor geometry
# ---------------------------------------------------------------------------------------------
def _pixel_grid(rect: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pixel centres (P, 2) and sizes (2,) of a zone rectangle (x0, x1, y0, y1) on z = 1."""
    x0, x1, y0, y1 = rect
    nx = max(1, int(round((x1 - x0) / PIXEL_PITCH[0])))
    ny = max(1, int(round((y1 - y0) / PIXEL_PITCH[1])))
    px, py = (x1 - x0) / nx, (y1 - y0) / ny
    cx = x0 + px * (np.arange(nx) + 0.5)
    cy = y0 + py * (np.arange(ny) + 0.5)
    gx, gy = np.meshgrid(cx, cy, indexing="ij")
    return np.stack([gx.ravel(), gy.ravel()], axis=1), np.array([px, py])


@dataclass(frozen=True)
class _Samples:
    zone: np.ndarray        # (S,) zone index of each sample
    direction: np.ndarray   # (S, 3) unit directions in the receiver frame
    weight: np.ndarray      # (S,) solid angle x pixel gain x cos^4 fall-off, per sample


def _samples(spec: SensorSpec) -> _Samples:
    """The quadrature of all zones: active pixel areas, midpoint samples, solid-angle weights."""
    rng = np.random.default_rng(spec.pixel_seed)
    zones, dirs, wts = [], [], []
    t = (np.arange(spec.samples) + 0.5) / spec.samples - 0.5  # in [-0.5, 0.5)
    for z, rect in enumerate(ZONE_RECTS):
        centres, size = _pixel_grid(rect)
        active = size * spec.fill_factor
        gains = 1.0 + spec.pixel_gain_spread * rng.standard_normal(len(centres))
        for c, g in zip(centres, gains):
            gx, gy = np.meshgrid(c[0] + active[0] * t, c[1] + active[1] * t, indexing="ij")
            x, y = gx.ravel(), gy.ravel()
            norm2 = 1.0 + x * x + y * y
            d = np.stack([x, y, np.ones_like(x)], axis=1) / np.sqrt(norm2)[:, None]
            cos_axis = d[:, 2]
            solid = (active[0] * active[1] / spec.samples ** 2) * norm2 ** -1.5
            zones.append(np.full(len(x), z))
            dirs.append(d)
            wts.append(solid * max(g, 0.0) * cos_axis ** 4)
    w = np.concatenate(wts)
    zone = np.concatenate(zones)
    # scale so the centre zone's weights sum to 2304 (the published model's rays per zone): the
    # counts then have the scale of the published parameters
    return _Samples(zone, np.concatenate(dirs), w * (2304.0 / float(w[zone == 4].sum())))


# ---------------------------------------------------------------------------------------------
# Pulse
# ---------------------------------------------------------------------------------------------
def _pulse_cdf(t: np.ndarray, spec: SensorSpec) -> np.ndarray:
    """Integral of the continuous laser pulse from -inf to ``t`` (reference bins), peak-unnormalised.

    The pulse is a sum of exponentially modified Gaussians (rise std ``pulse_rise``, decays from
    ``pulse_tails``) starting at :data:`REF_PULSE_START`.
    """
    from scipy.special import erf

    s = spec.pulse_rise
    x = np.asarray(t, dtype=float) - REF_PULSE_START
    out = np.zeros_like(x)
    for w, tau in spec.pulse_tails:
        # CDF of Gaussian(0, s) convolved with Exp(tau), times w * tau (the area of w exp(-t/tau))
        gauss_cdf = 0.5 * (1.0 + erf(x / (s * math.sqrt(2.0))))
        arg = np.clip(-x / tau + s * s / (2 * tau * tau), None, 700.0)
        emg = gauss_cdf - np.exp(arg) * 0.5 * (1.0 + erf((x - s * s / tau) / (s * math.sqrt(2.0))))
        out += w * tau * emg
    return out


def reference_histogram(spec: SensorSpec) -> np.ndarray:
    """Noise-free reference histogram (128,): the pulse integrated over reference bins, plus its floor."""
    edges = np.arange(N_BINS + 1) - 0.5
    h = np.diff(_pulse_cdf(edges, spec))
    return h / h.max() * REF_PEAK_COUNTS + spec.ref_floor


def zone_pulse(spec: SensorSpec, reference: np.ndarray | None = None) -> np.ndarray:
    """The zone pulse on the fine grid (K * FINE,), peak 1, from the noise-free reference (see ``pulse_mode``)."""
    ts = spec.ref_time_scale
    k_len = int(math.floor((N_BINS - 1) * ts)) + 1
    lag = np.arange(k_len * FINE) / FINE  # zone bins
    if spec.pulse_mode == "exact":
        # the continuous pulse integrated over one fine sub-bin (in reference-bin time)
        edges = (np.arange(k_len * FINE + 1) - 0.5) / FINE / ts
        k = np.diff(_pulse_cdf(edges, spec))
    else:
        ref = (reference_histogram(spec) if reference is None else reference) - spec.ref_floor
        ref = np.clip(ref, 0.0, None)
        if spec.pulse_mode == "linear":
            k = np.interp(lag / ts, np.arange(N_BINS), ref)
        else:  # gaussian soft-binning of every reference bin at zone position i * ts
            pos = np.arange(N_BINS) * ts
            z = (lag[:, None] - pos[None, :]) / spec.pulse_sigma
            k = np.exp(-0.5 * z * z) @ ref
    return k / k.max()


# ---------------------------------------------------------------------------------------------
# Frames
# ---------------------------------------------------------------------------------------------
class IndependentGenerator:
    """Frames of one simulated sensor (:class:`SensorSpec`); see the module doc."""

    def __init__(self, sensor: SensorSpec | None = None) -> None:
        from scipy.signal import fftconvolve  # here, not at import: the CLI imports this module's constants

        self.sensor = sensor if sensor is not None else SensorSpec.draw(0)
        s = self.sensor
        self._samples = _samples(s)
        self.reference = reference_histogram(s)
        base = zone_pulse(s, self.reference)
        # per-zone pulse: the common pulse with the zone's own tail, and the timing jitter
        n_fine = N_BINS * FINE
        t = np.arange(n_fine) / FINE
        kernels = []
        half = int(math.ceil(5 * s.jitter * FINE))
        jt = np.arange(-half, half + 1) / FINE
        jit = np.exp(-0.5 * (jt / s.jitter) ** 2)
        jit /= jit.sum()
        for z in range(N_ZONES):
            tail = s.zone_tail_weight[z] * np.exp(-t[FINE:] / s.zone_tail_decay[z]) / FINE
            kz = fftconvolve(base, np.concatenate([[1.0], np.zeros(FINE - 1), tail]))[:len(base)]
            kz = fftconvolve(kz, jit)  # centred jitter: shifts the kernel by ``half`` sub-bins, undone below
            kernels.append(kz)
        self._kernels = np.array(kernels)
        self._jitter_shift = half

    # -- rendering ----------------------------------------------------------------------------
    def expected(self, plane: Plane, albedo: float, specular_weight: float, specular_exponent: float,
                 floor: np.ndarray | float = 0.0) -> np.ndarray:
        """Expected counts (9, 128) of a plane (before Poisson noise and clipping)."""
        from scipy.signal import fftconvolve

        s, smp = self.sensor, self._samples
        n, d = plane.normal, plane.offset
        v = smp.direction
        cos_v = v @ n
        hit = cos_v > 1e-6
        t = np.where(hit, d / np.where(hit, cos_v, 1.0), 0.0)
        p = v * t[:, None]
        e = np.array([s.baseline[0], s.baseline[1], 0.0])
        le = p - e
        r_e = np.linalg.norm(le, axis=1)
        r_e = np.maximum(r_e, 1e-5)
        l_dir = le / r_e[:, None]                     # emitter -> point
        cos_light = np.clip(l_dir @ n, 0.0, None)     # incidence of the light
        beam = np.clip(l_dir[:, 2], 0.0, None) ** s.beam_power
        mirror = l_dir - 2.0 * (l_dir @ n)[:, None] * n   # reflected light direction
        rv = np.clip(-(mirror * v).sum(axis=1), 0.0, None)  # towards the receiver
        shade = cos_light + specular_weight * rv ** specular_exponent
        rho = albedo * s.albedo_scale
        sat = s.saturation
        if s.saturation_mode == "shaded":
            photons = sat * -np.expm1(-rho * beam * shade / (sat * r_e * r_e))
        else:
            # saturation of the unshaded term of a unit-albedo surface, reflectance and shading after
            photons = sat * -np.expm1(-s.albedo_scale * beam / (sat * r_e * r_e)) * albedo * shade
        amp = photons * smp.weight * hit
        # fine-grid deposit (linear split between neighbouring sub-bins), one-way range = half the path
        u = 0.5 * (r_e + t) / s.bin_size + s.bin_offset + np.asarray(s.zone_offsets)[smp.zone]
        n_fine = N_BINS * FINE
        f = (u + 0.5) * FINE  # fine index: bin b covers fine [b*FINE, (b+1)*FINE) <-> u in [b-0.5, b+0.5)
        i0 = np.floor(f).astype(int)
        frac = f - i0
        ok = hit & (i0 >= 0) & (i0 < n_fine - 1)
        fine = np.zeros((N_ZONES, n_fine))
        np.add.at(fine, (smp.zone[ok], i0[ok]), amp[ok] * (1 - frac[ok]))
        np.add.at(fine, (smp.zone[ok], i0[ok] + 1), amp[ok] * frac[ok])
        # fine sub-bin j (within a bin) sits at u = b - 0.5 + j / FINE; the pulse starts there
        conv = np.array([fftconvolve(fine[z], self._kernels[z])[self._jitter_shift:self._jitter_shift + n_fine]
                         for z in range(N_ZONES)])
        hist = conv.reshape(N_ZONES, N_BINS, FINE).sum(axis=2) / FINE
        total = hist.sum(axis=0, keepdims=True)
        if s.crosstalk_mode == "all":
            hist = hist + s.crosstalk * total
        else:
            hist = hist + s.crosstalk * (total - hist)
        if s.pileup > 0:
            before = np.cumsum(hist, axis=1) - hist
            hist = -np.expm1(-s.pileup * hist) / s.pileup * np.exp(-s.pileup * before)
        return hist + np.asarray(floor, dtype=float).reshape(-1, 1)

    def frames(self, n: int, seed: int = 0, scene: SceneSpec | None = None) -> list[Frame]:
        """``n`` frames with ground truth (random planes and reflectance from ``seed``)."""
        sc = scene or SceneSpec()
        rng = np.random.default_rng(seed)
        out = []
        for _ in range(n):
            theta = rng.uniform(*sc.theta_range)
            phi = rng.uniform(-math.pi, math.pi)
            z0 = rng.uniform(*sc.z_range)
            plane = Plane.from_angles(theta, phi, z0)
            albedo = rng.uniform(*sc.albedo_range)
            ks = rng.uniform(*sc.specular_weight_range)
            alpha = rng.uniform(*sc.specular_exponent_range)
            floor = rng.uniform(*sc.floor_range, N_ZONES)
            mean = self.expected(plane, albedo, ks, alpha, floor)
            if sc.noise:
                h = rng.poisson(np.clip(mean, 0.0, None)).astype(float)
                ref = rng.poisson(self.reference).astype(float)
            else:
                h, ref = mean, self.reference.copy()
            h = np.minimum(h, COUNT_MAX)
            pts = plane.intersect(ZONE_DIRECTIONS)
            dist = np.linalg.norm(pts, axis=1) + (rng.normal(0.0, 0.002, N_ZONES) if sc.noise else 0.0)
            meta = {"generator": "independent", "albedo": float(albedo), "specular_weight": float(ks),
                    "specular_exponent": float(alpha)}
            depths, confs = reported_distances(dist, 4, hists=h)
            out.append(Frame(h, ref, distances=depths, confidences=confs, truth=plane, extra={"meta": meta}))
        return out


def make_frames(n: int, seed: int = 0, sensor_seed: int = 0, scene: SceneSpec | None = None,
                **sensor_overrides) -> list[Frame]:
    """``n`` frames of the sensor drawn from ``sensor_seed`` (with ``sensor_overrides``)."""
    return IndependentGenerator(SensorSpec.draw(sensor_seed, **sensor_overrides)).frames(n, seed, scene)


__all__ = ["SensorSpec", "SceneSpec", "IndependentGenerator", "make_frames", "reference_histogram", "zone_pulse",
           "PULSE_MODES", "SATURATION_MODES", "CROSSTALK_MODES"]
