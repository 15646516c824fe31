"""Contact detection on a noisy TCP force estimate (the UR CB3's motor-current estimate, or an e-Series sensor).

Concept: a UR CB3 has no force sensor; ``getActualTCPForce`` is estimated from motor currents with a
standard deviation of about 3.6 N per axis per controller cycle (``shared/docs/ur5-rtde.md``). The norm of
one raw sample minus the rest reading is pure noise of about 6 N on average (a chi distribution with three
degrees of freedom), so a fixed 5 N threshold on it reads free air as contact. :class:`ContactDetector`
instead, once per controller cycle:

1. takes the force (base frame, N) minus the reading at rest (:meth:`ContactDetector.zero` keeps both the
   mean and the per-axis spread of the rest samples);
2. projects it on the **approach direction** (the tool axis the cup moves along): a table pushes back
   along it, so the axial component is the signal and the two lateral axes are left out of the test;
3. averages it over ``window`` cycles (a moving average: its noise is ``sigma / sqrt(window)``);
4. compares the average with a threshold of ``sigmas`` standard deviations of that average, set from the
   noise measured at rest (never below the configured ``noise_std`` for the controller, nor below
   ``min_threshold``);
5. calls it contact only after ``persistence`` consecutive cycles above the threshold (a persistence test),
   and lets go of it when the average falls below half the threshold (hysteresis).

Why a 6-cycle average and not a CUSUM (Page's test) on the CB3: the target is a touch that steps to 10 N
(2.8 standard deviations of one sample) seen within 50 ms, i.e. 6 cycles, in 95 % of touches, at about
3e-7 false alarms per cycle or fewer. An average over exactly those 6 cycles is the matched test for that
figure; one cycle above 5 standard deviations of it meets it (48 ms 95th percentile, 40 ms median, about
2e-7 per cycle). A one-sided CUSUM ``S = max(0, S + x / sigma - k)``, alarm at ``S > h``, minimises the
mean delay instead (32 ms median), and its slow tail is longer: measured on the same white noise, k = 1.2,
h = 5.5 gave 48 ms at the 95th percentile (95.5 % within 50 ms) at 4 false alarms in 1e7 cycles (Siegmund:
3e-7 per cycle); k = 1.2, h = 6 gave 2 in 1e7 and 56 ms; k = 1.39 (half the 10 N shift), h = 5 gave 3 in 1e7
and 56 ms (the script is in issue 29b's notes).

A lateral contact (a box beside the cup) is seen by the same test on the norm of the averaged vector, at
``lateral_sigmas`` (its noise is a 3-D chi, so it needs a higher factor).

:func:`false_alarm_rate` and :func:`detection_delay` measure a setting on synthetic noise of the given
standard deviation (numpy, no robot): the rate of false contacts per cycle and per descent, and the delay and
the true force at detection for a touch that rises as a ramp (N/s) or a step (N). ``place-safe bench robot``
prints them for the noise it measures on the arm.

Conventions: SI units (N, s); forces in the base frame; the approach direction is a unit vector along which
the tool moves towards the surface (the force of a touch points against it). Cycle counts are controller
cycles (CB3 125 Hz, e-Series 500 Hz).
"""

from __future__ import annotations

import functools
import math
from collections import deque
from typing import Annotated, Any, ClassVar

import numpy as np

from pydantic import ConfigDict, Field

from place_safe.config import ParamModel

#: Per-controller default settings (see :class:`DetectorSettings`). CB3: about 3.6 N per axis per cycle
#: (the documented spread of the motor-current estimate); 6 cycles (48 ms) averaged, 5 standard deviations
#: of the average (7.35 N), one cycle above it: about 2e-7 false alarms per cycle of such noise (11 in 6e7
#: cycles, seeds 0-5), a 10 N step seen after 40 ms median, 48 ms 95th percentile (97 % within 50 ms). Two
#: cycles in a row gave 5e-8 (3 in 6e7) but only 75 % of 10 N steps within 50 ms (48 ms median, 56-64 ms 95th
#: percentile); a one-sided CUSUM was slower at the 95th percentile for the same rate (module docstring).
#: e-Series: a flange force/torque sensor, about 1 N per axis per 2 ms cycle (assumed until
#: ``place-safe bench robot`` measures it).
CONTROLLER_DEFAULTS: dict[str, dict[str, float]] = {
    "cb3": {"noise_std": 3.6, "window": 6, "sigmas": 5.0, "persistence": 1, "min_threshold": 3.0,
            "lateral_sigmas": 7.0, "period": 1.0 / 125.0},
    "e-series": {"noise_std": 1.0, "window": 10, "sigmas": 5.0, "persistence": 5, "min_threshold": 1.5,
                 "lateral_sigmas": 7.0, "period": 1.0 / 500.0},
}


class DetectorSettings(ParamModel):
    """One contact detector's settings (SI units; cycles are controller cycles), immutable.

    ``noise_std``: N, standard deviation per axis per cycle of the force estimate at rest (the floor:
    a spread measured at rest raises it beyond its sampling error, never lowers it). ``window``: cycles
    averaged. ``sigmas``: threshold in standard deviations of the average. ``persistence``: consecutive
    cycles above it. ``min_threshold``: N, the least threshold whatever the noise. ``lateral_sigmas``: the
    factor for the norm of the averaged vector. ``period``: s, one controller cycle. The ranges are the
    fields' (the robot file's ``[contact]`` section takes them from here); a bad value raises ValueError.
    """

    model_config = ConfigDict(frozen=True)
    what: ClassVar[str] = "contact detector"
    error: ClassVar[type[Exception]] = ValueError

    noise_std: Annotated[float, Field(gt=0.0, le=50.0, description="N per axis per cycle")] = 3.6
    window: Annotated[int, Field(ge=1, le=1000, description="cycles")] = 6
    sigmas: Annotated[float, Field(gt=0.0, le=20.0, description="standard deviations")] = 5.0
    persistence: Annotated[int, Field(ge=1, le=1000, description="cycles")] = 2
    min_threshold: Annotated[float, Field(gt=0.0, le=100.0, description="N")] = 3.0
    lateral_sigmas: Annotated[float, Field(gt=0.0, le=30.0, description="standard deviations")] = 7.0
    period: Annotated[float, Field(gt=0.0, le=1.0, description="s")] = 0.008

    @classmethod
    def for_controller(cls, controller: str, **overrides: Any) -> "DetectorSettings":
        """The defaults of ``cb3`` or ``e-series`` (:data:`CONTROLLER_DEFAULTS`), with ``overrides``."""
        if controller not in CONTROLLER_DEFAULTS:
            raise ValueError(f"unknown controller {controller!r}; expected one of {sorted(CONTROLLER_DEFAULTS)}")
        d = dict(CONTROLLER_DEFAULTS[controller])
        d.update({k: v for k, v in overrides.items() if v is not None})
        d["window"], d["persistence"] = int(d["window"]), int(d["persistence"])
        return cls(**d)

    def threshold(self, noise_std: float | None = None) -> float:
        """N: the axial threshold for per-cycle noise ``noise_std`` (default the setting's)."""
        s = max(self.noise_std, noise_std or 0.0)
        return max(self.min_threshold, self.sigmas * s / math.sqrt(self.window))

    def lateral_threshold(self, noise_std: float | None = None) -> float:
        s = max(self.noise_std, noise_std or 0.0)
        return max(self.min_threshold, self.lateral_sigmas * s / math.sqrt(self.window))


class ContactDetector:
    """The detector (see the module docstring). Feed :meth:`update` once per controller cycle."""

    def __init__(self, settings: DetectorSettings | None = None) -> None:
        self.settings = settings if settings is not None else DetectorSettings()
        self.offset = np.zeros(3)
        self.rest_std = np.zeros(3)  # N per axis, measured at rest by zero()
        self.rest_samples = 0  # how many finite samples that spread was measured from
        self.reset()

    # -- rest reading --------------------------------------------------------------------------
    def zero(self, samples: Any) -> tuple[np.ndarray, np.ndarray]:
        """Take the rest reading from ``samples`` (n, 3) N, base frame: its mean becomes the offset
        subtracted from now on, its per-axis standard deviation the measured noise. Returns both."""
        s = np.asarray(samples, dtype=float).reshape(-1, 3)
        s = s[np.all(np.isfinite(s), axis=1)]
        if len(s) < 2:
            raise ValueError("zeroing the force needs at least 2 finite samples at rest")
        self.offset = s.mean(axis=0)
        self.rest_std = s.std(axis=0, ddof=1)
        self.rest_samples = len(s)
        self.reset()
        return self.offset.copy(), self.rest_std.copy()

    @property
    def noise_std(self) -> float:
        """N per axis per cycle the thresholds use: the setting, unless the spread measured at rest is larger
        than sampling alone explains.

        The largest of three per-axis standard deviations from ``n`` rest samples exceeds the true spread by
        chance (by about 10 % for the 50 samples a zeroing takes), and raising the threshold by that much cost
        a tenth of the 10 N touches their 50 ms bound. So a measured spread counts only above
        ``setting * (1 + 2.5 / sqrt(2 (n - 1)))`` (2.5 standard errors of a sample standard deviation): a
        clearly noisier arm still raises the threshold, and ``place-safe bench robot --write`` records an
        arm's own spread as the setting."""
        measured = float(self.rest_std.max())
        n = max(self.rest_samples, 2)
        if measured <= self.settings.noise_std * (1.0 + 2.5 / math.sqrt(2.0 * (n - 1))):
            return self.settings.noise_std
        return measured

    @property
    def threshold(self) -> float:
        return self.settings.threshold(self.noise_std)

    def touch_latency(self) -> float:
        """s: :func:`touch_latency` of these settings at :attr:`noise_std` (the noise measured at rest where it
        raised the threshold): how late this detector, as zeroed, reports a 10 N touch (95th percentile)."""
        return touch_latency(self.settings, math.ceil(self.noise_std * 1e3) / 1e3)  # (1 mN up: never kinder)

    @property
    def lateral_threshold(self) -> float:
        return self.settings.lateral_threshold(self.noise_std)

    def reset(self) -> None:
        """Forget the filter's history (after zeroing, or when the motion starts anew)."""
        self._buf: deque[np.ndarray] = deque(maxlen=self.settings.window)
        self._sum = np.zeros(3)
        self._above = 0
        self.contact = False
        self.axial = 0.0  # N: the averaged force against the approach direction
        self.filtered = np.zeros(3)  # N: the averaged force vector (base frame)
        self.cycles = 0

    # -- one cycle -----------------------------------------------------------------------------
    def update(self, force: Any, approach: Any) -> bool:
        """One controller cycle: ``force`` (3,) N raw base-frame reading, ``approach`` (3,) the direction the
        tool moves towards the surface. Returns whether contact is confirmed now. A non-finite reading
        counts as contact (fail closed)."""
        f = np.asarray(force, dtype=float).reshape(-1)[:3] - self.offset
        a = np.asarray(approach, dtype=float).reshape(3)
        na = float(np.linalg.norm(a))
        if not (np.all(np.isfinite(f)) and math.isfinite(na) and na > 0):
            self.contact, self.axial = True, math.inf
            return True
        if len(self._buf) == self._buf.maxlen:
            self._sum -= self._buf[0]
        self._buf.append(f)
        self._sum += f
        self.cycles += 1
        self.filtered = self._sum / len(self._buf)
        self.axial = float(-self.filtered @ (a / na))
        full = len(self._buf) == self._buf.maxlen
        hit = full and (self.axial > self.threshold or float(np.linalg.norm(self.filtered)) > self.lateral_threshold)
        self._above = self._above + 1 if hit else 0
        if self._above >= self.settings.persistence:
            self.contact = True
        elif self.contact and self.axial < 0.5 * self.threshold and \
                float(np.linalg.norm(self.filtered)) < 0.5 * self.lateral_threshold:
            self.contact = False
        return self.contact

    def contact_force(self) -> float:
        """N: the averaged contact force while contact is confirmed (the larger of its axial part and, for a
        lateral contact, its norm), else 0.0."""
        if not self.contact:
            return 0.0
        if not math.isfinite(self.axial):
            return math.inf
        return float(max(self.axial, np.linalg.norm(self.filtered)))


# ------------------------------------------------------------------------------------------------
# measuring a setting on synthetic noise
# ------------------------------------------------------------------------------------------------
def _alarms(axial: np.ndarray, lateral: np.ndarray, s: DetectorSettings, noise_std: float) -> np.ndarray:
    """Per-cycle contact onsets of the detector on axial (n,) and lateral-norm (n,) averaged streams."""
    hit = (axial > s.threshold(noise_std)) | (lateral > s.lateral_threshold(noise_std))
    c = np.cumsum(np.r_[0, hit.astype(np.int64)])
    P = s.persistence
    run = np.zeros(len(hit), dtype=bool)
    run[P - 1:] = (c[P:] - c[:-P]) == P
    return run


def _moving_average(x: np.ndarray, W: int) -> np.ndarray:
    c = np.cumsum(np.vstack([np.zeros((1,) + x.shape[1:]), x]), axis=0)
    return (c[W:] - c[:-W]) / W


def false_alarm_rate(settings: DetectorSettings, noise_std: float, cycles: int = 2_000_000, seed: int = 0,
                     chunk: int = 500_000) -> dict[str, float]:
    """False contacts on white noise of ``noise_std`` N per axis per cycle (after a perfect rest reading):
    ``{"cycles", "alarms", "per_cycle", "per_second"}`` (alarms = onsets of a confirmed contact)."""
    rng = np.random.default_rng(seed)
    W = settings.window
    alarms = 0
    done = 0
    while done < cycles:
        n = min(chunk, cycles - done)
        x = rng.normal(0.0, noise_std, (n + W - 1, 3))
        m = _moving_average(x, W)
        run = _alarms(-m[:, 2], np.linalg.norm(m, axis=1), settings, noise_std)
        alarms += int(np.count_nonzero(run[1:] & ~run[:-1]) + (1 if run[0] else 0))
        done += n
    per_cycle = alarms / max(done, 1)
    return {"cycles": float(done), "alarms": float(alarms), "per_cycle": per_cycle,
            "per_second": per_cycle / settings.period}


def detection_delay(settings: DetectorSettings, noise_std: float, *, ramp: float = 0.0, step: float = 0.0,
                    trials: int = 2000, seed: int = 1, max_seconds: float = 0.5) -> dict[str, float]:
    """Delay (s) and true axial force (N) at detection for a touch that starts between two cycles and then
    pushes back with ``step + ramp * t`` N (t in s), on white noise of ``noise_std`` N per axis per cycle.
    Returns median and 95th percentile of both over the touches seen, the 95th percentile of the delay counting a
    touch missed within ``max_seconds`` as never seen (``delay_p95_all``: inf when more than 5 % are missed), and
    the fraction missed."""
    rng = np.random.default_rng(seed)
    W, P, h = settings.window, settings.persistence, settings.period
    pre = W + P
    L = int(math.ceil(max_seconds / h))
    k = np.arange(1, L + 1)
    f = step + ramp * h * k
    x = rng.normal(0.0, noise_std, (trials, pre + L, 3))
    x[:, pre:, 2] -= f  # the touch pushes against the approach direction (-z here)
    delays, forces, missed = [], [], 0
    for t in range(trials):
        m = _moving_average(x[t], W)
        run = _alarms(-m[:, 2], np.linalg.norm(m, axis=1), settings, noise_std)
        idx = np.flatnonzero(run) + W - 1  # sample index at which the detector decides
        idx = idx[idx >= pre]
        if idx.size == 0:
            missed += 1
            continue
        j = int(idx[0]) - pre
        delays.append((j + 1) * h)
        forces.append(float(f[j]))
    d = np.asarray(delays) if delays else np.array([math.nan])
    F = np.asarray(forces) if forces else np.array([math.nan])
    every = np.concatenate([np.asarray(delays, dtype=float), np.full(missed, math.inf)])
    return {"delay_median": float(np.median(d)), "delay_p95": float(np.percentile(d, 95)),
            "delay_p95_all": float(np.percentile(every, 95, method="higher")) if every.size else math.nan,
            "force_median": float(np.median(F)), "force_p95": float(np.percentile(F, 95)),
            "missed": missed / trials}


#: N: the touch the detector is designed to see quickly (module docstring): a step to 10 N.
TOUCH_STEP = 10.0


@functools.lru_cache(maxsize=32)  # (settings are immutable; the figure is a fixed-seed simulation: 20-30 ms)
def touch_latency(settings: DetectorSettings, noise_std: float | None = None) -> float:
    """s: the 95th percentile of the delay from a :data:`TOUCH_STEP` touch to its detection, on white noise of
    ``noise_std`` N per axis per cycle (default the setting's): what
    :attr:`~place_safe.placement.config.PlacementConfig.contact_latency` should be for this detector (CB3 defaults
    48 ms, e-Series defaults 14 ms). 400 touches, a fixed seed: the same settings give the same figure. A touch missed
    within half a second counts as never seen: inf when the detector misses more than 5 % of them."""
    s = settings.noise_std if noise_std is None else max(settings.noise_std, float(noise_std))
    return detection_delay(settings, s, step=TOUCH_STEP, trials=400, seed=1)["delay_p95_all"]


__all__ = ["ContactDetector", "DetectorSettings", "CONTROLLER_DEFAULTS", "false_alarm_rate", "detection_delay",
           "touch_latency", "TOUCH_STEP"]
