"""The Frame: one TMF8820 measurement (nine zone histograms, the reference histogram, on-sensor
distances, timing and optional ground truth).

Conventions: zones 1..9 in the sensor's reporting order (arrays 0..8, see :mod:`place_safe.sensor.zones`);
a histogram has 128 bins of counts; channel 0 of a measurement is the reference histogram (the laser
pulse seen inside the package), channels 1..9 the zones; on-sensor distances are millimetres in
files and metres in :class:`Frame`; ``timestamp`` is seconds on the clock of the source that made it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from place_safe.exceptions import FrameError, NoPlaneError
from place_safe.geometry import Plane, is_rotation, plane_from_pose
from place_safe.sensor.histogram import COUNT_MAX, beyond_count_max, first_return
from place_safe.sensor.zones import CENTRE, CORNER, EDGE, N_BINS, N_ZONES, ZONE_DIRECTIONS, ZONE_KIND, ZONE_RECTS  # noqa: F401


#: m: the largest on-sensor distance a frame may carry: the TMF8820 reports whole millimetres in 16 bits.
MAX_SENSOR_DISTANCE = 0xFFFF / 1000.0
#: m: the farthest the TMF8820 is specified to measure (docs/tmf8820.md, "Range"; the datasheet's 5 m, in its
#: long-range mode). An on-sensor distance beyond it (up to :data:`MAX_SENSOR_DISTANCE` the field can hold: 65535 mm
#: at full confidence read as a plane 64 m away) is no target the sensor measured, and a plane recovered beyond it is
#: no plane (:func:`place_safe.recovery.estimator.checked`: a proprietary ``b`` of -10000 put planes 9-10 m away). A
#: ground truth may lie farther (it states geometry, not a reading); a return lands in the histograms only to about
#: 1.3 m.
SENSOR_RANGE = 5.0
#: The largest on-sensor confidence a frame may carry (one byte per zone; 0 = no object).
MAX_CONFIDENCE = 255
#: m: the smallest non-zero one (0 means no object).
MIN_SENSOR_DISTANCE = 1e-3


def reported_distances(ranges: Any, rounding: int = 3, *, hists: Any = None) -> tuple[np.ndarray, np.ndarray]:
    """On-sensor distances (m) and confidences as a TMF8820 reports them for the ranges ``ranges`` (m, per zone) a
    simulation computed: rounded to ``rounding`` decimals (mm), a range below :data:`MIN_SENSOR_DISTANCE` or above
    :data:`SENSOR_RANGE` (the sensor measures no farther), or not finite, as 0 with confidence 0 (no object), the rest at
    :data:`MAX_CONFIDENCE`. (The generators wrote a noisy range of 0.1 mm as -1 mm at full confidence, which the
    frame format does not allow: a review's bad-input search.)

    ``hists`` (9, 128), the frame's zone histograms: a zone whose histogram shows no return (the firmware's reading
    that the simulated sensor emulates, :func:`place_safe.sensor.histogram.first_return`) reports no object either.
    (``synth`` at 4.9-5 m wrote full-confidence distances over histograms with nothing in them: a return lands in
    the bins only to about 1.3 m.)"""
    r = np.round(np.asarray(ranges, dtype=float), rounding)
    seen = np.isfinite(r) & (r >= MIN_SENSOR_DISTANCE) & (r <= SENSOR_RANGE)
    if hists is not None:
        seen &= first_return(np.asarray(hists, dtype=float))[1]
    return np.where(seen, r, 0.0), np.where(seen, float(MAX_CONFIDENCE), 0.0)


def has_bool(value: Any) -> bool:
    """Whether ``value`` is a boolean or a (nested) list holding one."""
    return isinstance(value, bool) or (isinstance(value, list) and any(has_bool(v) for v in value))


def _array(value: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    """``value`` (a file's nested lists) as a float array of ``shape``; FrameError for strings, booleans, nulls
    and ragged data. Booleans are caught where a list of them reads as booleans (all of an array, or any entry
    of a short one such as the distances or a pose); a single ``true`` among a histogram's 1152 counts reads as a count
    of 1 here (checking every entry would cost a twentieth of the peak method's time a frame); the frame file reader
    catches it from the entry's text (``io.frame_file``)."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError, OverflowError):
        raise FrameError(f"{name} is not an array of numbers (ragged or unreadable)") from None
    if arr.dtype.kind == "O":  # integers beyond 64 bits (or mixed objects): numbers only, as floats
        if not all(type(v) in (int, float) for v in arr.ravel()):
            raise FrameError(f"{name} must hold numbers only")
        try:
            arr = arr.astype(float)
        except OverflowError:
            raise FrameError(f"{name} is not numeric: a number too large for a float") from None
    elif arr.dtype.kind not in "iuf" or (arr.size <= 16 and has_bool(value)):
        what = "booleans" if arr.dtype.kind in "biu" else "text" if arr.dtype.kind in "US" else f"{arr.dtype.name} values"
        raise FrameError(f"{name} must hold numbers, not {what}")
    if arr.shape != shape:
        raise FrameError(f"{name} has shape {arr.shape}, expected {shape}")
    return arr.astype(float, copy=False)


def real_array(value: Any, name: str) -> np.ndarray:
    """``value`` as an array of real numbers; FrameError for strings, objects, complex or ragged data, booleans, and
    for a masked array with any entry masked (its mask says those values are not to be used, and an array of numbers
    has no place to carry that: counted as they stand they would go into the plane unseen). Booleans are no counts or
    distances (a frame file's are refused when read): an array of them given as on-sensor distances read as 1 m in
    every zone, and ``proprietary`` stated a plane at 0.98 m (session 82)."""
    if isinstance(value, np.ma.MaskedArray) and (n := int(np.ma.getmaskarray(value).sum())):
        raise FrameError(f"{name} is a masked array with {n} masked entr{'y' if n == 1 else 'ies'}: the mask cannot be "
                         "honoured here; fill them (np.ma.filled) or leave the frame out")
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError, OverflowError):
        raise FrameError(f"{name} is not an array of numbers (ragged or unreadable)") from None
    if arr.dtype.kind == "b":
        raise FrameError(f"{name} must hold numbers, not booleans")
    if arr.dtype.kind not in "iuf":
        raise FrameError(f"{name} must hold real numbers, got {arr.dtype.name} values")
    return arr


def _measurement_key(frame: Any) -> bytes:
    """The bytes of what ``frame`` measured (histograms, reference, on-sensor distances and confidences; not its
    ground truth, pose or extras): two frames with equal keys are one measurement."""
    parts = []
    for value in (frame.hists, frame.reference, frame.distances, frame.confidences):
        if value is None:
            parts.append(b"-")
            continue
        arr = np.ascontiguousarray(np.asarray(value, dtype=float))
        parts.append(repr(arr.shape).encode() + arr.tobytes())
    return b"|".join(parts)


def repeated_frames(frames: Any) -> list[tuple[int, int]]:
    """Every frame ``i`` of ``frames`` that repeats an earlier frame ``j`` exactly (the same histograms, reference and
    on-sensor distances, whatever its ground truth or pose says), as ``(i, j)`` pairs in order (``j`` the first frame of
    that measurement); empty when every frame is its own measurement. No two real measurements hold the same 1152 counts
    (Poisson noise), so a repeat is a frame given twice (files pasted or joined, a stale frame read again) or a
    noise-free synthetic frame drawn twice: either way one measurement, which a fit must count once. Counted twice,
    fifteen frames that were three repeated five times passed ``calibrate``'s 5-frame minimum and wrote a peak
    calibration with no floor and the smallest scale (planes stated to micrometres), and a capture given twice halved
    the variance of every mount direction ``calibrate-mount`` states (an adversarial round, session 82). Entries that
    are not readable frames are passed over (whoever reads them says so)."""
    seen: dict[bytes, int] = {}
    pairs = []
    for i, f in enumerate(frames):
        try:
            key = _measurement_key(f)
        except (AttributeError, TypeError, ValueError, OverflowError):
            continue
        j = seen.setdefault(key, i)
        if j != i:
            pairs.append((i, j))
    return pairs


def without_repeats(frames: Any, counted: str = "counting from 0") -> tuple[list, str | None, list[int]]:
    """``frames`` (a list) with each exact repeat (:func:`repeated_frames`) left out, the first of each measurement
    kept in its place; a one-line note of what was left out (None: nothing), e.g. ``"frame 3 repeats frame 0 exactly
    (counting from 0; the same histograms and on-sensor distances; 12 frames repeat an earlier one): each measurement
    counted once, the repeats left out (frames pasted or files joined?)"``; and the indices kept (for arrays that go
    with the frames). ``counted`` says how the frames are numbered."""
    frames = list(frames)
    pairs = repeated_frames(frames)
    if not pairs:
        return frames, None, list(range(len(frames)))
    drop = {i for i, _ in pairs}
    keep = [k for k in range(len(frames)) if k not in drop]
    (i, j), n = pairs[0], len(pairs)
    note = (f"frame {i} repeats frame {j} exactly ({counted}; the same histograms and on-sensor distances; {n} "
            f"frame{'' if n == 1 else 's'} repeat{'s' if n == 1 else ''} an earlier one): each measurement counted once, "
            "the repeats left out (frames pasted or files joined?)")
    return [frames[k] for k in keep], note, keep


def _first_line(exc: BaseException) -> str:
    text = str(exc)
    return text.splitlines()[0] if text else type(exc).__name__


def _number(value: Any, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{name} must be a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


#: How far a ground-truth pose's rotation may be from orthonormal (|R^T R - I|, max entry).
POSE_ORTHONORMAL_TOL = 1e-3


def _truth(d: dict) -> Plane | None:
    """The ground-truth plane of a frame dict (None without one); raises ValueError/NoPlaneError if it is not
    a plane in front of the sensor (``n_z > 0``, ``d > 0``, finite; a pose must be a rigid transform)."""
    if d.get("plane") is not None:
        pl = d["plane"]
        if not isinstance(pl, dict):
            raise ValueError(f"'plane' must be an object with 'normal' and 'offset', got {type(pl).__name__}")
        normal = _array(pl["normal"], "plane.normal", (3,))
        offset = _number(pl["offset"], "plane.offset")
        truth = Plane(normal, offset)  # normalises, and flips a normal written with n_z < 0
    elif "pose" in d and "dist_to_plane" in d:
        pose = _array(d["pose"], "pose", (4, 4))
        if not np.all(np.isfinite(pose)):
            raise ValueError("pose must be a finite 4x4 matrix")
        if not is_rotation(pose[:3, :3], POSE_ORTHONORMAL_TOL):
            raise ValueError("pose is not a rigid transform (its 3x3 block is not a rotation)")
        truth = plane_from_pose(pose, _number(d["dist_to_plane"], "dist_to_plane"))
    else:
        return None
    if not 0 < truth.offset <= MAX_SENSOR_DISTANCE:
        raise ValueError(f"plane offset must be > 0 (plane in front of the sensor) and at most "
                         f"{MAX_SENSOR_DISTANCE:g} m (the farthest the sensor reports), got {truth.offset:.6g} m")
    return truth


def _on_sensor(dist: Any) -> tuple[np.ndarray, np.ndarray | None]:
    """(distances in m, confidences or None) of a frame file's ``distances`` entry; FrameError if malformed."""
    entry = dist[0] if isinstance(dist, list) else dist
    if not isinstance(entry, dict) or "depths_1" not in entry:
        raise FrameError("'distances' must hold a dict with 'depths_1'")
    distances = _array(entry["depths_1"], "depths_1", (N_ZONES,)) / 1000.0
    confidences = _array(entry["confs_1"], "confs_1", (N_ZONES,)) if "confs_1" in entry else None
    return distances, confidences


@dataclass
class Frame:
    """One 3x3 TMF8820 measurement.

    Attributes
    ----------
    hists: (9, 128) zone histograms in counts, zones 1..9 in the sensor's order.
    reference: (128,) reference histogram (counts) or None when the source had none.
    distances: (9,) on-sensor first-object distances (m) or None; 0 means no object.
    confidences: (9,) on-sensor confidences (0..MAX_CONFIDENCE) or None.
    timestamp: seconds (source-defined epoch) or None.
    truth: ground-truth plane in the sensor frame, if known.
    extra: everything else from the file (joint angles, pose, meta), carried through.
    truth_error: why the file's ground truth could not be used (then ``truth`` is None); it affects
        only evaluation and calibration, which skip such frames, never recovery.
    timestamp_error: why the file's ``timestamp`` could not be used (not a finite number of seconds): ``from_dict``
        leaves ``timestamp`` None, an unstamped frame, which the frame gate drops (a replay stamps it anew);
        recovery does not read it.
    distances_error: why the file's ``distances`` could not be read (not a dict with 9 numbers in ``depths_1`` and
        ``confs_1``): ``from_dict`` leaves ``distances`` and ``confidences`` None; only the methods that read the
        on-sensor distances (``proprietary``) refuse the frame, with this reason, and the histogram methods read it.
    """

    hists: np.ndarray
    reference: np.ndarray | None = None
    distances: np.ndarray | None = None
    confidences: np.ndarray | None = None
    timestamp: float | None = None
    truth: Plane | None = None
    extra: dict = field(default_factory=dict)
    truth_error: str | None = None
    timestamp_error: str | None = None
    distances_error: str | None = None

    def validate(self, *, need_reference: bool = True) -> None:
        """Raise :class:`FrameError` unless the histograms can be used for recovery.

        Counts must be real numbers (not strings, objects, complex or ragged lists), finite and >= 0; a reference
        histogram's no more than its 24-bit counters hold (:func:`~place_safe.sensor.histogram.beyond_count_max`: the
        zones' histograms are each method's to check, which names the zones).
        ``need_reference=False``: a frame without a reference histogram passes (one that has it is checked): for a
        method that reads no histogram but trusts no corrupt frame (``proprietary``).
        """
        h = real_array(self.hists, "hists")
        if h.shape != (N_ZONES, N_BINS):
            raise FrameError(f"hists has shape {h.shape}, expected ({N_ZONES}, {N_BINS})")
        if np.count_nonzero(np.isfinite(h)) < h.size:
            raise FrameError("hists contains NaN or infinite counts")
        if h.min() < 0:
            raise FrameError("hists contains negative counts")
        if self.reference is None:
            if not need_reference:
                return
            raise FrameError("reference histogram is missing")
        r = real_array(self.reference, "reference_hist")
        if r.shape != (N_BINS,):
            raise FrameError(f"reference_hist has shape {r.shape}, expected ({N_BINS},)")
        # the usual reference, in two reductions (NaN fails both tests; compared as Python floats, since COUNT_MAX
        # cast to float16 is infinite and an infinite count would pass)
        if float(r.min()) >= 0 and float(r.max()) <= COUNT_MAX:
            return
        if np.count_nonzero(np.isfinite(r)) < r.size or r.min() < 0:
            raise FrameError("reference_hist contains NaN, infinite or negative counts")
        if (beyond := beyond_count_max(r, "reference histogram")) is not None:  # corrupt, whether a method reads it
            raise FrameError(beyond)  # or not (peak gave its plane, where proprietary and diff refused: round 14)

    def is_valid(self) -> bool:
        """Whether :meth:`validate` passes (False where it raises :class:`FrameError`)."""
        try:
            self.validate()
        except FrameError:
            return False
        return True

    # -- file form (docs/interfaces.md) ----------------------------------------------------------
    @classmethod
    def from_dict(cls, d: dict, *, truth: bool = True) -> "Frame":
        """Build a frame from the JSON form; raises :class:`FrameError` on malformed entries.

        ``truth=False`` leaves the ground truth unread (``truth`` and ``truth_error`` None): for a reader that never
        uses it (``recover``), which it spares parsing a pose (a third of reading a frame). Ground truth never makes
        a frame unreadable, so every other field comes out the same either way."""
        if not isinstance(d, dict):
            raise FrameError(f"a frame must be a JSON object, got {type(d).__name__}")
        if "hists" not in d:
            raise FrameError("frame has no 'hists'")
        hists = _array(d["hists"], "hists", (N_ZONES, N_BINS))
        ref = d.get("reference_hist")
        reference = None if ref is None else _array(ref, "reference_hist", (N_BINS,))
        distances = confidences = distances_error = None
        dist = d.get("distances")
        if dist:  # read only by the methods of the on-sensor distances: a bad one costs them the frame, not the others
            try:
                distances, confidences = _on_sensor(dist)
            except FrameError as exc:
                distances_error = f"on-sensor distances unusable: {exc}"
        plane, truth_error = None, None
        try:
            plane = _truth(d) if truth else None
        except (KeyError, TypeError, ValueError, OverflowError, NoPlaneError) as exc:
            truth_error = f"ground truth is not a plane in front of the sensor: {_first_line(exc)}"
        known = {"hists", "reference_hist", "distances", "plane"}
        extra = {k: v for k, v in d.items() if k not in known}
        ts, timestamp_error = d.get("timestamp"), None
        if ts is not None:  # not in the shared format: a bad one costs the frame its stamp, not its histograms
            if isinstance(ts, bool) or not isinstance(ts, (int, float)):
                timestamp_error = f"timestamp must be a number of seconds, got {type(ts).__name__}"
            else:
                try:
                    ts = float(ts)
                except OverflowError:
                    ts = math.inf
                if not math.isfinite(ts):
                    timestamp_error = "timestamp must be a finite number of seconds"
            ts = None if timestamp_error else ts
        return cls(hists, reference, distances, confidences, ts, plane, extra, truth_error, timestamp_error,
                   distances_error)

    def to_dict(self) -> dict:
        """The JSON form of docs/interfaces.md (ground truth as ``plane``; extras carried)."""
        out: dict[str, Any] = dict(self.extra)
        out["hists"] = np.asarray(self.hists).tolist()
        if self.reference is not None:
            out["reference_hist"] = np.asarray(self.reference).tolist()
        if self.distances is not None:
            entry: dict[str, Any] = {"depths_1": [float(v) for v in np.round(np.asarray(self.distances) * 1000.0, 3)]}
            if self.confidences is not None:
                entry["confs_1"] = [float(v) for v in self.confidences]
            out["distances"] = [entry]
        if self.truth is not None:
            out["plane"] = self.truth.to_dict()
            out.pop("pose", None) if "dist_to_plane" not in out else None
        if self.timestamp is not None:
            out["timestamp"] = self.timestamp
        return out
