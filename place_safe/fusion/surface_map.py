"""Surface map: what each zone saw, in the base frame, and whether the cup's landing footprint was observed.

Concept: the plane filter extrapolates the patch of surface the sensor sees -- 70 mm beside the cup by
the mount's design -- to where the cup lands. A :class:`SurfaceMap` keeps the per-zone evidence
instead: for every frame, each zone's first return as a base-frame point (the calibrated peak
mapping, :class:`~place_safe.recovery.points.PeakParams`) and whether the zone shows a second, later
surface. From it come

* per-frame multi-surface evidence (:meth:`SurfaceMap.add` -> :class:`FrameSurfaces`): the largest set
  of zones that lie on one plane, a step's zones beside it counted (:func:`consensus`: a level parallel to it,
  parted from it by a straight line); the other zones, second (farther) returns and
  nearer surfaces mixed into a zone's return (:func:`early_returns`) mean the frame saw more than one
  surface (an edge, a step, clutter); a farther surface mixed into a zone's return (:func:`late_returns`: a step
  down under part of it) is edge evidence against the footprint. The loop replaces such a frame's plane by
  the consensus plane of its inlier zones, or drops the frame when no majority agrees;
* the footprint verdict (:meth:`SurfaceMap.verdict` -> :class:`FootprintVerdict`): the cup's landing
  footprint -- a disc of ``cup_radius + margin`` on the fused surface, centred on the cup's axis -- is
  *observed* by a frame whose field of view held the whole disc; it is *supported* when every zone
  that saw part of the disc returned a single surface within ``tolerance`` of the fused plane. A
  missing return or a surface below means an edge or a step down, a surface above means clutter or
  a step up. The verdict also says how far the TCP must move sideways (``look_shift``) to bring the
  disc into view, so the placement can survey it before descending.

Conventions: SI units; base-frame points and planes (``n . x = d``, ``n`` up); sensor frame +z the
optical axis. Zone ``z`` covers the directions nearest to its calibrated centre direction
(``PeakParams.directions()``); the field of view is the square ``|x/z|, |y/z| <= tan(fov_half_angle)``.
Bins of a second return are counted after the first return's peak.
"""

from __future__ import annotations

import itertools
import math
from collections import Counter, deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from place_safe.geometry import MAX_REACH, finite_number
from place_safe.sensor.histogram import measure_floor
from place_safe.sensor.zones import N_BINS, N_ZONES, ZONE_RECTS, zone_numbers

#: rad, half the TMF8820's 33 x 33 deg field of view, less a margin for the mount's calibration error.
FOV_HALF_ANGLE = math.radians(15.5)
#: bins after the first return's peak before a second return may start (the pulse's own tail is shorter).
SECOND_GAP_BINS = 8
#: A second return must rise this many Poisson sigmas of the floor above the tail before it ...
SECOND_SIGMAS = 10.0
#: ... and by this fraction of the first return's height.
SECOND_RELATIVE = 0.004
#: Last bin searched for a second return (the floor window starts at bin 100).
SECOND_LAST_BIN = 100
#: Bins before the first return's peak where a nearer surface mixed into the zone shows (one bin is about
#: 14 mm of range; the pulse's own leading edge has fallen to about 1 % of its peak there on clean
#: tables, sim and real, at 0.5-40 cm).
EARLY_BINS = 3.0
#: A nearer surface must lift that bin by this fraction of the peak's height above the floor (over the
#: frame's median edge there) ...
EARLY_RELATIVE = 0.06
#: ... and by this many Poisson sigmas of the floor.
EARLY_SIGMAS = 6.0
#: Bins after the first return's peak where a farther surface mixed into the zone shows: a step down under part of
#: the zone 15-110 mm below (1-8 bins; farther is a second return of its own). Board 7 of `--kind boards --seed 4`, a
#: 22.5 mm board with the cup's rim 5 mm past its edge: zones reaching past the edge read within 2 mm of the board (the
#: dark table below returns little light) but their falling edge three bins after the peak stands 5-37 % of the peak's
#: height above the frame's median there; zones on one surface stay within 3.6 % (random level tables, both simulated
#: sensors) and the real sweep's within 5.1 % (6.5 % below 2 cm). Two bins after the peak the real pulse's own edge
#: scatters by 10-14 % from zone to zone with the peak's sub-bin position.
LATE_BINS = 3.0
#: A farther surface must lift that bin by this fraction of the peak's height above the floor (over the frame's median
#: there) ...
LATE_RELATIVE = 0.08
#: Zones that must agree on one plane for a frame's consensus plane (a majority of the 9).
MIN_INLIERS = 5
#: A plane through one zone fewer (a majority still) that fits its zones this many times as closely (least squares, the
#: residual per degree of freedom) is a frame's consensus instead of the plane through the most zones: a box 25 mm tall
#: beside the footprint at 17 cm blends into the zones' returns (1.6 bins apart: no second return, no shoulder), and a
#: plane tilted 18.5 deg through its top and the far row of the table took 6 zones at 1.2 mm RMS, within the 3.8 mm
#: tolerance, where the table's own 5 zones lay within 0.03 mm; the placement refused the level table as tilted (random
#: scene 69 of seed 65).
CLOSER_FIT = 10.0
#: ... when the plane through the most zones fits them no better than this share of the frame's tolerance (per degree
#: of freedom): a plane through one surface fits its zones to their noise (a tenth of a millimetre or so at 17 cm), and
#: five zones can fit far more closely by chance (two degrees of freedom); scene 69's six fit at 1.7 mm against a
#: 3.8 mm tolerance, 36 times the table's five. With zones as noisy as 1 mm (a tilted table beside a box, 1000 draws)
#: the rule gave up the six for five of them in 5 frames (for a plane through the box in none; 5 and 1/3: 16 and 5)
POOR_FIT = 1.0 / 3.0
#: Directions (rad) tried for a straight line between two sets of zones in the zones' layout (:func:`_separable`):
#: the nine zone centres lie on a near-square grid, and every line that parts two sets of them leaves a wedge of
#: directions tens of degrees wide.
_LINE_DIRECTIONS = np.deg2rad(np.arange(0.0, 360.0, 1.0))
#: The zones' centres on the sensor's tangent plane (ZONE_RECTS), projected on each of those directions (D, 9).
_LAYOUT_PROJECTIONS = (np.stack([np.cos(_LINE_DIRECTIONS), np.sin(_LINE_DIRECTIONS)], axis=1)
                       @ np.stack([ZONE_RECTS[:, :2].mean(axis=1), ZONE_RECTS[:, 2:].mean(axis=1)]))
#: The zones of a step's other level (:func:`_step_zones`) lie within this fraction of the frame's tolerance of one
#: level parallel to the plane: a table's row past a board's edge lies within 0.1-0.5 mm of one at 30 cm, and up to
#: 3.8 mm where the edge crosses the row at a slant (random board 139 of seed 4: 5.9 mm tolerance)
STEP_LEVEL = 1.0
#: Zones a step's other level needs (:func:`_step_zones`): two lie on a level in any plane that tilts along them only,
#: and a plane tilted 6 deg through a box's corner of zones and four of a level table's, seen from 10 cm, left the
#: table's other two within the 3.5 mm tolerance of a level parallel to it (scenarios/set/
#: clutter_beside_footprint_late_doubt.toml)
STEP_ZONES = 3
#: rad: a reading with as many inliers as the winning step's plane that reads a slope this far from it leaves the
#: frame without a step (:func:`_unambiguous`)
STEP_AMBIGUOUS = math.radians(3.0)
#: rad: the most a step's level may turn from facing the sensor (a plane through a table's zones and the floor's past
#: its edge can hold five zones and stand 76 deg from the optical axis)
STEP_INCIDENCE = math.radians(60.0)
#: Zones of a frame lie on one plane within this fraction of their median range (see
#: :meth:`SurfaceMap.consensus_tolerance`), at least :data:`CONSENSUS_MIN` m.
CONSENSUS_RELATIVE = 0.02
CONSENSUS_MIN = 0.002
#: m the sensor climbs above the lowest height that can hold the footprint when it must climb.
CLIMB_MARGIN = 0.01
#: m inside the edge of the view the survey aims for.
VIEW_SLACK = 0.008
#: rad inside the edge of the view the footprint must be, at the current pose, to count as in view.
SIGHT_SLACK_RAD = math.radians(1.0)
#: Observations kept.
MAX_OBSERVATIONS = 400
#: m between footprint sample points (and points on its rim).
DISC_SPACING = 0.01
_RIM_POINTS = 24
#: m above the survey height up to which a frame's zones are small enough to certify or blame the footprint.
CLOSE_SLACK = 0.04
#: The zone on the optical axis (0-based): the second look centres it on footprint points the latest views doubt.
CENTRE_ZONE = 4
#: m beyond the footprint's rim where a frame's optical axis may still meet the plane and the frame count as looking
#: at the footprint: the second look centres the view on the points in doubt, often on the rim, and arrives within a
#: few millimetres (the arm's arrival tolerance, the fused plane moving a little). Random scene 0 of seed 74 (a box
#: 36 mm beyond the footprint) aimed 0.6 mm past the rim; none of its look's views counted, so the centred clean views
#: never lifted the veto the first survey views had raised, and the cup was refused. The descent's views aim about
#: 70 mm from the centre (the sensor beside the cup) and stay out.
AIM_SLACK = 0.005
#: m below the fused plane from which a zone centred under the cup, in a frame looking at the footprint, reads a step
#: down under part of the cup (the *lowered* doubt of :meth:`SurfaceMap.footprint`) even within the frame's consensus
#: tolerance (2 % of the range: 4.6 mm from the survey height). A thin board's edge under the rim: board 39 of `--kind
#: boards --seed 4` (6.2 mm thick, 9 mm of the rim past its edge, a user-calibrated mismatched unit): from the survey
#: pose the centre zone, two thirds of its footprint points past the edge, read 3.8 mm below the fused plane and
#: certified them, while the zones on the board read within 0.7 mm of it.
LOWERED_STEP = 0.0025


def second_returns(hists: np.ndarray, first: np.ndarray, valid: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per zone (9,): whether a second, later return follows the first, and its peak bin (NaN if none).

    A second return is a bin at least :data:`SECOND_GAP_BINS` after the first peak that rises above the
    lowest count between them by ``SECOND_SIGMAS`` floor sigmas and ``SECOND_RELATIVE`` of the first
    return: the first return's own tail only decays, a farther surface rises again.
    """
    h = np.asarray(hists, dtype=float)
    floor = measure_floor(h)
    sigma = np.sqrt(np.maximum(floor, 0.0) + 1.0)
    has = np.zeros(N_ZONES, dtype=bool)
    where = np.full(N_ZONES, np.nan)
    for z in range(N_ZONES):
        if not valid[z] or not np.isfinite(first[z]):
            continue
        x = h[z] - floor[z]
        k0 = int(round(first[z]))
        top = x[min(max(k0, 0), N_BINS - 1)]
        start = k0 + SECOND_GAP_BINS
        if start >= SECOND_LAST_BIN - 2:
            continue
        seg = x[start:SECOND_LAST_BIN]
        low = np.minimum.accumulate(seg)
        rise = seg - low
        need = max(SECOND_SIGMAS * sigma[z], SECOND_RELATIVE * top)
        hit = np.flatnonzero(rise > need)
        if hit.size:
            k = hit[0]
            k_peak = k + int(np.argmax(seg[k:min(k + 6, seg.size)]))
            has[z], where[z] = True, float(start + k_peak)
    return has, where


def early_returns(hists: np.ndarray, first: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per zone (9,): whether a nearer surface is mixed into the first return (clutter a few centimetres
    above the surface, covering part of the zone).

    Such a surface lies too close to the main one for a peak of its own; it shows as a shoulder on the
    return's leading edge. The leading edge is read :data:`EARLY_BINS` before each zone's peak (linear
    interpolation at the sub-bin position) as a fraction of the peak's height above the floor; the
    pulse's own edge is what the frame's zones show there in the median (the zones share the pulse, and
    clutter rarely covers most of them). A zone has a nearer surface when its edge stands
    :data:`EARLY_RELATIVE` above that median and :data:`EARLY_SIGMAS` floor sigmas above the floor.
    """
    return _shoulders(hists, first, valid, -EARLY_BINS, EARLY_RELATIVE)


def late_returns(hists: np.ndarray, first: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per zone (9,): whether a farther surface is mixed into the first return (part of the zone a step of 1-8 bins
    lower: the table past a board's edge). As :func:`early_returns`, on the falling edge :data:`LATE_BINS` after the
    peak, by :data:`LATE_RELATIVE` over the frame's median there."""
    return _shoulders(hists, first, valid, LATE_BINS, LATE_RELATIVE)


def _shoulders(hists: np.ndarray, first: np.ndarray, valid: np.ndarray, offset: float, relative: float
               ) -> np.ndarray:
    """Per zone (9,): whether the histogram ``offset`` bins from the zone's peak ``first`` stands ``relative`` of the
    peak's height above the frame's median there and :data:`EARLY_SIGMAS` floor sigmas above the floor."""
    h = np.asarray(hists, dtype=float)
    floor = measure_floor(h)
    sigma = np.sqrt(np.maximum(floor, 0.0) + 1.0)
    x = np.arange(N_BINS, dtype=float)
    top = np.full(N_ZONES, np.nan)
    rise = np.full(N_ZONES, np.nan)
    for z in range(N_ZONES):
        p = float(first[z])
        if not valid[z] or not math.isfinite(p) or not 0 <= p + offset <= N_BINS - 1:
            continue
        top[z] = max(float(np.interp(p, x, h[z])), float(h[z].max())) - floor[z]
        rise[z] = float(np.interp(p + offset, x, h[z])) - floor[z]
    ok = np.isfinite(top) & (top > 0)
    if not ok.any():
        return np.zeros(N_ZONES, dtype=bool)
    edge = float(np.median(rise[ok] / top[ok]))
    with np.errstate(invalid="ignore"):
        return ok & (rise > (max(edge, 0.0) + relative) * top) & (rise > EARLY_SIGMAS * sigma)


def consensus(points: np.ndarray, valid: np.ndarray, tolerance: float, deep: bool = True, early: Any = None
              ) -> tuple[np.ndarray, np.ndarray, float]:
    """The largest set of zone points (9, 3) lying on one plane within ``tolerance`` (m).

    Every plane through three valid points is tried (at most 84); the one that explains the most zones -- its
    inliers, and with ``deep`` the zones off it when :data:`STEP_ZONES` or more lie on one level parallel to it,
    beyond it on one side and parted from its inliers by a straight line across the zones' layout
    (:func:`_step_zones`: a step, the table past a board's edge, not where a zone of its upper level shows a nearer
    surface mixed into its return, ``early``; not where a reading with as many inliers reads another slope,
    :func:`_unambiguous`),
    their level counting one zone fewer for its offset -- then the one that fits its inliers most closely per degree
    of freedom (without a step, the most inliers; ties: smallest RMS;
    when its least-squares residual per degree of freedom is :data:`POOR_FIT` of ``tolerance`` or more, the largest
    set of at least :data:`MIN_INLIERS` zones -- one zone fewer only, unless ``deep`` -- that fits :data:`CLOSER_FIT`
    times as closely wins: :func:`_closer_subset`) is refitted by least squares on its inliers. ``deep`` False suits
    zone points a centimetre off (an uncalibrated peak mapping): their own plane fits them poorly, and subsets fit by
    chance. Returns the inlier mask (9,), the plane ``(nx, ny, nz, d)`` (sensor frame, ``n_z > 0``) and its RMS
    residual; all-False / NaN when fewer than 3 points are valid or they are collinear.
    """
    return _consensus_reading(points, valid, tolerance, deep, early, False)[:3]


def consensus_and_ambiguity(points: np.ndarray, valid: np.ndarray, tolerance: float, early: Any = None
                            ) -> tuple[np.ndarray, np.ndarray, float, float]:
    """:func:`consensus` (``deep``) and its :func:`slope_ambiguity` (rad), the candidate planes fitted once."""
    return _consensus_reading(points, valid, tolerance, True, early, True)


def _consensus_reading(points: np.ndarray, valid: np.ndarray, tolerance: float, deep: bool, early: Any,
                       ambiguity: bool) -> tuple[np.ndarray, np.ndarray, float, float]:
    """:func:`consensus` and, with ``ambiguity``, its :func:`slope_ambiguity` (else 0), the candidates fitted once."""
    from place_safe.recovery.points import fit_planes

    P = np.asarray(points, dtype=float)
    ok = np.asarray(valid, dtype=bool) & np.all(np.isfinite(P), axis=1)
    idx = np.flatnonzero(ok)
    none = (np.zeros(N_ZONES, dtype=bool), np.full(4, np.nan), math.nan, 0.0)
    if idx.size < 3:
        return none
    if (cand := _candidates(P, idx, tolerance)) is None:
        return none
    n, res, inl = cand
    count = inl.sum(0)
    rms = np.sqrt(np.where(inl, res ** 2, 0.0).sum(0) / np.maximum(count, 1))
    # the same zones may read as a board's level with the table past its edge, or as a steep ramp through that table
    # and the board's near row with the far row a level below it (random board 60 of seed 4): the heights alone may
    # not tell them apart, and preferring the more level reading read a tilted table with a box on it level as often
    # (session 75's check: tilted planes with a patch of zones moved by a parallel level, 48 of 3000 read 2 deg or
    # more less tilted that the plane through the most zones had read right). Where readings disagree no step is read
    step, steps = np.zeros(len(n), dtype=int), None
    if deep and count.max() < idx.size:  # a plane through every zone explains more than any step can
        steps = _step_zones(P, inl, idx, tolerance, early)
        step = _unambiguous(count, *steps)
    # of the planes that explain as many zones, the one that fits its own more closely (per degree of freedom), a step
    # or not: a plane tilted through the board's six and the table's row fits them at 2.9 mm, the board's own at
    # 0.4 (random board 61 of seed 4)
    best = np.lexsort((rms, -count, _per_dof(rms, count), -_explained(count, step)))[0]
    mask = np.zeros(N_ZONES, dtype=bool)
    mask[idx[inl[:, best]]] = True
    nf, df, rf, okf = fit_planes(P[None], mask[None])
    if not okf[0]:
        return none
    closer = _closer_subset(P, idx, mask, float(rf[0]), tolerance, MIN_INLIERS if deep else int(mask.sum()) - 1)
    if closer is not mask:
        mask = closer
        nf, df, rf, okf = fit_planes(P[None], mask[None])
    # keep the refit honest: zones it moved beyond the tolerance leave the set
    r = np.abs(P @ nf[0] - df[0])
    mask &= r <= tolerance
    plane, rms0 = np.append(nf[0], df[0]), float(rf[0])
    amb = _ambiguity(P, idx, tolerance, inl, steps, mask, plane, rms0, early) if ambiguity else 0.0
    return mask, plane, rms0, amb


def _candidates(P: np.ndarray, idx: np.ndarray, tolerance: float
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Every plane through three of the valid zones ``idx`` of the points ``P`` (9, 3): their unit normals (c, 3), the
    valid zones' distances from each (k, c) and which lie within ``tolerance`` (k, c); None when all are collinear."""
    combos = np.array(list(itertools.combinations(idx, 3)))
    a, b, c = P[combos[:, 0]], P[combos[:, 1]], P[combos[:, 2]]
    n = np.cross(b - a, c - a)
    norm = np.linalg.norm(n, axis=1)
    good = norm > 1e-12
    if not good.any():
        return None
    n, a = n[good] / norm[good, None], a[good]
    res = np.abs(P[idx] @ n.T - np.sum(n * a, axis=1))
    return n, res, res <= tolerance


def slope_ambiguity(points: np.ndarray, valid: np.ndarray, tolerance: float, inliers: np.ndarray, plane: np.ndarray,
                    rms: float, early: Any = None) -> float:
    """rad: how far from the consensus plane (``inliers`` (9,), ``plane`` ``(n, d)`` and its RMS ``rms`` from
    :func:`consensus` of the same ``points``, ``valid``, ``tolerance`` and ``early``) another reading of the frame's
    zones puts the slope; 0 where there is none.

    Another reading: a plane through :data:`MIN_INLIERS` or more zones that fits them as one surface (its
    least-squares residual per degree of freedom within :data:`POOR_FIT` of ``tolerance``), with a step's other level
    beside it (:func:`_step_zones`: :data:`STEP_ZONES` or more zones on one level parallel to it, not vetoed by
    ``early``), whose zones and step hold as many zones as the consensus does, and whose slope lies
    :data:`STEP_AMBIGUOUS` or more from the consensus plane's. A frame whose zones hold every valid one on a plane
    that fits them closely has none.

    A board seen past its far edge from 30-45 cm leaves the table in one row of zones, 13-23 mm farther; the zones in
    between see both. A plane tilted 6-10 deg through all nine within the 7-8 mm tolerance, or through the table's
    row and the board's far row (a two-row plane fits exactly), is the consensus, and the board's own six with the
    table's row a level below them reads as well (random boards 51, 60, 61, 73, 109 of seed 4). The heights of one
    frame do not tell which is right: a real slope reads the same from every height, a board's edge leaves the view
    as the sensor descends. The fusion holds the slope uncertain by this angle while such frames are in its window
    (:meth:`PlaneFilter.update <place_safe.fusion.plane_filter.PlaneFilter.update>`), so that no frames that can be
    read either way make the surface confidently tilted, or level."""
    P = np.asarray(points, dtype=float)
    idx = np.flatnonzero(np.asarray(valid, dtype=bool) & np.all(np.isfinite(P), axis=1))
    if idx.size < 3 or (cand := _candidates(P, idx, tolerance)) is None:
        return 0.0
    return _ambiguity(P, idx, tolerance, cand[2], None, inliers, plane, rms, early)


def _ambiguity(P: np.ndarray, idx: np.ndarray, tolerance: float, inl: np.ndarray, steps: Any, inliers: np.ndarray,
               plane: np.ndarray, rms: float, early: Any) -> float:
    """:func:`slope_ambiguity` from the candidate planes' inliers ``inl`` (:func:`_candidates`) and their
    :func:`_step_zones` (``steps``; None: not yet found)."""
    from place_safe.recovery.points import fit_planes

    mask = np.asarray(inliers, dtype=bool)
    held = int(mask.sum())
    n0 = np.asarray(plane, dtype=float)[:3]
    if idx.size < MIN_INLIERS + STEP_ZONES - 1 or held < MIN_INLIERS or not np.all(np.isfinite(n0)):
        return 0.0
    if held >= idx.size and float(_per_dof(np.array(rms), np.array(held))) < POOR_FIT * tolerance:
        return 0.0  # one surface under every zone
    count = inl.sum(0)
    extra, normals, _ = steps if steps is not None else _step_zones(P, inl, idx, tolerance, early)
    rival = count + extra >= held
    if not rival.any():
        return 0.0
    sets = np.zeros((int(rival.sum()), N_ZONES), dtype=bool)
    sets[:, idx] = inl[:, rival].T
    sets, first = np.unique(sets, axis=0, return_index=True)
    _, _, r, fit = fit_planes(np.broadcast_to(P, (len(sets),) + P.shape), sets)
    close = fit & (_per_dof(r, sets.sum(1)) <= POOR_FIT * tolerance)
    if not close.any():
        return 0.0
    n = normals[np.flatnonzero(rival)[first[close]]]
    n = n[np.all(np.isfinite(n), axis=1)]  # no normal: facing the sensor beyond STEP_INCIDENCE (not a reading)
    if n.size == 0:
        return 0.0
    angle = float(np.arccos(np.clip(np.abs(n @ n0), 0.0, 1.0).min()))
    return angle if angle >= STEP_AMBIGUOUS else 0.0


def _step_zones(points: np.ndarray, inl: np.ndarray, idx: np.ndarray, tolerance: float, early: Any = None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For each candidate plane (columns of ``inl``, its inliers among the valid zones ``idx`` (0-8), whose points are
    ``points`` (9, 3), sensor frame): how many zones off it it explains as a step, the least-squares normal of its
    inliers (NaN: fewer than :data:`MIN_INLIERS`), and whether it is a reading of its own (its zones one surface,
    the rest none or one level beside it).

    About the least-squares plane of its inliers (:data:`MIN_INLIERS` or more, facing the sensor within
    :data:`STEP_INCIDENCE`), the zones off it are a level beside it when they lie on its one side beyond
    ``tolerance``, within :data:`STEP_LEVEL` of it of one another (a level parallel to it) and on the far side of a
    straight line from its inliers in the zones' layout (:func:`_separable`), and no zone of the upper level (the one
    nearer the sensor) shows a nearer surface mixed into its return (``early``, (9,) or None: a zone below a step may,
    one above it cannot). They count as a step when there are :data:`STEP_ZONES` or more of them.

    A board's edge seen from 20-40 cm leaves the table past it in a row or a corner of zones, 5-25 mm farther; the
    consensus tolerance there is 4-8 mm, and a plane tilted 6-10 deg through the table's row and the board's far
    row took more zones (7) than the board's own (6), the placement refusing the level board as tilted from the
    first frames (random boards 13-142 of seed 4). The step takes all nine. A single surface with clutter keeps its
    consensus: the plane through most zones is the surface itself, and the clutter's zones only add to it."""
    from place_safe.recovery.points import fit_planes

    P = np.asarray(points, dtype=float)
    extra = np.zeros(inl.shape[1], dtype=int)
    normals = np.full((inl.shape[1], 3), np.nan)
    reading = np.zeros(inl.shape[1], dtype=bool)
    sets = np.zeros((inl.shape[1], N_ZONES), dtype=bool)
    sets[:, idx] = inl.T
    others = np.zeros_like(sets)
    others[:, idx] = ~inl.T
    maybe = np.flatnonzero(sets.sum(1) >= MIN_INLIERS)
    if maybe.size == 0:
        return extra, normals, reading
    # many of the 84 planes hold the same zones: each set is fitted and judged once
    _, first, which = np.unique(sets[maybe], axis=0, return_index=True, return_inverse=True)
    which = np.asarray(which).reshape(-1)
    nearer = None if early is None else np.asarray(early, dtype=bool).reshape(-1)
    if nearer is not None and nearer.shape != (N_ZONES,):
        nearer = None
    n, d, _, ok = fit_planes(np.broadcast_to(P, (first.size,) + P.shape), sets[maybe[first]])
    for j, c in enumerate(maybe[first]):
        if not ok[j] or not n[j, 2] >= math.cos(STEP_INCIDENCE):
            continue
        normals[c] = n[j]
        if not others[c].any():
            reading[c] = True
            continue
        s = P[others[c]] @ n[j] - d[j]
        if others[c].sum() < 2 or not ((s > tolerance).all() or (s < -tolerance).all()) \
                or not float(s.max() - s.min()) <= STEP_LEVEL * tolerance or not _separable(sets[c], others[c]):
            continue
        upper = others[c] if s[0] * d[j] < 0 else sets[c]  # the sensor at the origin lies on the side of -d
        if nearer is not None and (nearer & upper).any():
            continue
        reading[c] = True
        if others[c].sum() >= STEP_ZONES:
            extra[c] = int(others[c].sum())
    same = maybe[first][which]  # each candidate of maybe's representative
    extra[maybe], normals[maybe], reading[maybe] = extra[same], normals[same], reading[same]
    return extra, normals, reading


def _unambiguous(count: np.ndarray, step: np.ndarray, normals: np.ndarray, reading: np.ndarray) -> np.ndarray:
    """``step`` (:func:`_step_zones`' zones per candidate plane, with ``count`` inliers, the least-squares normals of
    its inliers ``normals`` and whether each is a ``reading`` of its own), or none at all where a reading with as many
    inliers as the steps that explain the most zones reads a slope :data:`STEP_AMBIGUOUS` or more from theirs.

    In a 3 x 3 grid a plane through two rows of zones fits them exactly whatever their heights: a box's top over one
    row beside a level table's two reads as well as a ramp 17 deg steep through the box's row and the table's next
    with the far row a level below it, and a tilted table with a box on it as a level ramp. A board on a tilted table
    with one zone of the table's row lost (two left, not a step) read as a ramp through the board's near row and
    the table's two zones, with the board's far row a step above it: 2 deg for 12 (a review's search). Where the
    readings disagree the consensus is the plane through the most zones, as without steps."""
    has = step > 0
    if not has.any():
        return step
    score = _explained(count, step)
    top = has & (score == score[has].max())
    n = normals[reading & (count >= count[top].min())]  # the steps on top are readings themselves
    if float(np.clip(np.abs(n @ normals[np.flatnonzero(top)[0]]), 0.0, 1.0).min()) < math.cos(STEP_AMBIGUOUS):
        return np.zeros_like(step)
    return step


def _explained(count: np.ndarray, step: np.ndarray) -> np.ndarray:
    """Zones a candidate plane explains: its ``count`` inliers and its ``step`` zones (:func:`_step_zones`), the step's
    level costing one zone, for its offset (two zones of a level table beside a box read as a level below a plane
    tilted 4 deg through the box's zone, the half-covered centre and five of the table's, 7 + 2 against the table's
    own 8: a review's box beside the footprint)."""
    return count + np.maximum(step - 1, 0)


def _separable(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether a straight line parts the zones ``a`` from the zones ``b`` (masks (9,)) in the zones' layout on the
    sensor's tangent plane (:data:`_LAYOUT_PROJECTIONS`)."""
    pa = np.where(a, _LAYOUT_PROJECTIONS, -np.inf).max(1)
    pb = np.where(b, _LAYOUT_PROJECTIONS, np.inf).min(1)
    return bool(np.any(pa < pb - 1e-9))


def _per_dof(rms: np.ndarray, count: np.ndarray) -> np.ndarray:
    """A least-squares plane's RMS residual per residual degree of freedom (a plane takes three)."""
    return rms * np.sqrt(count / np.maximum(count - 3, 1))


def _closer_subset(P: np.ndarray, idx: np.ndarray, mask: np.ndarray, rms: float, tolerance: float, fewest: int
                   ) -> np.ndarray:
    """``mask`` (the zones on the plane through the most; ``rms`` its least-squares plane's RMS residual), or, when
    that plane fits them poorly
    (per degree of freedom :data:`POOR_FIT` of ``tolerance`` or more), the largest set of at least ``fewest`` (and
    :data:`MIN_INLIERS`) of the valid zones ``idx`` that fits :data:`CLOSER_FIT` times as closely, each of its zones
    within ``tolerance`` of its own plane and, two or more zones fewer, every zone of ``mask`` it leaves out nearer the
    sensor than that plane by :data:`POOR_FIT` of ``tolerance`` or more (ties: the closest fit). Every such subset is
    tried (at most 256 of nine).

    One surface fits its zones to their noise; a box covering a corner zone and parts of its neighbours lifts them
    by fractions of its height, all within the tolerance of a plane tilted through them (random scene 16 of seed
    85: a 12 mm box at 20 cm, four zones lifted 2-12 mm, nine zones on a plane tilted 6.4 deg at 2.1 mm RMS against
    the table's five at 0.1 mm), and the level table was refused as tilted from the first frames."""
    from place_safe.recovery.points import fit_planes

    n_best = int(mask.sum())
    sigma0 = float(_per_dof(np.array(rms), np.array(n_best)))
    if n_best <= MIN_INLIERS or not sigma0 >= POOR_FIT * tolerance:
        return mask
    for k in range(n_best - 1, max(fewest, MIN_INLIERS) - 1, -1):
        combos = np.array(list(itertools.combinations(idx, k)))  # k < n_best <= len(idx): never empty
        sets = np.zeros((len(combos), N_ZONES), dtype=bool)
        np.put_along_axis(sets, combos, True, axis=1)
        n, d, r, ok = fit_planes(np.broadcast_to(P, (len(sets),) + P.shape), sets)
        with np.errstate(invalid="ignore"):
            ahead = np.nan_to_num(d)[:, None] - np.einsum("zk,bk->bz", np.nan_to_num(P), np.nan_to_num(n))
            inside = np.all(np.where(sets, np.abs(ahead) <= tolerance, True), axis=1)
            # what it leaves out of the poorly fitting set stands clear of it, nearer the sensor: a box's top or a
            # zone part-covered by it, not the scatter of one surface (a checker table's zones scatter a millimetre,
            # and one of 126 five-zone sets fits it ten times as closely by chance) nor a plane through a box's
            # zones that leaves the table's farther (both found by a review of this rule). One zone fewer keeps the
            # rule it had: a zone partly past an edge or over a step down reads farther
            dropped = mask[None, :] & ~sets
            clear = np.all(np.where(dropped, ahead >= POOR_FIT * tolerance, True), axis=1) | (k == n_best - 1)
            sigma = _per_dof(r, np.full(len(sets), k))
            good = ok & inside & clear & (CLOSER_FIT * sigma <= sigma0)
        if good.any():
            return sets[np.flatnonzero(good)[np.argmin(sigma[good])]]
    return mask


@dataclass
class FrameSurfaces:
    """Per-zone evidence of one frame (see module docstring). Arrays are (9,) or (9, 3)."""

    stamp: float
    base_T_sensor: np.ndarray
    points_base: np.ndarray  # first return of each zone, base frame (NaN without a return)
    valid: np.ndarray  # zone has a first return
    second: np.ndarray  # zone shows a second, later surface
    second_depth: np.ndarray  # m, how much farther the second return is (range), NaN if none
    early: np.ndarray  # zone shows a nearer surface mixed into its first return (clutter, a step up)
    inliers: np.ndarray  # zones on the frame's consensus plane
    plane_sensor: np.ndarray  # (4,) consensus plane (n, d) in the sensor frame, NaN if none
    rms: float = math.nan
    tolerance: float = math.nan  # m, the frame's consensus tolerance (SurfaceMap.consensus_tolerance of its valid zones)
    ambiguity: float = 0.0  # rad, how far another reading of its zones puts the slope (slope_ambiguity; 0: none)
    late: np.ndarray = field(default_factory=lambda: np.zeros(N_ZONES, dtype=bool))  # a farther surface mixed in

    @property
    def multi_surface(self) -> bool:
        """More than one surface in view: a valid zone off the consensus plane, or a second return."""
        return bool(np.any(self.valid & ~self.inliers) or np.any(self.second) or np.any(self.early))

    @property
    def split(self) -> np.ndarray:
        """Zones (9,) whose field holds more than one surface: a second, farther return or a nearer surface mixed
        into the first. The first return of such a zone comes from part of its field only, whose mean direction is
        not the zone's: its point lies off the surface by up to 1-2 % of the range even where the zone agrees with
        the others within the consensus tolerance (a zone half past a table edge reads 1-2 mm near at 10 cm)."""
        return self.valid & (self.second | self.early)

    def describe(self) -> str:
        out = []
        off = np.flatnonzero(self.valid & ~self.inliers)
        if off.size:
            out.append("zone(s) " + zone_numbers(off) + " off the plane of the others")
        two = np.flatnonzero(self.second)
        if two.size:
            out.append("zone(s) " + zone_numbers(two) + " see a second surface "
                       f"{np.nanmax(self.second_depth[two]) * 1e3:.0f} mm farther")
        near = np.flatnonzero(self.early)
        if near.size:
            out.append("zone(s) " + zone_numbers(near) + " see a nearer surface mixed into the return")
        none = np.flatnonzero(~self.valid)
        if none.size:
            out.append("no return in zone(s) " + zone_numbers(none))
        return "; ".join(out)


@dataclass
class FootprintVerdict:
    """What the map says about the cup's landing footprint (see module docstring)."""

    observed: int = 0  # frames that held the whole footprint in view
    supported: int = 0  # of those, frames whose footprint zones saw one surface on the fused plane
    problem: str | None = None  # why the footprint cannot take the cup (edge, step, clutter, no support)
    in_view: bool = False  # the footprint is in the field of view at the current pose
    look_shift: np.ndarray = field(default_factory=lambda: np.zeros(3))  # m, base frame: TCP move to see it
    view_margin: float = math.nan  # m the sensor may descend before the footprint leaves the view
    certify_margin: float = math.nan  # m the sensor must still descend before its frames can certify it
    close_frames: int = 0  # frames from the close height that saw part of the footprint
    recheck_point: np.ndarray | None = None  # base frame: centre of the points behind ``problem``, or of those in doubt
    recheck_shift: np.ndarray | None = None  # m, base frame: TCP move that centres the view on it
    doubt: str | None = None  # what the latest view of points now in doubt saw (raised, or a step lower)


class SurfaceMap:
    """Per-zone surface evidence in the base frame and the landing-footprint verdict (see module doc).

    ``peak_params``: the calibrated reading -> point mapping (bins); ``cup_radius``, ``margin``,
    ``tolerance`` in m; ``min_frames``: observing frames the footprint needs; ``relative``: the
    fraction of the zones' range within which a frame's zones agree on one plane
    (:meth:`consensus_tolerance`; 0: ``tolerance`` at every range, for an uncalibrated mapping whose
    points are good to a centimetre only).
    """

    def __init__(self, peak_params: Any, cup_radius: float = 0.035, margin: float = 0.01,
                 tolerance: float = 0.008, min_frames: int = 3, fov_half_angle: float = FOV_HALF_ANGLE,
                 relative: float = CONSENSUS_RELATIVE) -> None:
        self.params = peak_params
        self.radius = float(cup_radius) + float(margin)
        self.cup_radius = float(cup_radius)
        self.tolerance = float(tolerance)
        self.relative = float(relative)
        self.min_frames = int(min_frames)
        self.tan_fov = math.tan(fov_half_angle)
        self._dirs = np.asarray(peak_params.directions(), dtype=float)
        self._bins_per_m = float(peak_params.m)
        self.frames: deque[FrameSurfaces] = deque(maxlen=MAX_OBSERVATIONS)

    # -- per frame -------------------------------------------------------------------------------
    def add(self, frame: Any, base_T_sensor: Any, stamp: float) -> FrameSurfaces | None:
        """Record one frame measured at ``base_T_sensor``; None when it has no usable histograms."""
        try:
            h = np.asarray(frame.hists, dtype=float)
            T = np.asarray(base_T_sensor, dtype=float)
        except (TypeError, ValueError, AttributeError):
            return None
        if h.shape != (N_ZONES, N_BINS) or T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return None
        if float(np.abs(T[:3, 3]).max()) > MAX_REACH:  # not a pose of the arm's sensor
            return None
        if (stamp := finite_number(stamp)) is None:
            return None
        # the shape tests look from each return's maximum, not the calibrated reading: a centroid moves towards
        # a nearer surface mixed into the return, the very shoulder the early test looks for
        pos, top, valid, _ = self.params.returns(h)
        valid = valid & np.isfinite(pos)
        with np.errstate(invalid="ignore"):
            pts = self.params.points(np.where(valid, pos, 0.0))
        valid &= np.all(np.isfinite(pts), axis=1) & (pts[:, 2] > 0)
        second, where = second_returns(h, top, valid)
        early = early_returns(h, top, valid)
        late = late_returns(h, top, valid)
        depth = (where - top) / self._bins_per_m
        tol = self.consensus_tolerance(pts, valid)
        if self.relative > 0:
            inliers, plane, rms, ambiguity = consensus_and_ambiguity(pts, valid, tol, early)
        else:
            (inliers, plane, rms), ambiguity = consensus(pts, valid, tol, deep=False, early=early), 0.0
        pb = pts @ T[:3, :3].T + T[:3, 3]
        pb[~valid] = np.nan
        fs = FrameSurfaces(float(stamp), T.copy(), pb, valid, second, np.where(second, depth, np.nan), early,
                           inliers, plane, rms, tol, ambiguity, late)
        self.frames.append(fs)
        return fs

    def consensus_tolerance(self, points: np.ndarray, valid: np.ndarray) -> float:
        """m: how far a zone's point may lie off its frame's plane and still count as the same surface:
        ``relative`` (default :data:`CONSENSUS_RELATIVE`) of the median zone range, between
        :data:`CONSENSUS_MIN` and ``tolerance``. Close up the zones are a centimetre or two apart, and a
        step of ``tolerance`` between them would pass for a steep plane; far away the zones are wide and
        mixed."""
        r = np.linalg.norm(np.asarray(points, dtype=float)[np.asarray(valid, dtype=bool)], axis=1)
        if not self.relative > 0 or r.size == 0 or not np.all(np.isfinite(r)):
            return self.tolerance
        return float(np.clip(self.relative * np.median(r), min(CONSENSUS_MIN, self.tolerance), self.tolerance))

    def on_plane(self, fs: FrameSurfaces, normal: Any, offset: float, mixed: bool = False) -> np.ndarray:
        """Zones (9,) of a recorded frame whose single return lies on the base-frame plane
        ``normal . x = offset`` within the frame's consensus tolerance (:meth:`consensus_tolerance`):
        valid, no nearer surface mixed in (with ``mixed``, also zones with a nearer surface mixed into the
        return whose peak still lies on the plane). With the fused surface as the plane these are the zones that
        still see the known surface when clutter or a step comes into view beside it. A zone that also sees a
        farther surface behind (the floor past a table edge) counts: its first return is the known surface,
        though from part of its field only (:attr:`FrameSurfaces.split`)."""
        n = np.asarray(normal, dtype=float)
        T = fs.base_T_sensor
        ok = fs.valid & (True if mixed else ~fs.early) & np.all(np.isfinite(fs.points_base), axis=1)
        if not ok.any() or n.shape != (3,) or not np.all(np.isfinite(n)) or not math.isfinite(float(offset)):
            return np.zeros(N_ZONES, dtype=bool)
        pb = np.where(ok[:, None], fs.points_base, 0.0)
        tol = self.consensus_tolerance((pb - T[:3, 3]) @ T[:3, :3], ok)
        return ok & (np.abs(pb @ n - float(offset)) <= tol)

    # -- footprint ---------------------------------------------------------------------------------
    def disc(self, normal: np.ndarray, offset: float, base_T_cup: np.ndarray) -> np.ndarray | None:
        """Sample points (K, 3) of the landing footprint on the plane ``normal . x = offset`` (base frame):
        its centre first, then a grid of :data:`DISC_SPACING` inside it and a ring on its rim."""
        n = np.asarray(normal, dtype=float)
        C = np.asarray(base_T_cup, dtype=float)
        p, axis = C[:3, 3], -C[:3, 2]
        den = float(n @ axis)
        if not (abs(den) > 1e-6):
            return None
        centre = p + axis * (offset - float(n @ p)) / den
        u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        k = np.arange(-self.radius, self.radius + 1e-9, DISC_SPACING)
        a, b = np.meshgrid(k, k)
        keep = (a ** 2 + b ** 2 <= self.radius ** 2) & ((a != 0) | (b != 0))
        ang = np.linspace(0.0, 2 * math.pi, _RIM_POINTS, endpoint=False)
        ca = np.concatenate([[0.0], a[keep], self.radius * np.cos(ang)])
        cb = np.concatenate([[0.0], b[keep], self.radius * np.sin(ang)])
        return centre + ca[:, None] * u + cb[:, None] * v

    def _view(self, disc: np.ndarray, base_T_sensor: np.ndarray, tan_fov: float | None = None
              ) -> tuple[np.ndarray, np.ndarray]:
        """Sensor-frame directions of the disc points: (in view mask (K,), zone index (K,))."""
        T = np.asarray(base_T_sensor, dtype=float)
        t = self.tan_fov if tan_fov is None else tan_fov
        q = (disc - T[:3, 3]) @ T[:3, :3]
        z = q[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            inside = (z > 0) & (np.abs(q[:, 0] / z) <= t) & (np.abs(q[:, 1] / z) <= t)
            u = q / np.linalg.norm(q, axis=1, keepdims=True)
        zone = np.argmax(np.nan_to_num(u) @ self._dirs.T, axis=1)
        return inside, zone

    def _zone_issue(self, fs: FrameSurfaces, z: int, n: np.ndarray, d: float) -> tuple[str, str] | None:
        """(kind, detail) of what zone ``z`` of the frame shows besides one surface on the plane, or None."""
        if not fs.valid[z]:
            return "edge", f"no return from zone {z + 1} over the cup's footprint (edge, no support)"
        if fs.second[z]:
            return "edge", (f"zone {z + 1} over the cup's footprint sees a second surface "
                            f"{fs.second_depth[z] * 1e3:.0f} mm farther (edge or step)")
        s = float(fs.points_base[z] @ n - d)
        if fs.early[z]:
            return "clutter", (f"zone {z + 1} over the cup's footprint sees a nearer surface mixed into the "
                               "table's return (clutter or step)")
        if s > self.tolerance:
            return "clutter", (f"something {s * 1e3:.0f} mm above the surface in zone {z + 1} over the cup's "
                               "footprint (clutter or step)")
        if s < -self.tolerance:
            return "edge", (f"the surface in zone {z + 1} over the cup's footprint is {-s * 1e3:.0f} mm "
                            "below the fused surface (edge or step, no support)")
        if fs.late[z] and abs(s) <= fs.tolerance:  # on the plane by its reading, but part of it lies lower
            return "edge", (f"zone {z + 1} over the cup's footprint sees a farther surface mixed into the "
                            "surface's return (edge or step down under part of it)")
        return None

    def survey_height(self) -> float:
        """m above the surface from which the sensor, centred over the footprint, just holds it in view
        (its zones are then no larger than they must be)."""
        return (self.radius + VIEW_SLACK) / self._tan_aim + CLIMB_MARGIN

    def close_height(self) -> float:
        """m above the surface up to which a frame's zones are small enough to certify the footprint or to
        blame it: :meth:`survey_height` + :data:`CLOSE_SLACK`."""
        return self.survey_height() + CLOSE_SLACK

    @property
    def _tan_aim(self) -> float:
        return math.tan(math.atan(self.tan_fov) - 2 * SIGHT_SLACK_RAD)

    def footprint(self, normal: Any, offset: float, landing_T_cup: Any) -> FootprintVerdict:
        """Judge the landing footprint against the fused plane ``normal . x = offset`` for the cup's landing
        pose (its axis fixes the footprint's centre).

        Only frames taken from no higher than :meth:`close_height` count: there a zone is at most about
        5 cm wide, so clutter a few centimetres across shows in it. From higher up a box covering part of
        a 9 cm zone moves the zone's point by a millimetre or two and the zone reads as clean table.

        Each close frame *views* the sample points of the footprint in its field of view; a view is

        * *clean*: the point lies in a zone that saw one surface on the fused plane within the frame's
          consensus tolerance (:meth:`consensus_tolerance`, 2 % of the range: 4.6 mm from the survey
          height);
        * *doubtful*: the zone is off the plane by more than that but less than ``tolerance``: a box
          covering part of the zone lifts its return by a fraction of its height;
        * *flagged*: the zone shows an issue (no return, a second return, a nearer surface mixed in, a
          surface more than ``tolerance`` off the plane, or a farther surface mixed into a return that lies on
          the plane: the table a board's thickness below part of the zone, :func:`late_returns`).

        A point is *certified* by its clean views; ``supported`` is the smallest number of clean views of
        a point (0 while any point has none). A ``problem`` is reported

        * when a point with fewer than ``min_frames`` clean views was flagged in ``min_frames`` views, or
        * **latest close views decide**: when the last ``min_frames`` views of a point from frames
          *looking at the footprint* -- the optical axis meets the plane inside the footprint (or within
          :data:`AIM_SLACK` of its rim), as from the survey pose or the second look -- all see something
          *raised* (a doubtful zone above the plane, a nearer surface mixed in, a surface above), whatever
          earlier views certified. Edge
          evidence (no return, a farther surface, a lower one but for the *lowered* doubt below) keeps to the first
          rule: a zone reaching past
          the footprint sees the floor beyond a table edge 2 cm away, while a point over the floor is
          never certified by a zone on the plane. Frames that only hold part of the footprint at the edge of their view (the descent,
          the sensor 7 cm beside the cup) add clean views but cannot veto: their zones over the footprint
          reach centimetres past it, where a box beside the cup may stand. A vetoed point stays vetoed
          until ``min_frames`` views with it in the centre zone (:data:`CENTRE_ZONE`, the second look's
          view centred on it, whose zone reaches least far past it) see it clean; views sliding off a box
          as the sensor moves away do not lift a veto. A point whose latest such view saw it raised (fewer
          than ``min_frames`` of them: no veto yet), or *lowered* (a doubtful zone below the plane, or one
          :data:`LOWERED_STEP` or more below it within the frame's tolerance, whose centre ray meets it within the
          cup's own radius: part of the footprint a step lower than the surface the cup is lowered to, as when the
          plane is the top of a box that reaches under part of the footprint, whose edge the cup would pivot on, or a
          thin board's edge under the rim; such a view is not clean; a zone centred past the rim that reads lower sees
          a step beside the footprint; lowered views never veto), is *in doubt* and counts 0 in ``supported`` until
          a clean
          view from no lower than the highest one that raised it since (less :data:`CLIMB_MARGIN`), or centred on
          it, sees it clean: the descent's lower views reach past the far rim. This rule needs zone points good to a few millimetres:
          it applies only to a calibrated peak mapping (``relative > 0``); with built-in constants, whose zone
          points lie a centimetre off, the first rule alone decides.
        """
        n = np.asarray(normal, dtype=float)
        d = float(offset)
        disc = self.disc(n, d, np.asarray(landing_T_cup, dtype=float))
        if disc is None:
            return FootprintVerdict(problem="the cup's axis is parallel to the surface: no landing footprint")
        close = self.close_height()
        k = max(self.min_frames, 1)
        certified = np.zeros(len(disc), dtype=int)
        flagged = np.zeros(len(disc), dtype=int)
        latest = np.zeros((len(disc), k), dtype=int)  # last k views from frames looking at it: 0 none, 1 clean, 2 not
        vetoed = np.zeros(len(disc), dtype=bool)  # latest views said no; only views centred on the point lift it
        doubt_at = np.full(len(disc), np.nan)  # height of the frame whose view of the point last saw it raised
        cleared = np.zeros(len(disc), dtype=int)  # clean views centred on a vetoed point since its veto
        details: dict[str, str] = {}
        kinds: Counter = Counter()
        doubt_detail = None  # what the latest view that saw a point raised saw (a veto's reason)
        said: list[str] = []  # what views saw of points in doubt; point_said indexes it (-1: nothing)
        point_said = np.full(len(disc), -1)
        observed = close_frames = 0
        for fs in self.frames:
            inside, zone = self._view(disc, fs.base_T_sensor)
            if not inside.any():
                continue
            observed += int(inside.all())
            height = float(fs.base_T_sensor[:3, 3] @ n - d)
            if height > close:
                continue
            close_frames += 1
            issue = {z: self._zone_issue(fs, z, n, d) for z in set(zone[inside].tolist())}
            doubt = self._doubtful(fs, n, d)
            bad_zone = np.array([issue.get(int(z)) is not None for z in range(N_ZONES)])
            # raised evidence is a few millimetres: only zone points of a calibrated peak mapping (relative > 0,
            # see consensus_tolerance) are good enough for it; built-in constants put zones a centimetre off
            looking = self.relative > 0 and self._looks_at(fs.base_T_sensor, disc, n)
            off = fs.points_base @ n - d  # m above the fused plane per zone (NaN without a return)
            with np.errstate(invalid="ignore"):
                lifted = off > 0
                low = fs.valid & (off < -LOWERED_STEP)
            # lowered: one surface below the plane by more than the frame's tolerance, within ``tolerance``, or
            # LOWERED_STEP below it where the frame's other zones lie on the plane, in a zone centred under the cup:
            # part of the footprint lies a step lower than the surface the cup is lowered to (the cup lowered onto a
            # box beside it pivots on the box's edge, a thin board's edge under the rim); it puts the point in doubt
            # but does not veto, and such a view is not clean. A zone centred past the rim that reads lower sees a
            # step beside the footprint
            lowered_zone = np.zeros(N_ZONES, dtype=bool)
            if looking:
                if not self._on_the_plane(off, fs.valid & ~low):  # the frame does not read the fused plane that well
                    low[:] = False
                lowered_zone = (doubt | low) & ~lifted & ~bad_zone & self._centred_under_cup(fs.base_T_sensor,
                                                                                             disc[0], n)
            clean_zone = np.array([issue.get(int(z)) is None and not doubt[int(z)] and not lowered_zone[int(z)]
                                   for z in range(N_ZONES)])
            clean = inside & clean_zone[zone]
            bad = inside & bad_zone[zone]
            certified += clean
            if bad.any():
                flagged += bad
                for z in set(zone[bad].tolist()):
                    kind, detail = issue[z]
                    kinds[kind] += 1
                    details[kind] = detail
            if looking:
                # raised: something above the surface in the zone (a box's top lifts or leads its return); an edge's
                # floor or a step down beside the footprint shows as a missing, farther or lower return instead
                raised_zone = np.array([(doubt[z] and bool(lifted[z])) or (issue.get(z) is not None
                                                                           and issue[z][0] == "clutter")
                                        for z in range(N_ZONES)])
                seen = clean | (inside & raised_zone[zone])  # edge evidence neither vetoes nor lifts
                lowered = inside & ~clean & lowered_zone[zone]
                latest[seen] = np.column_stack([latest[seen][:, 1:], np.where(clean[seen], 1, 2)])
                vetoed |= np.all(latest == 2, axis=1)
                centred = seen & (zone == CENTRE_ZONE)
                # in doubt: raised in the latest such view; lifted by a clean view from no lower (zones as wide as the
                # one that saw it, or wider) or centred on it, not by views from further down the descent, whose
                # zones over the far rim lie at the edge of the view and reach past it
                # the highest raising view since the doubt was last lifted sets the bar: seeing it raised again from
                # lower down is more evidence, not a lower bar (fmax: NaN, no doubt yet, gives this height)
                raised = (seen & ~clean) | lowered
                doubt_at[raised] = np.fmax(doubt_at[raised], height)
                with np.errstate(invalid="ignore"):
                    lifts = clean & ((height >= doubt_at - CLIMB_MARGIN) | centred)
                doubt_at[lifts] = np.nan
                cleared = np.where(centred & vetoed, np.where(clean, cleared + 1, 0), cleared)
                lift = vetoed & (cleared >= k)
                vetoed &= ~lift
                cleared[lift] = 0
                latest[lift] = 0
                for z in sorted(set(zone[raised].tolist())):  # what the view saw of the points it put in doubt
                    said.append(issue[z][1] if issue.get(z) is not None else _off_surface(fs, z, n, d))
                    point_said[raised & (zone == z)] = len(said) - 1
                doubted = inside & ~clean & ~bad & raised_zone[zone]
                if doubted.any():
                    doubt_detail = _off_surface(fs, int(zone[doubted][0]), n, d)
        # a point in doubt is not supported by its clean views from before: a placement that moves on as soon as
        # every point has min_frames clean views (the faster descent) would leave before the views that veto it
        # (box_at_rim_mismatch: a box at the rim seen clean 3 times as it came into view at the survey pose,
        # raised twice, then clean from 5 cm lower, where its zone reaches past it)
        supported = int(np.where(np.isfinite(doubt_at), 0, certified).min()) if len(certified) else 0
        problem = None
        recheck = None
        open_points = (certified < self.min_frames) & (flagged >= self.min_frames)
        if open_points.any() and kinds:
            kind = kinds.most_common(1)[0][0]
            share = 100.0 * float(np.mean(certified == 0))
            problem = (f"{details[kind]}; {share:.0f} % of the footprint never seen on the surface in "
                       f"{int(flagged.max())} close frames")
            recheck = disc[open_points].mean(axis=0)
        elif vetoed.any():
            kind = kinds.most_common(1)[0][0] if kinds else None
            why = details[kind] if kind is not None and doubt_detail is None else doubt_detail
            problem = (f"{why or 'zones over the cup footprint off the surface'}; the latest {k} close views of "
                       f"{100.0 * float(np.mean(vetoed)):.0f} % of the footprint do not see it on the surface")
            recheck = disc[vetoed].mean(axis=0)
        elif np.isfinite(doubt_at).any():  # no problem, but points in doubt: where a second look would lift it
            recheck = disc[np.isfinite(doubt_at)].mean(axis=0)
        still = np.flatnonzero(np.isfinite(doubt_at) & (point_said >= 0))
        doubt = said[int(point_said[still].max())] if still.size else None  # the latest view of points still in doubt
        return FootprintVerdict(observed, supported, problem, close_frames=close_frames, recheck_point=recheck,
                                doubt=doubt)

    def _doubtful(self, fs: FrameSurfaces, n: np.ndarray, d: float) -> np.ndarray:
        """Zones (9,) of a frame that returned one surface off the plane ``n . x = d`` by more than the frame's
        consensus tolerance (they may still lie within ``tolerance``): see :meth:`footprint`."""
        ok = fs.valid & np.all(np.isfinite(fs.points_base), axis=1)
        if not ok.any():
            return np.zeros(N_ZONES, dtype=bool)
        pb = np.where(ok[:, None], fs.points_base, 0.0)
        return ok & (np.abs(pb @ n - d) > fs.tolerance)

    @staticmethod
    def _on_the_plane(offsets: np.ndarray, rest: np.ndarray) -> bool:
        """Whether a frame's zones ``rest`` (9,), those not read :data:`LOWERED_STEP` below the fused plane, lie on it:
        three or more, their offsets (m) within ``LOWERED_STEP / 2`` RMS. Only then is a zone that step below the plane
        a step down: where the fused plane is itself off the frame's surface, its zones' offsets run across the grid
        (board 15 of ``--kind boards --seed 4``: a 12.7 mm board, its edge 34 mm past the rim, the fused plane 2 deg
        off; the zones read -10 to +3 mm, the centre zone -3.7 mm over the level board)."""
        o = np.asarray(offsets, dtype=float)[np.asarray(rest, dtype=bool)]
        return o.size >= 3 and bool(np.sqrt(np.mean(o ** 2)) <= 0.5 * LOWERED_STEP)

    def _centred_under_cup(self, base_T_sensor: np.ndarray, centre: np.ndarray, n: np.ndarray) -> np.ndarray:
        """Zones (9,) whose centre ray meets the plane through the footprint's ``centre`` (normal ``n``) within the
        cup's own radius. A lower surface such a zone reads lies mostly under the cup (a zone centred at the rim still
        has about 40 % of its field past it); a zone centred past the rim that reads lower sees a step beside the
        footprint (a board the cup stands on 12-22 mm inside its edge: a review's scan). From the survey pose, centred
        over the footprint, only the centre zone qualifies: the others' centres meet the table about 44 mm out."""
        T = np.asarray(base_T_sensor, dtype=float)
        rays = self._dirs @ T[:3, :3].T
        den = rays @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = ((centre - T[:3, 3]) @ n) / den
            off = T[:3, 3] + t[:, None] * rays - centre
            off -= np.outer(off @ n, n)
            return (t > 0) & (np.linalg.norm(off, axis=1) <= self.cup_radius)

    def _looks_at(self, base_T_sensor: np.ndarray, disc: np.ndarray, n: np.ndarray) -> bool:
        """Whether the sensor's optical axis meets the plane inside the footprint (``disc[0]`` its centre), or
        within :data:`AIM_SLACK` of its rim."""
        aim = _axis_offset(np.asarray(base_T_sensor, dtype=float), disc[0], n)
        return aim is not None and float(np.linalg.norm(aim[0])) <= self.radius + AIM_SLACK

    def sight(self, verdict: FootprintVerdict, normal: Any, offset: float, landing_T_cup: Any,
              base_T_sensor: Any) -> FootprintVerdict:
        """``verdict`` with ``in_view``, ``look_shift`` and ``view_margin`` for the sensor pose now."""
        n = np.asarray(normal, dtype=float)
        disc = self.disc(n, float(offset), np.asarray(landing_T_cup, dtype=float))
        T = np.asarray(base_T_sensor, dtype=float)
        if disc is None or T.shape != (4, 4) or not np.all(np.isfinite(T)):
            return replace(verdict, in_view=False, look_shift=np.zeros(3), view_margin=-math.inf)
        # in view *now* only with room to spare, so frames taken here still hold the disc when the fused
        # plane moves a little
        inside, _ = self._view(disc, T, math.tan(math.atan(self.tan_fov) - SIGHT_SLACK_RAD))
        shift, margin = self._look(disc, T, n)
        above = float(T[:3, 3] @ n - float(offset)) - self.close_height()
        recheck = None
        if verdict.recheck_point is not None:
            recheck, _ = self._look(np.asarray(verdict.recheck_point, dtype=float).reshape(1, 3), T, n)
        return replace(verdict, in_view=bool(inside.all()), look_shift=shift, view_margin=margin,
                       certify_margin=above, recheck_shift=recheck)

    def verdict(self, normal: Any, offset: float, landing_T_cup: Any, base_T_sensor: Any) -> FootprintVerdict:
        """:meth:`footprint` and :meth:`sight` together."""
        return self.sight(self.footprint(normal, offset, landing_T_cup), normal, offset, landing_T_cup,
                          base_T_sensor)

    def _look(self, disc: np.ndarray, base_T_sensor: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, float]:
        """The TCP move (base frame) to the survey pose -- the optical axis through the footprint's centre,
        the sensor :meth:`survey_height` above the surface -- and the height (m) the sensor may still lose
        before the footprint leaves the view from where it is now (negative: out of view already)."""
        aim = _axis_offset(base_T_sensor, disc[0], n)
        if aim is None:
            return np.zeros(3), -math.inf
        off, height = aim
        dist = float(np.linalg.norm(off))
        margin = height - (dist + self.radius) / self.tan_fov
        return off + n * (self.survey_height() - height), margin


def _off_surface(fs: FrameSurfaces, z: int, n: np.ndarray, d: float) -> str:
    """What zone ``z`` of a recorded frame saw of the plane ``n . x = d``: a doubtful zone above it (part of it
    covered) or below it (part of the footprint a step lower)."""
    s = float(fs.points_base[z] @ n - d)
    return (f"zone {z + 1} over the cup's footprint {s * 1e3:+.0f} mm off the surface "
            + ("(part of it covered: clutter or step)" if s > 0 else
               "(part of the footprint lower: a step the cup would pivot on)"))


def _axis_offset(base_T_sensor: np.ndarray, centre: np.ndarray, n: np.ndarray) -> tuple[np.ndarray, float] | None:
    """Where the sensor's optical axis meets the plane through ``centre`` with unit normal ``n`` (base frame):
    (the in-plane move from that point to ``centre`` (3,), the sensor's height above the plane in m), or None
    when the sensor is not above the plane or its axis does not point down onto it."""
    S, axis = base_T_sensor[:3, 3], base_T_sensor[:3, 2]
    height = float((S - centre) @ n)
    den = float(-(axis @ n))
    if height <= 0 or den <= 1e-6:
        return None
    hit = S + axis * height / den
    off = centre - hit
    off -= n * float(off @ n)
    return off, height


__all__ = ["SurfaceMap", "FrameSurfaces", "FootprintVerdict", "consensus", "consensus_and_ambiguity",
           "slope_ambiguity", "second_returns", "early_returns",
           "FOV_HALF_ANGLE"]
