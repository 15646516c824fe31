"""The placement machine's rules: why the cup may not be released (or must be refused), as plain functions.

Concept: each ``*_problem`` function takes what :class:`place_safe.placement.machine.PlacementMachine` knows
on a tick (the fused plane, the robot state, the surface map's footprint verdict, the clock) and its
placement config ``cfg`` (:class:`~place_safe.placement.machine.PlacementConfig`, or any object with the same
fields), and returns a one-line reason, or None when the rule sees no problem. Every comparison fails
closed: NaN, a missing attribute or a malformed value is a problem, never a pass. The machine decides what
a problem leads to (refuse, abort, wait); the release rule itself is listed in the machine's docstring.

Conventions: SI units (m, s, rad). The fused plane is a :class:`place_safe.fusion.plane_filter.FusedPlane`
in the robot base frame; ``now`` and every stamp are on the robot clock.
"""

from __future__ import annotations

import math
from statistics import NormalDist
from typing import Any, Callable

import numpy as np
from scipy.stats import chi2 as _chi2

from place_safe.fusion.plane_filter import FusedPlane
from place_safe.geometry import finite_number as number  # (rules.number: the placement's name for it)
from place_safe.geometry import rotation_angle_between
from place_safe.recovery.too_close import TOO_CLOSE_REASON


def fault_text(fault: Any) -> str | None:
    """The first non-blank line of what a robot's ``fault()`` said (None: no fault). A false value (None, "", False,
    0) is no fault; any other is one, and one that cannot be read (its ``bool`` or ``str`` raises: an array, a broken
    object) is said to be unreadable, never dropped. At most 200 characters."""
    try:
        if not fault:
            return None
        text = str(fault)
    except Exception:
        return f"an unreadable fault report ({type(fault).__name__})"
    text = next((line for line in text.splitlines() if line.strip()), "")  # its first line that says something
    if not text:
        return f"an empty fault report ({type(fault).__name__})"
    return text[:200] + (" ..." if len(text) > 200 else "")


def degrees_text(rad: float) -> str:
    """An uncertainty (rad) in degrees for a reason: two decimals, or three figures where that would fill the line
    (an estimate stating 1e154 rad)."""
    v = math.degrees(rad)
    return f"{v:.2f}" if abs(v) < 1e4 else f"{v:.3g}"


#: The most decimals :func:`compared_text` gives a number before it prints it in full (``repr``).
MAX_DECIMALS = 9


def number_text(value: float, decimals: int = 1) -> str:
    """``value`` with ``decimals`` decimals for a reason, never a negative zero: a clearance of -0.04 mm prints "0.0",
    not "-0.0" (a transition line of a new user's walkthrough)."""
    text = f"{value:.{decimals}f}"
    return text[1:] if text.startswith("-") and not any(c in "123456789" for c in text) else text


def exact_text(value: float, decimals: int = 1) -> str:
    """A threshold for a reason: with ``decimals`` decimals, more where those do not give it exactly (to a billionth of
    it, up to :data:`MAX_DECIMALS`; past them in full), never a negative zero."""
    return next((t for k in range(decimals, MAX_DECIMALS + 1)
                 if abs(float(t := number_text(value, k)) - value) <= 1e-9 * max(1.0, abs(value))), repr(value))


def compared_text(value: float, limit: float, decimals: int = 1, limit_decimals: int | None = None,
                  exact: bool = True) -> tuple[str, str]:
    """``value`` and ``limit`` as a reason prints them on the two sides of a comparison (``<``, ``>``), in the unit
    they are given in: ``limit`` with ``limit_decimals`` decimals (default ``decimals``), more where those do not give
    it exactly (a setting), and ``value`` with ``decimals``, more where fewer would print it equal to the limit or on
    its other side (9.96 mm against 10 mm printed "clearance 10.0 mm < 10 mm": now "9.96 mm < 10 mm"); neither is a
    negative zero (:func:`number_text`). ``exact=False`` (a computed limit, a chi-square quantile): the limit is rounded
    too, both gaining decimals together until they compare as printed. Past :data:`MAX_DECIMALS` in full."""
    side = (value > limit) - (value < limit)
    first = decimals if limit_decimals is None else limit_decimals
    for k in range(MAX_DECIMALS + 1):
        limit_text = exact_text(limit, first) if exact else number_text(limit, min(first + k, MAX_DECIMALS))
        shown = float(limit_text)
        if exact:
            return next(((t, limit_text) for j in range(decimals, MAX_DECIMALS + 1)
                         if (float(t := number_text(value, j)) > shown) - (float(t) < shown) == side),
                        (repr(value + 0.0), repr(limit + 0.0)))  # (+ 0.0: no negative zero)
        text = number_text(value, min(decimals + k, MAX_DECIMALS))
        if (float(text) > shown) - (float(text) < shown) == side:
            return text, limit_text
    return repr(value + 0.0), repr(limit + 0.0)


def _chi_square_text(chi2: float, limit: float) -> tuple[str, str]:
    """A chi-square beyond its limit (a quantile), as "chi-square X > Y" prints them: three figures and one decimal, or
    as many as it takes for X to print above Y (:func:`compared_text`)."""
    text, bound = f"{chi2:.3g}", f"{limit:.1f}"
    return (text, bound) if float(text) > float(bound) else compared_text(chi2, limit, 1, 1, exact=False)


def too_close(note: str | None) -> bool:
    """Whether the last frame's note says it was too close to read (:mod:`place_safe.recovery.too_close`)."""
    return isinstance(note, str) and TOO_CLOSE_REASON in note


def plane_problem(plane: FusedPlane | None, now: float, note: str | None, cfg: Any, period: float,
                  blind: Callable[[], bool], check_age: bool = True) -> str | None:
    """Why the fused plane cannot be used at robot time ``now``: missing, malformed, not finite, inconsistent,
    stamped in the future (more than one control ``period``) or older than ``plane_timeout``. A plane up to
    ``too_close_hold`` old still counts while ``blind()`` says the sensor is too close to read (called only
    once the plane is otherwise valid; see :meth:`PlacementMachine._blind`). ``note`` says why the last frame
    gave no plane and is quoted in the reason. ``check_age=False`` leaves out the age test (whether the plane is
    usable once a fresh one comes)."""
    if plane is None:
        return "no surface plane" + (f" ({note})" if note else "")
    try:
        n = np.asarray(plane.normal_base, dtype=float)
        vals = (float(plane.offset_base), float(plane.tilt_rad), float(plane.std_angle), float(plane.std_offset),
                float(plane.stamp))
    except (TypeError, ValueError, AttributeError):
        return "fused plane is malformed"
    if n.shape != (3,) or not np.all(np.isfinite(n)) or not all(math.isfinite(v) for v in vals):
        return "fused plane is not finite"
    if abs(float(np.linalg.norm(n)) - 1.0) > 1e-6:
        return "fused plane normal is not a unit vector"
    if not (0.0 <= plane.tilt_rad <= math.pi):
        return f"fused plane tilt {plane.tilt_rad!r} rad is out of range [0, pi]"
    if abs(math.acos(max(-1.0, min(1.0, float(n[2] / np.linalg.norm(n))))) - plane.tilt_rad) > 1e-6:
        return "fused plane is inconsistent: its tilt does not match its normal"
    if not (plane.std_angle >= 0.0 and plane.std_offset >= 0.0):
        return "fused plane spread is negative"
    age = now - plane.stamp
    if age < -period:
        return f"surface plane is stamped {-age:.3f} s in the future"
    if not check_age or (blind() and age <= cfg.too_close_hold):
        return None  # the sensor is too close to read: the farther frames' plane and the kinematics decide
    if not (age <= cfg.plane_timeout):
        return (f"surface plane is stale ({'{} s old > {} s'.format(*compared_text(age, cfg.plane_timeout, 2))})"
                + (f"; last frame: {note}" if note else ""))
    return None


def sensor_problem(last_frame_time: float | None, now: float, t_start: float, note: str | None,
                   cfg: Any) -> str | None:
    """Sensor timeout: no frame for more than ``sensor_timeout`` s before ``now`` (counted from ``t_start``,
    the machine's first tick, until a frame has arrived)."""
    ref = t_start if last_frame_time is None else float(last_frame_time)
    if not (now - ref <= cfg.sensor_timeout):
        return (f"sensor timeout: no frame for {'{} s (> {} s)'.format(*compared_text(now - ref, cfg.sensor_timeout, 2))}"
                + (f"; {note}" if note else ""))
    return None


def planar_problem(plane: FusedPlane, cfg: Any) -> str | None:
    """The fused estimates spread more than ``max_std_angle`` / ``max_std_offset`` (not one planar surface)."""
    if not (plane.std_angle <= cfg.max_std_angle and plane.std_offset <= cfg.max_std_offset):
        angle = compared_text(math.degrees(plane.std_angle), math.degrees(cfg.max_std_angle), 2, 1)
        offset = compared_text(plane.std_offset * 1e3, cfg.max_std_offset * 1e3)
        return (f"surface not planar or estimates inconsistent: spread {angle[0]} deg / {offset[0]} mm (limits "
                f"{angle[1]} deg / {offset[1]} mm)")
    return None


def tilt_problem(plane: FusedPlane, limit: float, cfg: Any) -> str | None:
    """The fused tilt exceeds ``limit`` rad (the reason quotes ``max_tilt``, the tilt a cup may stand on)."""
    if not (plane.tilt_rad <= limit):
        tilt, allowed = compared_text(math.degrees(plane.tilt_rad), math.degrees(cfg.max_tilt))
        return f"surface tilted {tilt} deg (> {allowed} deg allowed)"
    return None


def steep_problem(plane: FusedPlane, cfg: Any) -> str | None:
    """The early refusal: the fused tilt exceeds ``early_refuse_tilt`` whichever way the window's frames read, i.e.
    by more than the window's slope ambiguity (``plane.ambiguity``, rad: the frames' zones read as well as a plane
    that far away; :func:`~place_safe.fusion.surface_map.slope_ambiguity`). A board seen past its far edge from 27 cm
    read 10.1 deg through the table's row, or 3.6 deg as a board, and was refused before a lower frame could tell
    (random board 51 of seed 4). Without an ambiguity, :func:`tilt_problem` at ``early_refuse_tilt``."""
    amb = number(getattr(plane, "ambiguity", 0.0))
    amb = amb if amb is not None and amb > 0 else 0.0
    why = tilt_problem(plane, cfg.early_refuse_tilt + amb, cfg)
    if why is not None and amb:
        why += f" whichever way its frames read (ambiguous by {math.degrees(amb):.1f} deg)"
    return why


def tilt_sigma(plane: FusedPlane) -> float:
    """Standard error (rad) of the fused plane's tilt: ``plane.tilt_std`` from the estimates' covariances (the
    calibration's reference error in it), or, without them, the window's spread over sqrt(n) with the reference
    error (``plane.reference_tilt_std``) added."""
    s = getattr(plane, "tilt_std", math.nan)
    if isinstance(s, (int, float)) and math.isfinite(s) and s >= 0:
        return float(s)
    spread = float(plane.std_angle) / math.sqrt(max(int(getattr(plane, "n", 1) or 1), 1))
    ref = getattr(plane, "reference_tilt_std", 0.0)
    return math.hypot(spread, float(ref)) if isinstance(ref, (int, float)) and math.isfinite(ref) else spread


def confidence_margin(sigma: float, cfg: Any) -> float:
    """rad between the fused tilt and its one-sided ``level_confidence`` bound, for tilt std ``sigma``."""
    return NormalDist().inv_cdf(cfg.level_confidence) * sigma


def window_reading(plane: FusedPlane, cfg: Any) -> tuple[float, float] | None:
    """The window's own tilt and its standard error (rad) where the fused normal is the memory's
    (``plane.source == "memory"``), the plane carries them, the window could certify a level surface by itself (its
    ``level_confidence`` margin within ``max_tilt``) and it reads the surface steeper than the memory by more than half
    its own standard error, or at all where the memory's normal was fused beyond the narrow gate
    (``plane.memory_wide``: :class:`~place_safe.fusion.plane_filter.PlaneFilter`'s wide gate); None otherwise: the fused reading is the window's, or the window's planes are too uncertain
    to say anything of the level (a jaw-mounted sensor's last centimetres, whose planes state degrees: there the
    memory's slope is what there is), or they agree with the memory (a clutter scene's 1.07 +- 1.89 deg against a
    remembered 1.01 was refused when every window was held to the bound)."""
    if getattr(plane, "source", "window") != "memory":
        return None
    t, s = number(getattr(plane, "window_tilt_rad", None)), number(getattr(plane, "window_tilt_std", None))
    if t is None or s is None or s < 0 or not confidence_margin(s, cfg) <= cfg.max_tilt:
        return None
    # (a memory fused beyond the narrow gate disagrees with the window by more than its error could say: a steeper
    # window is held however little steeper; review of session 84's wide gate: 4.83 deg fused, the window's 5.30 deg,
    # 1.8 deg apart, released)
    steeper = t - plane.tilt_rad
    return (t, s) if steeper > 0.5 * s or (getattr(plane, "memory_wide", False) is True and steeper > 0) else None


def level_problem(plane: FusedPlane, cfg: Any) -> str | None:
    """Tilt not below ``max_tilt`` with ``level_confidence`` (one-sided normal bound on the tilt). Where the fused
    normal is the memory's, the window's own reading (:func:`window_reading`) must pass the same bound: the memory
    may mix slopes the recent planes no longer see as one, and which is right is not known."""
    if (why := tilt_problem(plane, cfg.max_tilt, cfg)) is not None:
        return why
    sigma = tilt_sigma(plane)
    bound = plane.tilt_rad + confidence_margin(sigma, cfg)
    if not (bound <= cfg.max_tilt):
        return (f"surface tilt {math.degrees(plane.tilt_rad):.2f} +- {degrees_text(sigma)} deg is not below "
                f"{math.degrees(cfg.max_tilt):.1f} deg with {cfg.level_confidence:.0%} confidence")
    if (recent := window_reading(plane, cfg)) is not None and not (recent[0] + confidence_margin(recent[1], cfg)
                                                              <= cfg.max_tilt):
        return (f"surface tilt {math.degrees(recent[0]):.2f} +- {degrees_text(recent[1])} deg in the latest "
                f"planes (the remembered slope reads {math.degrees(plane.tilt_rad):.2f}) is not below "
                f"{math.degrees(cfg.max_tilt):.1f} deg with {cfg.level_confidence:.0%} confidence")
    return None


def confidently_tilted(plane: FusedPlane, cfg: Any) -> str | None:
    """Refuse early (before descending onto it) a surface steeper than ``max_tilt`` with ``level_confidence``,
    once the window holds ``check_frames`` planes: the fused reading, or the window's own where the fused normal is
    the memory's (:func:`window_reading`)."""
    if int(getattr(plane, "n", 0) or 0) < cfg.check_frames:
        return None
    readings = [(plane.tilt_rad, tilt_sigma(plane))]
    if (recent := window_reading(plane, cfg)) is not None:
        readings.append(recent)
    for tilt, sigma in readings:
        if tilt - confidence_margin(sigma, cfg) > cfg.max_tilt:
            return (f"surface tilted {math.degrees(tilt):.1f} deg (> {math.degrees(cfg.max_tilt):.1f} deg "
                    f"allowed, with {cfg.level_confidence:.0%} confidence)")
    return None


def footprint_problem(footprint: Any, cfg: Any) -> str | None:
    """Why the landing footprint cannot take the cup, from the surface map's verdict ``footprint`` (None:
    no problem seen, or nothing known yet, or ``footprint_frames`` = 0)."""
    if cfg.footprint_frames == 0 or footprint is None:
        return None
    problem = getattr(footprint, "problem", None)
    return f"no safe support under the cup: {problem}" if problem else None


def footprint_seen(footprint: Any) -> int:
    """Frames that saw the landing footprint supported by the fused surface (0 when unknown or malformed)."""
    s = number(getattr(footprint, "supported", None))
    return int(s) if s is not None else 0


def most_check_frames(cfg: Any) -> int:
    """The most post-stop planes CHECK waits for: ``max_check_frames``, never fewer than ``check_frames``."""
    return max(cfg.check_frames, cfg.max_check_frames)


def pending_problem(plane: FusedPlane) -> str | None:
    """Planes the fusion's gates rejected are pending (``FusedPlane.pending``: not yet outweighed by accepted ones): at
    rest, a surface that rose or tipped beyond the gates (a box put under the cup, a tip of more than 5 deg) shows only
    there, and the window's planes all pass every stillness test (a review)."""
    pending = getattr(plane, "pending", ()) or ()
    if len(pending):
        return (f"{len(pending)} plane{'' if len(pending) == 1 else 's'} at rest rejected as outliers of the fused "
                "surface: the surface may have changed")
    return None


def check_frames_needed(plane: FusedPlane, cfg: Any) -> int:
    """Post-stop measurements CHECK waits for, sized from the fused uncertainty: ``check_frames`` when the
    fused plane (frames taken while slowing down included) lies well inside every limit -- its tilt below
    ``max_tilt`` by twice its one-sided ``level_confidence`` margin (the bound itself clears the limit by one
    margin: more frames of the same surface are not expected to move it across), its angle and offset spreads
    within half of ``max_std_angle`` / ``max_std_offset`` -- else ``max_check_frames`` (if larger). Never
    fewer than ``check_frames``. (It was half of ``max_tilt`` for the bound, which made every plane tilted
    more than 2.5 deg wait for 5 frames however well it was measured.)"""
    most = most_check_frames(cfg)
    try:
        bound = plane.tilt_rad + 2.0 * confidence_margin(tilt_sigma(plane), cfg)
        clear = (bound <= cfg.max_tilt and plane.std_angle <= 0.5 * cfg.max_std_angle
                 and plane.std_offset <= 0.5 * cfg.max_std_offset)
    except (TypeError, ValueError, AttributeError):
        clear = False
    return cfg.check_frames if clear else most


def post_stop_stamps(plane: FusedPlane, now: float, t_stop: float | None, cfg: Any) -> list[float]:
    """Distinct measurement times in the fused plane taken after the stop at ``t_stop`` (+ ``check_settle``)
    and not after ``now`` (empty when there was no stop, ``t_stop`` None)."""
    if t_stop is None:
        return []
    lo = t_stop + cfg.check_settle
    stamps = getattr(plane, "stamps", None) or ()
    out = set()
    for s in stamps:
        v = number(s)
        if v is not None and lo <= v <= now + 1e-9:
            out.add(v)
    return sorted(out)


_UP = np.array([0.0, 0.0, 1.0])

#: A judged plane's offset std above this (m) carries no information on whether the surface is still (its inverse
#: variance would vanish, or overflow to 0 beyond ~1e154 m): a reason, as a plane with no std is.
STILL_STD_LIMIT = 1.0


def _judged(stamps: tuple, post: list[float], cfg: Any) -> list[int] | str:
    """Indices into ``stamps`` of the planes the stillness tests judge: those measured at rest (``post``), or the
    newest ``check_frames`` (at least 2) when fewer than 2 were (the sensor too close to read); else a reason."""
    rest = set(post)
    idx = [i for i, t in enumerate(stamps) if t in rest]
    if len(idx) < 2:
        idx = list(range(len(stamps)))[-max(2, int(cfg.check_frames)):]
    if len(idx) < 2:
        return f"only {len(idx)} plane to tell whether the surface is still"
    return idx


def _judged_rows(plane: FusedPlane, post: list[float], cfg: Any, values: str, stds: str, what: str,
                 unknown: str, convert: Callable[[Any], Any]) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """(stamps, values, stds) of the planes the stillness tests judge (:func:`_judged`), read from the fused plane's
    per-plane tuples ``values`` and ``stds`` (each entry through ``convert``), or a reason naming ``what`` they are
    (the plane carries none: ``unknown`` says what is then not known; or they are malformed)."""
    stamps = tuple(getattr(plane, "stamps", ()) or ())
    v = tuple(getattr(plane, values, ()) or ())
    s = tuple(getattr(plane, stds, ()) or ())
    if not stamps or len(v) != len(stamps) or len(s) != len(stamps):
        return f"the fused plane carries no per-plane {what}: {unknown}"
    idx = _judged(stamps, post, cfg)
    if isinstance(idx, str):
        return idx
    try:
        return (np.array([float(stamps[i]) for i in idx]), np.array([convert(v[i]) for i in idx]),
                np.array([float(s[i]) for i in idx]))
    except (TypeError, ValueError, OverflowError):
        return f"the fused plane's per-plane {what} are malformed"


def _still_normals(plane: FusedPlane, post: list[float], cfg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """(stamps, unit normals (k, 3), direction stds (rad)) of the planes the stillness test judges (:func:`_judged`),
    or a reason: as for the offsets, a judged plane that states no finite direction error fails closed."""
    got = _judged_rows(plane, post, cfg, "normals", "normal_stds", "normals",
                       "whether the surface keeps its slope is unknown", lambda v: [float(x) for x in v])
    if isinstance(got, str):
        return got
    t, n, sd = got
    if n.shape != (len(t), 3) or not (np.all(np.isfinite(t)) and np.all(np.isfinite(n))):
        return "the fused plane's per-plane normals are malformed or not finite"
    norm = np.linalg.norm(n, axis=1)
    if not np.all(np.abs(norm - 1.0) <= 1e-6):
        return "a plane's normal is not a unit vector"
    if not (np.all(np.isfinite(sd)) and np.all(sd > 0.0)):
        return ("a plane at rest states no usable error in its normal (its estimate has no covariance): whether "
                "the surface keeps its slope is unknown")
    return t, n, sd


#: rad: a judged plane stating a direction error above this says nothing of the slope (a jaw-mounted sensor's last
#: planes, too close to read well, state 370-390 deg): it is left out of the slope tests.
SLOPE_STD_LIMIT = 0.5
#: rad: each judged plane's direction error is taken as at least this in the slope tests: planes of one still table
#: from the same pose differ by their estimators' biases as well as their noise (a frame the blend returns beside one
#: peak returns: 0.2-0.5 deg apart, each stating 0.1 deg, refused a still table on 2-50 % of checks; an adversarial
#: search), which no stated covariance of one frame holds. A table tipping under the cup by a degree or more is still
#: told from two planes.
SLOPE_STD_FLOOR = math.radians(0.25)


def _rest_normals(plane: FusedPlane, post: list[float], cfg: Any,
                  floor: bool = True) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str | None:
    """The informative judged planes (:func:`_informative`), less strays: the plane farthest from the others'
    weighted normal when it lies more than :data:`NEWEST_SIGMAS` of its own standard errors (floored at
    :data:`SLOPE_STD_FLOOR`) off them, and so on for up to a third of them (at least one) when there are three or
    more, the newest never. One plane that strays (a frame another estimator read, a glint) is not a table that tips,
    which moves every plane after it; two junk planes among five refused a still table when only one was left out
    (an adversarial search). The newest plane is the first to show a tip, and setting it aside passed a table that
    tipped to 6 deg on the fifth plane at rest (a review): a stray newest plane holds the check for one more plane
    instead (the machine waits before refusing). Their stds floored likewise with ``floor``, else as stated. A reason
    where the planes cannot be judged; None where fewer than two say anything of the slope (the level rule's own
    standard error then holds it)."""
    got = _informative(plane, post, cfg)
    if got is None or isinstance(got, str):
        return got
    t, n, sd = got
    floored = np.maximum(sd, SLOPE_STD_FLOOR)
    drops = max(1, (len(t) - 1) // 3)
    while drops and len(t) >= 3:
        w = 1.0 / floored**2
        off = []
        for i in range(len(t) - 1):  # never the newest: it is the one that shows a table tipping now
            others = np.arange(len(t)) != i
            off.append(rotation_angle_between(n[i], _weighted_normal(n[others], w[others])) / floored[i])
        j = int(np.argmax(off))
        if not off[j] > NEWEST_SIGMAS:  # (only a plane that strays: honest scatter stays in the tests)
            break
        keep = np.arange(len(t)) != j
        t, n, sd, floored = t[keep], n[keep], sd[keep], floored[keep]
        drops -= 1
    return t, n, (floored if floor else sd)


def _informative(plane: FusedPlane, post: list[float],
                 cfg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str | None:
    """(stamps, normals, stated stds) of the judged planes (:func:`_still_normals`) that state at most
    :data:`SLOPE_STD_LIMIT`; a reason where the planes cannot be judged; None with fewer than two of them."""
    got = _still_normals(plane, post, cfg)
    if isinstance(got, str):
        return got
    t, n, sd = got
    keep = sd <= SLOPE_STD_LIMIT
    return (t[keep], n[keep], sd[keep]) if np.count_nonzero(keep) >= 2 else None


def _weighted_normal(n: np.ndarray, w: np.ndarray) -> np.ndarray:
    """The unit normal of unit normals ``n`` (k, 3) weighted by ``w`` (k,)."""
    m = w @ n
    return m / np.linalg.norm(m)


def _steeper(tilt: float, sigma: float, plane: FusedPlane, cfg: Any) -> float | None:
    """The standard error (rad) of a tilt ``tilt`` read with error ``sigma``, the calibration's reference error
    (``plane.reference_tilt_std``) added, when the tilt is steeper than ``max_tilt`` with ``level_confidence``;
    None otherwise."""
    total = math.hypot(sigma, number(getattr(plane, "reference_tilt_std", 0.0)) or 0.0)
    return total if tilt - confidence_margin(total, cfg) > cfg.max_tilt else None


def slope_still_problem(plane: FusedPlane, post: list[float], cfg: Any) -> str | None:
    """The surface is not shown to keep its slope by the planes measured at rest (:func:`_rest_normals`): their
    normals disagree more than their errors allow (chi-square of their angles about their inverse-variance weighted
    normal above its ``still_confidence`` quantile, ``2 (k - 1)`` degrees of freedom), or they turn (weighted
    least-squares rate of the normal over time, both axes, beyond the ``still_confidence`` quantile of a chi-square of
    2 degrees of freedom). The window's fused normal weighs down a plane far off the others, and the memory's normal
    does not follow a table that tips while the cup stands still above it: a table tipping from 4.1 to 6.7 deg after
    the first plane at rest was released (an adversarial search). The machine waits for more planes at rest (until
    ``check_timeout``) before it refuses on this, so that stray planes can be set aside."""
    got = _rest_normals(plane, post, cfg)
    if got is None or isinstance(got, str):
        return got
    t, n, sd = got
    w = 1.0 / sd**2
    m = _weighted_normal(n, w)
    # tangent axes at the mean normal: the normals' small deviations as 2-vectors (rad)
    e1 = np.cross(m, [1.0, 0.0, 0.0] if abs(m[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(m, e1)
    dev = np.stack([n @ e1, n @ e2], axis=1)
    chi2 = float(np.sum(w[:, None] * dev**2))
    tc = t - float(w @ t / w.sum())
    stt = float(w @ tc**2)
    rate = (w * tc) @ dev / stt if stt > 0 else np.zeros(2)
    turn = float(rate @ rate * stt) if stt > 0 else 0.0
    limit = float(_chi2.ppf(cfg.still_confidence, 2 * (len(t) - 1)))
    if not (chi2 <= limit):
        worst = float(np.max(np.arccos(np.clip(n @ m, -1.0, 1.0))))
        return (f"surface not still: {len(t)} planes at rest differ in slope by up to {math.degrees(worst):.2f} deg "
                f"(chi-square {'{} > {}'.format(*_chi_square_text(chi2, limit))} for normals +- "
                f"{degrees_text(float(sd.min()))} deg)")
    turn_limit = float(_chi2.ppf(cfg.still_confidence, 2))
    if not (turn <= turn_limit):
        return (f"surface not still: {len(t)} planes at rest turn {math.degrees(float(np.linalg.norm(rate))):.2f} "
                f"deg/s (chi-square {'{} > {}'.format(*_chi_square_text(turn, turn_limit))})")
    return None


#: The newest plane at rest this many of its own (floored) standard errors off the others' weighted normal holds the
#: check for the next plane (:func:`newest_plane_problem`): a tip shows first on one plane.
NEWEST_SIGMAS = 3.0


def newest_plane_problem(plane: FusedPlane, post: list[float], cfg: Any) -> str | None:
    """The newest plane at rest reads the surface steeper than ``max_tilt`` with ``level_confidence`` on its own, or
    lies more than :data:`NEWEST_SIGMAS` standard errors (its own and the others' mean's, each plane's floored at
    :data:`SLOPE_STD_FLOOR`) off the weighted normal of the other planes at rest: the first plane of a table that tips,
    or a stray one; the machine waits for the next plane (until ``check_timeout``), which tells them apart. Four
    planes at 4 deg and a fifth at 6 deg, each stating 0.5 deg, passed the slope tests on the fifth (a review); a
    table stepping from 4.5 to 5.6 deg between the first and second plane at rest was released on the two (an
    adversarial search). None with fewer than two informative planes."""
    got = _informative(plane, post, cfg)
    if got is None or isinstance(got, str):
        return None  # (the stillness tests say why)
    _, n, stated = got
    sd = np.maximum(stated, SLOPE_STD_FLOOR)
    tilt = rotation_angle_between(n[-1], _UP)
    if _steeper(tilt, float(stated[-1]), plane, cfg) is not None:
        return (f"surface tilted {math.degrees(tilt):.2f} +- {degrees_text(float(stated[-1]))} deg in the newest "
                f"plane at rest (> {math.degrees(cfg.max_tilt):.1f} deg allowed with {cfg.level_confidence:.0%} "
                "confidence): waiting for the next")
    others = _weighted_normal(n[:-1], 1.0 / sd[:-1] ** 2)
    # its error and the others' mean's, in quadrature (with one other plane, both count)
    scale = math.hypot(float(sd[-1]), math.sqrt(1.0 / float(np.sum(1.0 / sd[:-1] ** 2))))
    off = rotation_angle_between(n[-1], others)
    if off > NEWEST_SIGMAS * scale:
        return (f"surface not still: the newest plane at rest is {math.degrees(off):.2f} deg off the others "
                f"(> {NEWEST_SIGMAS:g} x {math.degrees(scale):.2f} deg)")
    return None


def rest_tilt_problem(plane: FusedPlane, post: list[float], cfg: Any) -> str | None:
    """The planes measured at rest (:func:`_rest_normals`) read the surface steeper than ``max_tilt`` with
    ``level_confidence`` (their weighted normal's tilt less its one-sided margin, from their stated errors, the
    calibration's reference error in its standard error): the surface under the cup now, which the fused normal (the
    memory's, or the window's robust centre of planes taken on the way down) may not yet show -- a table tipping at
    10 deg/s from the stop was released at 5.9 deg on a remembered 4.5 while its two planes at rest read 5.06 and 5.39
    (an adversarial search)."""
    got = _rest_normals(plane, post, cfg, floor=False)
    if got is None or isinstance(got, str):
        return None  # (the slope and stillness tests say why the planes cannot be judged)
    _, n, sd = got
    w = 1.0 / sd**2
    tilt = rotation_angle_between(_weighted_normal(n, w), _UP)
    if (sigma := _steeper(tilt, math.sqrt(1.0 / float(w.sum())), plane, cfg)) is not None:
        return (f"surface tilted {math.degrees(tilt):.2f} +- {degrees_text(sigma)} deg in the planes at rest "
                f"(> {math.degrees(cfg.max_tilt):.1f} deg allowed, with {cfg.level_confidence:.0%} confidence; the "
                f"fused plane reads {math.degrees(plane.tilt_rad):.2f})")
    return None


def _still_planes(plane: FusedPlane, post: list[float], cfg: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray] | str:
    """(stamps, heights, stds) of the planes the stillness test judges: the post-stop ones (``post``), or the
    newest ``check_frames`` (at least 2) of the window when fewer than 2 were measured at rest (the sensor too
    close to read); else a reason. Stds are floored at ``still_offset_floor``. A judged plane that states no
    finite offset std (its estimate has no covariance) is a reason, not a guess: nothing else says how far its
    offset may err, so nothing can tell a still surface from a moving one (fail closed); so is one above
    :data:`STILL_STD_LIMIT`."""
    got = _judged_rows(plane, post, cfg, "heights", "height_stds", "offsets", "whether the surface is still is unknown",
                       float)
    if isinstance(got, str):
        return got
    t, y, sd = got
    if not (np.all(np.isfinite(t)) and np.all(np.isfinite(y))):
        return "the fused plane's per-plane offsets are not finite"
    if not np.all(np.isfinite(sd)):
        return ("a plane at rest states no uncertainty in its offset (its estimate has no covariance): "
                "whether the surface is still is unknown")
    if np.any(sd < 0.0):
        return "a plane's offset std is negative"
    if np.any(sd > STILL_STD_LIMIT):
        return (f"a plane at rest states an offset std over {STILL_STD_LIMIT:g} m (no information): whether the "
                "surface is still is unknown")
    return t, y, np.maximum(sd, cfg.still_offset_floor)


def still_problem(plane: FusedPlane, post: list[float], cfg: Any) -> str | None:
    """The surface is not shown still by the planes measured at rest (:func:`_still_planes`): their offsets
    along the fused normal (anchors in the base frame, so the arm's own motion does not enter) disagree more
    than their covariances allow (chi-square of the inverse-variance weighted offsets about their mean
    above its ``still_confidence`` quantile, ``k - 1`` degrees of freedom), or they trend (weighted
    least-squares rate over time more than the two-sided ``still_confidence`` normal quantile times its
    standard error). A surface that moves while the cup stands still above it is no place to let go: the
    fused offset lags it, and the clearance computed from it is wrong by the motion since."""
    got = _still_planes(plane, post, cfg)
    if isinstance(got, str):
        return got
    t, y, sd = got
    # (offsets of 1e154 m and beyond overflow their squares: the chi-square and the rate then read inf or NaN, and
    # both tests below fail closed on either)
    with np.errstate(over="ignore", invalid="ignore"):
        w = 1.0 / sd**2
        mean = float(w @ y / w.sum())
        chi2 = float(w @ (y - mean) ** 2)
        tc = t - float(w @ t / w.sum())
        stt = float(w @ tc**2)
        rate, rate_sd = (float(w @ (tc * (y - mean)) / stt), 1.0 / math.sqrt(stt)) if stt > 0 else (0.0, math.inf)
    limit = float(_chi2.ppf(cfg.still_confidence, len(y) - 1))
    z = NormalDist().inv_cdf(0.5 + 0.5 * cfg.still_confidence)
    if not (chi2 <= limit):
        return (f"surface not still: {len(y)} planes at rest spread {1e3 * (y.max() - y.min()):.3g} mm "
                f"(chi-square {'{} > {}'.format(*_chi_square_text(chi2, limit))} for offsets +- "
                f"{1e3 * float(sd.min()):.1f} mm)")
    if not (abs(rate) <= z * rate_sd):
        return (f"surface not still: {len(y)} planes at rest move {1e3 * rate:.3g} mm/s "
                f"(> {1e3 * z * rate_sd:.0f} mm/s their noise allows)")
    return None


def contact_limit(cfg: Any) -> float:
    """The highest cup clearance (m) at which a contact counts as arrival on the sensed surface: ``contact_clearance``,
    and at most ``cup_radius tan(max_tilt) - descend_speed contact_latency``. A contact higher up is the cup on
    something above the surface that no footprint view need have seen (a box a few millimetres high under part of a
    zone moves its point by a fraction of its height). Released on a thing ``h`` high whose edge lies ``e`` from the
    cup's centre (``0 <= e <= cup_radius``), the cup pivots on that edge until its far rim meets the table: tilted
    ``atan(h / (cup_radius + e))``, at worst (``e`` = 0) ``h / cup_radius``: 3.1 mm at 35 mm and 5 deg. The touch is
    read ``descend_speed contact_latency`` late (1.2 mm at 25 mm/s and the CB3's 48 ms). So at the defaults a contact
    counts as arrival up to 1.9 mm, and, the descent stopping 3 mm above the sensed surface (``stop_clearance``), a
    table sensed 2.5-3 mm or more too low (the tool's cup offset or sensor mount that far off) is touched and refused
    as an obstacle. The estimate's own error adds. A negative limit admits no contact. A cup of no radius cannot tilt:
    ``contact_clearance``."""
    if cfg.cup_radius > 0.0:
        tilt_bound = cfg.cup_radius * math.tan(cfg.max_tilt) - cfg.descend_speed * cfg.contact_latency
        return min(cfg.contact_clearance, tilt_bound)
    return cfg.contact_clearance


def contact_clearance_text(cfg: Any, clearance: float) -> str:
    """The cup's ``clearance`` (m) in millimetres as a contact refusal prints it before :func:`contact_limit_text`: on
    the limit's side it is on (:func:`compared_text`)."""
    return compared_text(clearance * 1e3, contact_limit(cfg) * 1e3)[0]


def contact_limit_text(cfg: Any) -> str:
    """The contact limit as a refusal states it: "> 1.9 mm" (exactly: :func:`exact_text`; the cup's clearance before it
    is :func:`contact_clearance_text`), and where no touch can count as arrival (the limit below zero: a detector that
    reads a touch later than the descent allows) why."""
    limit = contact_limit(cfg)
    text = f"> {exact_text(limit * 1e3)} mm"
    if limit < 0.0:
        text += (f": no touch can count as arrival, the contact detector reading a touch {cfg.contact_latency * 1e3:.0f}"
                 f" ms late, {cfg.descend_speed * cfg.contact_latency * 1e3:.1f} mm of descent")
    return text


def clearance_floor(plane: FusedPlane, post: list[float], cfg: Any) -> float:
    """The most negative cup clearance (m, <= 0) the noise allows without contact: minus the two-sided
    ``still_confidence`` quantile of the standard error of the planes' mean offset (:func:`_still_planes`), and
    never below ``-release_clearance``. A surface farther above the cup bottom than that has moved, or the
    cup stands on something; 0 when the planes cannot say (the caller's stillness test refuses then)."""
    got = _still_planes(plane, post, cfg)
    if isinstance(got, str):
        return 0.0
    with np.errstate(over="ignore"):
        info = float(np.sum(1.0 / got[2] ** 2))  # stds beyond ~1e154 m square to inf: no information
    if not (info > 0.0):
        return 0.0
    z = NormalDist().inv_cdf(0.5 + 0.5 * cfg.still_confidence)
    return -min(cfg.release_clearance, z * math.sqrt(1.0 / info))


__all__ = ["fault_text", "degrees_text", "number_text", "exact_text", "compared_text", "contact_clearance_text",
           "number", "too_close", "plane_problem", "sensor_problem", "planar_problem",
           "tilt_problem",
           "tilt_sigma", "confidence_margin", "level_problem", "confidently_tilted", "footprint_problem",
           "footprint_seen", "check_frames_needed", "post_stop_stamps", "still_problem", "slope_still_problem",
           "rest_tilt_problem", "newest_plane_problem", "pending_problem", "most_check_frames",
           "contact_limit", "contact_limit_text", "clearance_floor"]
