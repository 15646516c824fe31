"""Histogram helpers shared by every estimator, calibration and the simulated sensor: one definition each.

* :data:`COUNT_MAX`: the TMF8820's histogram bins are 24-bit counters; a bin at this value is clipped
  (:func:`clipped_zones` also reads a flat top, or a narrower store's limit, as clipped), and a count above it is
  none the sensor can report (:func:`beyond_count_max` says so).
* :data:`FLOOR_BINS` / :func:`measure_floor`: the late bins where no return of a surface within the
  sensor's range lands (beyond ~1.3 m); their median is the per-zone floor (ambient and dark counts).
* :func:`floor_profile` / :func:`ambient_slopes`: the floor across the bins when the ambient slopes (a unit whose
  ambient changes by the same share from the first bin to the last in every frame), and each frame's slope read
  from :data:`HEAD_BINS`, the first bins, before any return.
* :func:`find_peaks`: the calibrated ``peak`` method's sub-bin position of each zone's return (the
  maximum of a cubic spline, or a windowed centroid started there: :data:`SUBBIN_METHODS`), optionally
  after :func:`undo_pileup`.
* :func:`find_returns`: the same readings with each zone's maximum, for the shape of its return.
* :data:`INTERNAL_BINS` / :data:`INTERNAL_MAX_COUNTS`: where the sensor's internal (cover-glass) return lies and
  how high it can be; a zone's maximum there is a return only when it stands well above it (:func:`find_peaks`).
* :func:`undo_pileup`: the Coates correction of SPAD pile-up (a bright return arrives early).
* :func:`first_return`: the first return above the noise, as the sensor's own firmware reports a
  distance (used to emulate on-sensor distances).

Histograms are arrays ``(..., 9, 128)`` of counts (zones 1..9 in reporting order), bins are 0-based.
"""

from __future__ import annotations

import functools
import math
import warnings

import numpy as np

from place_safe.sensor.zones import N_BINS, N_ZONES, zone_numbers

#: Largest count of the sensor's 24-bit histogram bins; a bin at this value is clipped.
COUNT_MAX = 2 ** 24 - 1
#: Widths (bits) of the unsigned integer stores a histogram may have been clipped by on its way here.
STORE_BITS = range(8, 25)
#: Counts a histogram clipped by a narrower store on its way here (an 8- to 24-bit unsigned integer) tops out at.
STORE_LIMITS = tuple(float(2 ** k - 1) for k in STORE_BITS)
#: Consecutive bins that hold a zone's highest count, at :data:`CLIP_MIN_COUNTS` or more, in a clipped return: a
#: return's peak is about 2 bins wide at half its height, so three equal tops are a flat top (a clip), not counts.
#: None of the real sweep's 477 zone histograms (or its references) holds its highest count in two bins; capped at
#: 65535, 291 of them hold it in three or more (and were read up to 30 sigma off, confidently, before this test).
CLIP_PLATEAU_BINS = 3
#: counts: how far above the histogram's least count a flat top must stand for :func:`clipped_zones` (a low return's
#: equal bins are noise; a flat floor is no return).
CLIP_MIN_COUNTS = 100.0
#: Bins at the end of every histogram used to measure the per-zone floor.
FLOOR_BINS = slice(100, N_BINS)


def measure_floor(hists: np.ndarray) -> np.ndarray:
    """Per-zone floor (..., 9) in counts: median of :data:`FLOOR_BINS`."""
    return np.median(np.asarray(hists)[..., FLOOR_BINS], axis=-1)


#: Bins of each histogram that hold the ambient alone, before the earliest return (zero range is bin 9-10): a
#: model fitted with the ambient through the pile-up (``fit_forward(..., ambient=True)``) reads it there.
AMBIENT_BINS = slice(0, 8)
#: The first of :data:`AMBIENT_BINS`, where :func:`ambient_slopes` reads a unit's slope: two bins short of them, for
#: a cover-glass return that comes early (the simulated units' glass delays spread by 0.5-1 bin).
HEAD_BINS = slice(AMBIENT_BINS.start, AMBIENT_BINS.stop - 2)


def arriving_ambient(hists: np.ndarray) -> np.ndarray:
    """Each zone's ambient as it arrives, counts per bin (..., 9): the mean of :data:`AMBIENT_BINS` of ``hists``
    (..., 9, bins), before any return and so before the return's pile-up shadows it."""
    return np.asarray(hists, dtype=float)[..., AMBIENT_BINS].mean(axis=-1)

#: Positions ``u = bin / (N_BINS - 1)`` (0 first bin, 1 last) of the middle of :data:`HEAD_BINS` and of
#: :data:`FLOOR_BINS`.
_U_HEAD = (HEAD_BINS.start + HEAD_BINS.stop - 1) / 2 / (N_BINS - 1)
_U_FLOOR = (FLOOR_BINS.start + N_BINS - 1) / 2 / (N_BINS - 1)


def floor_profile(hists: np.ndarray, slope: float = 0.0) -> np.ndarray:
    """Per-zone floor across the bins (..., 9, N_BINS), counts: the floor :func:`measure_floor` reads in
    :data:`FLOOR_BINS`, times ``(1 + slope (u - 1/2)) / (1 + slope (u_floor - 1/2))`` at ``u = bin / (N_BINS - 1)``
    (``slope``: the ambient's relative change from the first bin to the last; 0, the flat floor)."""
    floor = measure_floor(hists)[..., None]
    if slope == 0.0:
        return np.broadcast_to(floor, floor.shape[:-1] + (N_BINS,))
    u = np.arange(N_BINS) / (N_BINS - 1)
    return floor * ((1.0 + slope * (u - 0.5)) / (1.0 + slope * (_U_FLOOR - 0.5)))


def ambient_slopes(hists: np.ndarray) -> np.ndarray:
    """Each frame's ambient slope (...,), as :func:`floor_profile` takes it: the median over the zones of the slope
    that puts the mean of :data:`HEAD_BINS` and the floor of :data:`FLOOR_BINS` on one line through the bins (NaN
    where a zone's floor is not positive). On a real TMF8820 the first bins sit above the floor after a bright
    return by the pile-up's shadowing, a step at the return and not a slope: its values then change with distance."""
    h = np.asarray(hists, dtype=float)
    floor = measure_floor(h)
    ratio = h[..., HEAD_BINS].mean(axis=-1) / np.where(floor > 0, floor, np.nan)
    slope = (ratio - 1.0) / ((_U_HEAD - 0.5) - ratio * (_U_FLOOR - 0.5))
    with warnings.catch_warnings():  # a frame without a positive floor in any zone: NaN, quietly
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmedian(slope, axis=-1)


EARLY_BINS = 10
LATE_BINS = 32
SEARCH_START = 8
NOISE_SIGMAS = 5.0
MIN_NET_COUNTS = 10.0
HALF_WINDOW = 3
SUBBIN_STEPS = 100
#: Sub-bin estimators of :func:`find_peaks`: ``"spline"``, the maximum of a cubic spline through the
#: :data:`HALF_WINDOW` bins either side of the highest one; ``"centroid"``, the centre of the return
#: under a cos^2 window of half-width ``half_width`` bins that sits on it (:func:`windowed_centroid`).
SUBBIN_METHODS = ("spline", "centroid")
#: Default half-width (bins) of the centroid's window. On held-out frames of the real sweep (calibrated on
#: one half, measured on the other), 2.5-3.5 bins were best; wider windows took in more of the pulse's
#: tail, narrower ones more of the sampling phase.
CENTROID_HALF_WIDTH = 3.0
#: Half-widths (bins) :func:`windowed_centroid` accepts: under 2 bins the window's equation has several roots
#: between the samples of a noisy pulse (Newton's method, which found the root before, oscillated between them),
#: over 4 it reaches into the pulse's tail.
CENTROID_HALF_WIDTHS = (2.0, 4.0)
#: Grid points a bin on which :func:`windowed_centroid` finds its root (by linear interpolation between two):
#: within 6e-5 bins (1 um) of the exact root (at the narrowest window; 2e-5 at the default).
CENTROID_GRID_STEPS = 128
#: bins: a zone's return holds more than one surface when its centroid and its maximum disagree by more
#: than this beyond the frame's median disagreement (:func:`find_peaks`). On single surfaces (the real
#: sweep, the independent generator, both simulated sensors) the disagreement stays within 0.18 bins of the
#: median at 3 cm and beyond (0.31 bins in one zone at 0.5 cm); a box under part of a zone pulled it 0.37-0.91 bins.
MIXED_SHIFT = 0.3
#: Largest distance (bins) the centroid may move from the highest bin: a window reaching past the
#: bins gathered around it would be cut off.
CENTROID_MAX_SHIFT = 1.5
#: Bins [start, stop) the internal (cover-glass / package) return reaches: it arrives at zero range in every
#: frame, whatever the scene. On the real sweep's frames at >= 15 cm it peaks at bins 13-14 (its zero-range
#: bump spans bins 12-16); the simulated units put it at bins 12-15 (the true sensor's ``bin_offset`` plus
#: ``glass_delay`` and zone offsets, each mismatched unit its delay moved by N(0, 0.5) bins), and a pulse of
#: 2.1 bins at half maximum carries it about 3 bins past its peak (its tail after bin 18: under 4 counts).
#: From :data:`SEARCH_START` (the search starts there) to the end of that tail.
INTERNAL_BINS = (SEARCH_START, 19)
#: counts above the floor: the internal return's largest plausible height. The real sweep's bump peaks at
#: 26-44 counts; the mismatched units scale it per zone by up to x1.5 (their ``glass_spread``); a safety
#: factor of 2 covers the simulated rendering (up to 52 counts nominal, 75 on mismatched units) and a unit
#: brighter than the one measured: 44 x 1.5 x 2 = 132. A zone's maximum within :data:`INTERNAL_BINS` is a
#: return only above this plus its noise margin; a real surface there (0-5 cm) returns 1e4-1e6 counts.
INTERNAL_MAX_COUNTS = 132.0
#: Fraction of the in-window maximum a return found beyond :data:`INTERNAL_BINS` must clear on top of the
#: noise margin: the internal return's tail past the window (under 6 % of its peak on every simulated unit).
INTERNAL_TAIL_FRACTION = 0.1
#: A bin above the noise margin whose larger neighbour holds less than this fraction of its height (above the floor)
#: is a one-bin spike: no laser pulse is (the TMF8820's pulse spans about 4 bins; the real sweep's returns keep at
#: least 23 % of their height in the larger neighbour), so it is a glitch or a corrupted count, not a surface, and it
#: is lowered to its neighbour before the returns are looked for (a file of one-bin spikes read a plane at 0.51 m,
#: or 73 deg tilted: an adversarial corpus).
SPIKE_FRACTION = 0.02

_KNOTS = np.arange(-HALF_WINDOW, HALF_WINDOW + 1, dtype=float)
_KNOT_OFFSETS = _KNOTS.astype(int)
_FINE = np.linspace(-1.0, 1.0, 2 * SUBBIN_STEPS + 1)


@functools.cache
def _spline() -> np.ndarray:
    """(fine points, window) matrix: spline values at _FINE from the window's counts (built on first use: scipy's
    interpolation is slow to import, and a command's --help needs none of it)."""
    from scipy.interpolate import CubicSpline

    return CubicSpline(_KNOTS, np.eye(len(_KNOTS)), axis=0)(_FINE)


#: Largest fraction of the laser cycles x detectors that :func:`undo_pileup` lets the counts before a
#: bin use up (the correction diverges at 1: no detector left to record anything).
PILEUP_MAX_FRACTION = 0.95


def clipped_zones(hists: np.ndarray) -> np.ndarray:
    """Which histograms (..., 128) -> (...) were clipped: a bin at :data:`COUNT_MAX` (the sensor's own counters), the
    highest count held in :data:`CLIP_PLATEAU_BINS` or more consecutive bins (:data:`CLIP_MIN_COUNTS` or more above
    the least count: a flat top), or at a narrower store's limit (:data:`STORE_LIMITS`) in two or more bins. A clipped return's peak and
    centroid are wrong by up to its width and its height says nothing: estimators give such a zone no reading (a
    frame capped at 65535 counts read a plane at 42 mm as 61 mm, 10 deg, within 0.6 mm / 0.6 deg by its covariance).
    Non-finite counts are not clipped (they are refused as such)."""
    h = np.asarray(hists, dtype=float)
    top = h.max(axis=-1)
    return _clipped(h, top, np.count_nonzero(np.isnan(top)) > 0)


def _clipped(h: np.ndarray, top: np.ndarray, nan: bool) -> np.ndarray:
    """:func:`clipped_zones` of float counts ``h`` (..., 128) whose highest counts are ``top`` (...), with ``nan`` True
    exactly when a count is NaN."""
    # a count at the counters' maximum is one at the top (a histogram holding NaN has no top: each bin is asked)
    over = h >= COUNT_MAX if nan else top >= COUNT_MAX
    if over.ndim == h.ndim:
        over = over.any(axis=-1)
    at = h == top[..., None]
    # bins holding the top: 1 in almost every return (each histogram without NaN holds its top once at least, so as
    # many as histograms is once each), and the rarer tests below need two
    if not nan and np.count_nonzero(at) == top.size:
        return over
    held = at.sum(axis=-1)
    # the top stands CLIP_MIN_COUNTS above the histogram's least count: a return, not a flat floor (a zone that
    # sees nothing over a floor of 100 counts, noise-free in a synthetic frame, holds its "top" in every bin)
    flat = held >= CLIP_PLATEAU_BINS  # (a plateau needs that many bins at the top)
    if np.count_nonzero(flat):
        with np.errstate(invalid="ignore"):  # (an infinite top less an infinite least count)
            flat = (at[..., :-2] & at[..., 1:-1] & at[..., 2:]).any(axis=-1) & (top - h.min(axis=-1) >= CLIP_MIN_COUNTS)
    store = (held >= 2) & _at_store_limit(top)
    return over | flat | store


def _at_store_limit(counts: np.ndarray) -> np.ndarray:
    """Whether each count is one of :data:`STORE_LIMITS` (``2**k - 1`` for ``k`` in :data:`STORE_BITS`): ``count + 1``
    a power of two (its mantissa exactly 0.5) of such an exponent, and the count that power less one exactly (a count
    within half a unit of the last place of ``2**23 - 1``, 2**23 - 1 + 1e-9, rounds to 2**23 when 1 is added);
    NaN and infinity are not."""
    c = np.asarray(counts, dtype=float)
    mantissa, exponent = np.frexp(c + 1.0)
    return ((mantissa == 0.5) & (c == np.ldexp(1.0, exponent - 1) - 1.0) & (exponent - 1 >= STORE_BITS.start)
            & (exponent - 1 < STORE_BITS.stop))


def beyond_count_max(hists: np.ndarray, what: str = "histogram") -> str | None:
    """Why counts -- 128 of one histogram, or (9, 128) of the zones -- cannot be the TMF8820's: a count above
    :data:`COUNT_MAX`, more than its 24-bit counters hold (not a clip: a clipped counter stops at the maximum, and
    :func:`clipped_zones` reads a bin above it as clipped too; this names it), e.g. ``"histogram counts above the
    sensor's 24-bit maximum (16777215) in zone(s) 5: not counts it can report"``; None when there is none.
    ``what`` names the histogram."""
    h = np.asarray(hists, dtype=float)
    over = h > COUNT_MAX  # (NaN is not above it)
    if not np.count_nonzero(over):
        return None
    where = f" in zone(s) {zone_numbers(over.any(axis=-1))}" if h.ndim == 2 else ""
    return f"{what} counts above the sensor's 24-bit maximum ({COUNT_MAX}){where}: not counts it can report"


def undo_pileup(net: np.ndarray, pileup: float) -> np.ndarray:
    """Floor-subtracted counts (..., 128) with SPAD pile-up undone (Coates' correction).

    A SPAD records at most one photon per laser cycle, so a photon arriving in bin ``i`` is counted
    only when none arrived earlier in that cycle: expected recorded counts are
    ``m_i = (1 - exp(-k h_i)) / k * exp(-k H_i)`` for true counts ``h`` with ``H_i`` the true counts
    before bin ``i`` and ``k = pileup`` (1/counts: one over laser cycles x detectors; the forward
    model's :func:`~place_safe.recovery.forward.apply_pileup`). Summing telescopes to
    ``M_i = (1 - exp(-k H_i)) / k`` for the recorded counts before bin ``i``, hence
    ``H_i = -log(1 - k M_i) / k`` and ``h_i = H_{i+1} - H_i``. Pile-up moves a bright return's peak
    earlier (up to a bin and more at a few centimetres on white), by an amount that differs between
    zones that see different brightness: a tilt the surface does not have. Negative net counts count
    as 0; ``k M`` is capped at :data:`PILEUP_MAX_FRACTION`. ``pileup = 0`` returns ``net`` unchanged.

    This inverts Coates' pile-up only: the forward model's ``pileup_shadow = 1`` (its default). With a shadow
    ``s < 1`` the model's earlier counts shadow later bins by ``exp(-k s H_i)``, which this over-corrects. The
    peak method's ``pileup`` is its own calibration's (:func:`~place_safe.calibration.points.fit_pileup`), or the
    forward fit's ``pileup`` through :func:`~place_safe.calibration.points.adopt_pileup`, and that fit holds
    ``pileup_shadow`` at 1 (it is not in :data:`~place_safe.calibration.forward_fit.FITTED`; only a fit asked for
    its ``PULSE_TERMS`` frees it, and ``calibrate`` does not ask), so the two agree.
    """
    x = np.asarray(net, dtype=float)
    k = float(pileup)
    if not (math.isfinite(k) and k >= 0.0):
        raise ValueError(f"pileup must be a finite number >= 0 (1/counts), got {pileup!r}")
    if k == 0.0:
        return x
    recorded = np.maximum(x, 0.0).cumsum(axis=-1)  # recorded counts up to and including each bin
    true_upto = np.log1p(-np.minimum(k * recorded, PILEUP_MAX_FRACTION))
    np.negative(true_upto, out=true_upto)
    true_upto /= k
    out = true_upto.copy()
    out[..., 1:] -= true_upto[..., :-1]  # h_i = H_{i+1} - H_i (nothing before bin 0)
    out += np.minimum(x, 0.0)
    return out


def _median(x: np.ndarray) -> np.ndarray:
    """Median over the last axis (as :func:`numpy.median`, without its overhead on small arrays)."""
    s = np.sort(x, axis=-1)
    k = s.shape[-1]
    return s[..., k // 2] if k % 2 else 0.5 * (s[..., k // 2 - 1] + s[..., k // 2])


def find_peaks(hists: np.ndarray, pileup: float = 0.0, subbin: str = "spline",
               half_width: float = CENTROID_HALF_WIDTH, *, heights: bool = False) -> tuple[np.ndarray, ...]:
    """Sub-bin return positions (..., 9) in bins, return mask (..., 9) and saturation mask (..., 9); with
    ``heights``, then each zone's return height (..., 9): its highest bin in counts above the floor, after
    pile-up is undone (0 where there is no return).

    ``hists`` is (..., 9, 128) counts (any leading shape). Zones without a return, or clipped, or
    with non-finite counts, are False in the mask and NaN in the positions. ``pileup`` (1/counts,
    calibrated: :attr:`place_safe.recovery.points.PeakParams.pileup`): undo SPAD pile-up of the
    floor-subtracted counts first (:func:`undo_pileup`); 0 leaves them as recorded. ``subbin``: one of
    :data:`SUBBIN_METHODS`; ``"centroid"`` refines the spline peak with :func:`windowed_centroid` of
    ``half_width`` bins.

    A centroid follows every surface in its window in proportion to its light, so where a zone sees two
    (a box under part of it, an edge) it lands between them, on neither, where the maximum stays on the
    stronger. A zone whose centroid and maximum disagree by more than :data:`MIXED_SHIFT` bins beyond the
    frame's median disagreement (the pulse's own skew) therefore reads its maximum plus that median: the
    nearest the centroid's calibration can come to the stronger surface. (A random placement scene with a
    box 41 mm beside the cup read a level table as tilted 11.7 deg through pulled centroids.)
    """
    reading, _, valid, saturated, height = _returns(hists, pileup, subbin, half_width)
    out = (np.where(valid, reading, np.nan), valid, saturated)
    return out + (np.where(valid, height, 0.0),) if heights else out


def find_returns(hists: np.ndarray, pileup: float = 0.0, subbin: str = "spline",
                 half_width: float = CENTROID_HALF_WIDTH, *, heights: bool = False) -> tuple[np.ndarray, ...]:
    """:func:`find_peaks`' readings (..., 9) with each zone's maximum (the spline's, bins (..., 9); NaN where
    there is no return), from the same pass: the reading for the zone's point, the maximum for the shape of
    its return (a shoulder or a second return is looked for relative to the maximum, which a nearer surface
    mixed into the return does not pull). Then the return and saturation masks. With ``subbin="spline"``
    the two positions are the same. ``heights``: the return heights last, as in :func:`find_peaks`."""
    reading, top, valid, saturated, height = _returns(hists, pileup, subbin, half_width)
    out = (np.where(valid, reading, np.nan), np.where(valid, top, np.nan), valid, saturated)
    return out + (np.where(valid, height, 0.0),) if heights else out


def _returns(hists: np.ndarray, pileup: float, subbin: str,
             half_width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(reading, spline maximum, valid, saturated, height) of :func:`find_peaks`, not yet masked."""
    if subbin not in SUBBIN_METHODS:
        raise ValueError(f"subbin must be one of {', '.join(SUBBIN_METHODS)}, got {subbin!r}")
    h = np.asarray(hists, dtype=float)
    finite_bins = np.isfinite(h)
    finite = True  # (every zone's counts finite: the usual frame)
    if np.count_nonzero(finite_bins) < h.size:
        finite = finite_bins.all(axis=-1)
        h = np.where(finite_bins, h, 0.0)
    saturated = _clipped(h, h.max(axis=-1), False)  # (NaN counts set to 0 above)
    floor = np.minimum(_median(h[..., :EARLY_BINS]), _median(h[..., -LATE_BINS:]))
    noise = _noise_margin(floor)
    x = _despiked(undo_pileup(h - floor[..., None], pileup), floor, noise)
    k, top, has_return = _highest_return(x, floor, noise)
    rows = x.reshape(-1, x.shape[-1])  # one row per zone (of every frame)
    kc = np.minimum(k, N_BINS - 1 - HALF_WINDOW)  # (k >= SEARCH_START >= HALF_WINDOW: the window's start is in)
    cols = kc.reshape(-1, 1) + _KNOT_OFFSETS
    if rows.shape[-1] == N_BINS:  # the window's counts by flat index (a third of indexing by row and column)
        window = rows.take(_row_starts(rows.shape[0]) + cols)
    else:  # (histograms of another length: a window past a row's end is an IndexError, not the next row's counts)
        window = rows[np.arange(rows.shape[0])[:, None], cols]
    window = window.reshape(kc.shape + (len(_KNOTS),))  # (..., 9, W)
    fine = window @ _spline().T  # (..., 9, F)
    pos = kc + _FINE[fine.argmax(axis=-1)]  # kc == k except for a top in the last bins
    valid = has_return & ~saturated
    if finite is not True:
        valid &= finite
        saturated = saturated & finite
    reading = pos
    if subbin == "centroid":
        centre = windowed_centroid(rows, k.reshape(-1), pos.reshape(-1), half_width).reshape(pos.shape)
        reading = _unmixed(centre, pos, valid)
    return reading, pos, valid, saturated, top


def _highest_return(x: np.ndarray, floor: np.ndarray,
                    noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each zone's return bin (..., 9), its height (counts above the floor) and whether it is a return, from the
    floor-subtracted counts ``x`` (..., 9, 128) and the floors (..., 9).

    The highest bin from :data:`SEARCH_START` on is a return when it clears the noise margin
    (:data:`NOISE_SIGMAS` Poisson sigmas of the floor and :data:`MIN_NET_COUNTS`). Within the internal return's
    bins (:data:`INTERNAL_BINS`) it must clear :data:`INTERNAL_MAX_COUNTS` by the same number of Poisson sigmas of
    the floor plus that return (189 counts on a floor of 0, 236 on 300): otherwise it may be the internal return alone (a zone that sees nothing would read a surface at zero range). Such a zone reads instead the
    highest bin beyond the internal return, a return if it clears the noise margin plus
    :data:`INTERNAL_TAIL_FRACTION` of the in-window maximum (the internal return's tail). ``noise``: the floors'
    :func:`_noise_margin`, if the caller has it.
    """
    lo, hi = INTERNAL_BINS
    noise = _noise_margin(floor) if noise is None else noise
    searched = x[..., SEARCH_START:]
    k = searched.argmax(axis=-1) + SEARCH_START
    top = searched.max(axis=-1)  # (the count at k)
    if k.size == 0 or k.min() >= hi:  # (every zone's highest bin beyond the internal return's: the usual frame)
        return k, top, top > noise
    inside = (k >= lo) & (k < hi)
    # the internal return at its largest plus NOISE_SIGMAS of its own and the floor's shot noise
    near = INTERNAL_MAX_COUNTS + NOISE_SIGMAS * np.sqrt(np.maximum(floor, 0.0) + INTERNAL_MAX_COUNTS + 1.0)
    internal = inside & (top <= near)  # not told apart from the internal return
    if not np.count_nonzero(internal):
        return k, top, top > noise
    k2 = x[..., hi:].argmax(axis=-1) + hi
    top2 = _at_bins(x, k2)
    far = top2 > noise + INTERNAL_TAIL_FRACTION * np.maximum(top, 0.0)
    k = np.where(internal, k2, k)
    has_return = np.where(internal, far, top > noise)
    top = np.where(internal, top2, top)
    return k, top, has_return


def _row_starts(n: int, n_bins: int = N_BINS) -> np.ndarray:
    """The flat index (n, 1) of the first count of each of ``n`` rows of ``n_bins`` counts (C order): a row's bin ``k``
    is ``rows.take(starts + k)``."""
    return _ROW_STARTS[:n] if n <= len(_ROW_STARTS) and n_bins == N_BINS else (np.arange(n) * n_bins)[:, None]


#: :func:`_row_starts` of up to a frame's zones (the usual call), worked out once.
_ROW_STARTS = np.arange(N_ZONES)[:, None] * N_BINS
_ROW_STARTS.flags.writeable = False


def _at_bins(x: np.ndarray, k: np.ndarray) -> np.ndarray:
    """``x[..., k]`` per histogram: the counts (...) of histograms ``x`` (..., 128) at bins ``k`` (...) (as
    ``np.take_along_axis``, without its overhead on one frame)."""
    rows = x.reshape(-1, x.shape[-1])
    return rows[np.arange(rows.shape[0]), k.reshape(-1)].reshape(k.shape)


def _noise_margin(floor: np.ndarray) -> np.ndarray:
    """Counts above the floor a return must clear: :data:`NOISE_SIGMAS` Poisson sigmas of the floor and
    :data:`MIN_NET_COUNTS`."""
    return np.maximum(NOISE_SIGMAS * np.sqrt(np.maximum(floor, 0.0) + 1.0), MIN_NET_COUNTS)


def _despiked(x: np.ndarray, floor: np.ndarray, noise: np.ndarray | None = None) -> np.ndarray:
    """The floor-subtracted counts ``x`` (..., 128) with each one-bin spike (a bin above the noise margin whose larger
    neighbour holds less than :data:`SPIKE_FRACTION` of it; at the histogram's ends, its one neighbour) lowered to that
    neighbour: no laser pulse is one bin wide, and a spike taller than a zone's real return hid the return.
    ``noise``: the floors' :func:`_noise_margin`, if the caller has it."""
    side = np.empty_like(x)  # each bin's larger neighbour (at either end, its one neighbour)
    np.maximum(x[..., :-2], x[..., 2:], out=side[..., 1:-1])
    side[..., 0] = x[..., 1]
    side[..., -1] = x[..., -2]
    spike = (x > (_noise_margin(floor) if noise is None else noise)[..., None]) & (side < SPIKE_FRACTION * x)
    return np.where(spike, np.maximum(side, 0.0), x) if np.count_nonzero(spike) else x


def _unmixed(centre: np.ndarray, top: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The centroids (..., 9), with each zone whose centroid lies more than :data:`MIXED_SHIFT` bins from its
    maximum ``top`` beyond the frame's median shift (over its valid zones) replaced by ``top`` + that median
    (see :func:`find_peaks`)."""
    shift = centre - top
    used = shift[valid]
    if used.size == 0 or float(used.max() - used.min()) <= MIXED_SHIFT:  # no zone can lie that far from a median
        return centre
    n = valid.sum(axis=-1, keepdims=True)
    ordered = np.sort(np.where(valid, shift, np.inf), axis=-1)  # invalid zones last
    lo = np.take_along_axis(ordered, np.maximum((n - 1) // 2, 0), axis=-1)
    hi = np.take_along_axis(ordered, np.maximum(n // 2, 0), axis=-1)
    median = np.where(n > 0, 0.5 * (lo + hi), 0.0)
    with np.errstate(invalid="ignore"):
        mixed = valid & (np.abs(shift - median) > MIXED_SHIFT)
    return np.where(mixed, top + median, centre) if np.count_nonzero(mixed) else centre


def windowed_centroid(rows: np.ndarray, top: np.ndarray, start: np.ndarray,
                      half_width: float = CENTROID_HALF_WIDTH) -> np.ndarray:
    """Centre ``p`` (bins, (N,)) of each row's return under a window that sits on it: the root of
    ``g(p) = sum_i w((i - p) / half_width) (i - p) x_i`` with ``w(u) = cos^2(pi u / 2)`` for ``|u| < 1``
    (``g`` falls through it as ``p`` rises).

    ``rows`` (N, 128) floor-subtracted counts (negative counts count as 0), ``top`` (N,) the highest
    bin of each row, ``start`` (N,) where the search starts (the spline peak). ``p`` stays within
    :data:`CENTROID_MAX_SHIFT` bins of ``top``. ``half_width`` within :data:`CENTROID_HALF_WIDTHS`.

    The root is found on a grid: ``g`` is linear in the counts, so its values at :data:`CENTROID_GRID_STEPS` points
    a bin around ``top`` are one matrix product (:func:`_centroid_kernel`), and the root is interpolated linearly
    between the two grid points it lies between (within 6e-5 bins, 1 um, of the exact root on the real sweep and on
    noisy synthetic returns; Newton's method from the spline peak, which this replaced, stopped within 3e-3 bins and
    cost more than twice as much a frame). A row whose ``g`` falls through zero once in the allowed range reads that
    root, wherever ``start`` is. Otherwise (two surfaces in the window, or no root within the range) the search goes
    from ``start`` the way ``g`` points there (up where ``g > 0``) to the first root that way, or to the end of the
    range (:func:`_centroid_search`); a row without counts in its window reads ``start``, and one whose counts or
    ``start`` are not numbers reads NaN.

    Why not the spline's maximum: a spline through samples of a peaked pulse puts its top off the
    pulse's by an amount that depends on where the pulse falls between bin centres and on the pulse's
    width and shape, so the error has a period of one bin and changes with range, brightness and tilt.
    The window is smooth and wider than the pulse's core, so its centre moves with the pulse by the same
    amount wherever it falls between bins; the window's cut into the pulse's tail is a constant offset,
    which calibration takes up.
    """
    lo_w, hi_w = CENTROID_HALF_WIDTHS
    if not (math.isfinite(half_width) and lo_w <= half_width <= hi_w):
        raise ValueError(f"half_width must be between {lo_w:g} and {hi_w:g} bins, got {half_width!r}")
    top = np.asarray(top)
    if top.size == 0:
        return np.asarray(start, dtype=float).copy()
    kernel, grid, offsets = _centroid_kernel(float(half_width))
    reach = len(offsets) // 2  # (offsets run -reach .. reach)
    n_bins = rows.shape[-1]
    idx = top[:, None] + offsets  # (N, W) bins gathered around the top
    at = _row_starts(len(top), n_bins)  # (flat indices into rows)
    if int(top.min()) < reach or int(top.max()) + reach >= n_bins:  # a return at either end: missing bins are 0
        # (as Python integers: a top of a narrow integer type would wrap round)
        x = np.where((idx >= 0) & (idx < n_bins), rows.take(at + np.minimum(np.maximum(idx, 0), n_bins - 1)), 0.0)
    else:
        x = rows.take(at + idx)
    g = np.maximum(x, 0.0, out=x) @ kernel  # (N, S): g at top + grid
    above = g > 0.0
    turns = above[:, :-1] != above[:, 1:]  # (N, S - 1): g changes sign between grid points k and k + 1
    # every row from above zero to not: an odd number of turns each, so as many turns as rows is one each
    n = len(top)
    if np.count_nonzero(turns) == n and np.count_nonzero(above[:, 0]) == n and not np.count_nonzero(above[:, -1]):
        return top + _root(g, grid, turns.argmax(axis=1))
    return top + _centroid_search(g, above, np.asarray(start, dtype=float) - top, grid)


def _root(g: np.ndarray, grid: np.ndarray, k: np.ndarray) -> np.ndarray:
    """The root (N,) of each row of ``g`` (N, S) on ``grid`` (S,) in its interval ``[k, k + 1]`` (N,), where
    ``g[k] > 0 >= g[k + 1]``: linear interpolation between the two grid points."""
    at = np.arange(0, g.size, g.shape[1]) + k  # (flat indices: a third faster than g[rows, k] on a frame's zones)
    g0, g1 = g.take(at), g.take(at + 1)
    return grid.take(k) + (grid[1] - grid[0]) * g0 / (g0 - g1)


def _centroid_search(g: np.ndarray, above: np.ndarray, start: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """:func:`windowed_centroid`'s readings (N,), relative to the top, where a row's ``g`` (N, S) on ``grid`` (S,)
    does not fall through zero just once (``above``: ``g > 0``): from ``start`` (N,), relative to the top and clipped
    to the grid, the way ``g`` points there to the first interval ``[k, k + 1]`` where it falls (``g[k] > 0 >=
    g[k + 1]``), or the end of the range that way where there is none; the grid point itself where ``g`` is 0 there
    (a root on it); ``start`` in a row without counts (``g`` 0 everywhere); NaN where ``g`` or ``start`` is not a
    number."""
    at = np.arange(g.shape[0])
    bad = ~(np.isfinite(start) & np.isfinite(g).all(axis=1))
    s = np.where(bad, 0.0, np.minimum(np.maximum(start, grid[0]), grid[-1]))
    i0 = np.rint((s - grid[0]) / (grid[1] - grid[0])).astype(np.intp)
    g_start = g[at, i0]
    falls = above[:, :-1] & ~above[:, 1:]  # (N, S - 1)
    cols = np.arange(falls.shape[1])
    right = falls & (cols >= i0[:, None])
    left = falls & (cols < i0[:, None])
    k_right = right.argmax(axis=1)
    k_left = len(cols) - 1 - left[:, ::-1].argmax(axis=1)
    up = g_start > 0.0
    k = np.where(up, k_right, k_left)
    found = np.where(up, right[at, k_right], left[at, k_left])
    with np.errstate(divide="ignore", invalid="ignore"):  # (the rows without a root found: replaced below)
        out = np.where(found, _root(g, grid, k), np.where(up, grid[-1], grid[0]))
    out = np.where(g_start == 0.0, grid[i0], out)
    out = np.where(g.any(axis=1), out, s)
    return np.where(bad, np.nan, out)


@functools.lru_cache(maxsize=16)
def _centroid_kernel(half_width: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(kernel (W, S), grid (S,), the window's bins relative to the top (W,): ``-reach .. reach``) of
    :func:`windowed_centroid`: ``g`` at ``top + grid`` is the window's counts ``x`` (the ``W`` bins ``top - reach ..
    top + reach``) times the kernel: ``kernel[j, s] = w(d / half_width) d``,
    ``d = j - grid[s]``, 0 where ``|d| >= half_width``. The grid spans :data:`CENTROID_MAX_SHIFT` bins either side
    in steps of ``1 / CENTROID_GRID_STEPS``; ``reach`` covers the window from either end of it."""
    reach = int(math.ceil(half_width + CENTROID_MAX_SHIFT))
    grid = np.linspace(-CENTROID_MAX_SHIFT, CENTROID_MAX_SHIFT,
                       int(round(2 * CENTROID_MAX_SHIFT * CENTROID_GRID_STEPS)) + 1)
    d = np.arange(-reach, reach + 1, dtype=float)[:, None] - grid
    kernel = np.where(np.abs(d) < half_width, np.cos(0.5 * math.pi * d / half_width) ** 2 * d, 0.0)
    offsets = np.arange(-reach, reach + 1)
    for a in (kernel, grid, offsets):
        a.flags.writeable = False
    return kernel, grid, offsets


def first_return(hists: np.ndarray, threshold: float = 8.0, relative: float = 0.05) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sub-bin position of the first return per zone, whether one was found, and its peak SNR.

    The floor is the median of :data:`FLOOR_BINS`; a return starts at the first bin more than
    ``threshold`` Poisson sigmas of the floor and ``relative`` of the zone's largest return above it; its peak is the largest bin in the 6 bins
    from there (a return is about 4 bins wide), refined by a parabola through it and its neighbours.
    hists: (Z, 128); returns three (Z,) arrays (bins, bool, peak height in floor sigmas).
    """
    h = np.asarray(hists, dtype=float)
    z = h.shape[0]
    floor = np.median(h[:, FLOOR_BINS], axis=1, keepdims=True)
    sig = h - floor
    noise = np.sqrt(np.maximum(floor, 1.0))
    above = sig > np.maximum(threshold * noise, relative * sig.max(axis=1, keepdims=True))
    found = above.any(axis=1)
    first = np.argmax(above, axis=1)
    idx = np.clip(first[:, None] + np.arange(6)[None], 0, N_BINS - 1)
    win = np.take_along_axis(sig, idx, axis=1)
    k = np.clip(first + np.argmax(win, axis=1), 1, N_BINS - 2)
    rows = np.arange(z)
    y0, y1, y2 = sig[rows, k - 1], sig[rows, k], sig[rows, k + 1]
    den = y0 - 2 * y1 + y2
    frac = np.where(np.abs(den) > 1e-12, 0.5 * (y0 - y2) / np.where(den == 0, 1, den), 0.0)
    return k + np.clip(frac, -0.5, 0.5), found, y1 / noise[:, 0]


#: Bins at either end of the reference histogram where its peak may not be: a pulse there is cut off
#: (or is not the laser pulse at all), and a forward model built on it renders every return misplaced.
REFERENCE_EDGE_BINS = 3


def reference_floor(reference) -> float:
    """Floor (counts) of a reference histogram (128,): the median of the bins before its pulse, at most
    :data:`EARLY_BINS` of them and ending :data:`REFERENCE_EDGE_BINS` before the peak. Not the late bins:
    the pulse's tail runs to the last bin (a real TMF8820's reference still holds about 20 counts there,
    on a floor of 4). With fewer than 3 bins before the pulse, the smaller of their median and the late
    bins' (:data:`FLOOR_BINS`). The reference must be one :func:`reference_problem` accepts."""
    r = np.asarray(reference, dtype=float)
    end = int(np.argmax(r)) - REFERENCE_EDGE_BINS
    early = r[max(end - EARLY_BINS, 0):max(end, 0)]
    if early.size >= 3:
        return float(np.median(early))
    late = float(measure_floor(r))
    return min(float(np.median(early)), late) if early.size else late


def reference_problem(reference) -> str | None:
    """Why a reference histogram (128 counts) cannot serve as the laser pulse, or None if it can.

    It must be finite real counts, not clipped at :data:`COUNT_MAX`, with a peak that stands out of
    its floor (median of :data:`FLOOR_BINS`) by the same noise margin a zone return needs
    (``NOISE_SIGMAS`` Poisson sigmas and ``MIN_NET_COUNTS``), and that peak not within
    :data:`REFERENCE_EDGE_BINS` of either end.
    """
    try:
        r = np.asarray(reference, dtype=float)
    except (TypeError, ValueError, OverflowError):
        return "reference histogram is not numeric"
    if r.shape != (N_BINS,) or not np.all(np.isfinite(r)):
        return "reference histogram is not 128 finite counts"
    if not np.any(r > 0):
        return "reference histogram is empty (all zeros): no laser pulse to model returns with"
    if (beyond := beyond_count_max(r, "reference histogram")) is not None:
        return beyond
    if clipped_zones(r):
        return "reference histogram is clipped (saturated counts: a flat top, or counters at their maximum)"
    floor = float(measure_floor(r))
    k = int(np.argmax(r))
    if r[k] - floor <= float(_noise_margin(np.asarray(floor))):
        return "reference histogram has no pulse above its floor"
    if k < REFERENCE_EDGE_BINS or k >= N_BINS - REFERENCE_EDGE_BINS:
        return f"reference histogram peaks at bin {k}, at the edge of the histogram (not a laser pulse)"
    return None


__all__ = ["COUNT_MAX", "STORE_BITS", "STORE_LIMITS", "CLIP_PLATEAU_BINS", "CLIP_MIN_COUNTS", "clipped_zones", "beyond_count_max", "FLOOR_BINS", "AMBIENT_BINS", "HEAD_BINS", "arriving_ambient", "measure_floor", "floor_profile", "ambient_slopes", "find_peaks", "find_returns", "windowed_centroid", "SUBBIN_METHODS",
           "CENTROID_HALF_WIDTH", "CENTROID_HALF_WIDTHS", "MIXED_SHIFT", "INTERNAL_BINS", "INTERNAL_MAX_COUNTS", "SPIKE_FRACTION", "first_return", "reference_floor",
           "reference_problem"]
