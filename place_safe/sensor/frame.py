"""The Frame: one TMF8820 measurement (nine zone histograms, the reference histogram, on-sensor
distances, timing and optional ground truth).

Conventions: zones 1..9 in the sensor's reporting order (arrays 0..8, see :mod:`place_safe.sensor.zones`);
a histogram has 128 bins of counts; channel 0 of a measurement is the reference histogram (the laser
pulse seen inside the package), channels 1..9 the zones; on-sensor distances are millimetres in
files and metres in :class:`Frame`; ``timestamp`` is seconds on the clock of the source that made it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from place_safe.exceptions import FrameError
from place_safe.geometry import Plane, plane_from_pose
from place_safe.sensor.zones import CENTRE, CORNER, EDGE, N_BINS, N_ZONES, ZONE_DIRECTIONS, ZONE_KIND, ZONE_RECTS  # noqa: F401


def _array(value: Any, name: str, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise FrameError(f"{name} is not numeric: {exc}") from None
    if arr.shape != shape:
        raise FrameError(f"{name} has shape {arr.shape}, expected {shape}")
    return arr


@dataclass
class Frame:
    """One 3x3 TMF8820 measurement.

    Attributes
    ----------
    hists: (9, 128) zone histograms in counts, zones 1..9 in the sensor's order.
    reference: (128,) reference histogram (counts) or None when the source had none.
    distances: (9,) on-sensor first-object distances (m) or None; 0 means no object.
    confidences: (9,) on-sensor confidences (0..255) or None.
    timestamp: seconds (source-defined epoch) or None.
    truth: ground-truth plane in the sensor frame, if known.
    extra: everything else from the file (joint angles, pose, meta), carried through.
    """

    hists: np.ndarray
    reference: np.ndarray | None = None
    distances: np.ndarray | None = None
    confidences: np.ndarray | None = None
    timestamp: float | None = None
    truth: Plane | None = None
    extra: dict = field(default_factory=dict)

    def validate(self) -> None:
        """Raise :class:`FrameError` unless the histograms can be used for recovery."""
        h = np.asarray(self.hists)
        if h.shape != (N_ZONES, N_BINS):
            raise FrameError(f"hists has shape {h.shape}, expected ({N_ZONES}, {N_BINS})")
        if not np.all(np.isfinite(h)):
            raise FrameError("hists contains NaN or infinite counts")
        if np.any(h < 0):
            raise FrameError("hists contains negative counts")
        if self.reference is None:
            raise FrameError("reference histogram is missing")
        r = np.asarray(self.reference)
        if r.shape != (N_BINS,):
            raise FrameError(f"reference_hist has shape {r.shape}, expected ({N_BINS},)")
        if not np.all(np.isfinite(r)) or np.any(r < 0):
            raise FrameError("reference_hist contains NaN, infinite or negative counts")

    # -- file form (docs/interfaces.md) ----------------------------------------------------------
    @classmethod
    def from_dict(cls, d: dict) -> "Frame":
        """Build a frame from the JSON form; raises :class:`FrameError` on malformed entries."""
        if not isinstance(d, dict):
            raise FrameError(f"a frame must be a JSON object, got {type(d).__name__}")
        if "hists" not in d:
            raise FrameError("frame has no 'hists'")
        hists = _array(d["hists"], "hists", (N_ZONES, N_BINS))
        ref = d.get("reference_hist")
        reference = None if ref is None else _array(ref, "reference_hist", (N_BINS,))
        distances = confidences = None
        dist = d.get("distances")
        if dist:
            entry = dist[0] if isinstance(dist, list) else dist
            if not isinstance(entry, dict) or "depths_1" not in entry:
                raise FrameError("'distances' must hold a dict with 'depths_1'")
            distances = _array(entry["depths_1"], "depths_1", (N_ZONES,)) / 1000.0
            if "confs_1" in entry:
                confidences = _array(entry["confs_1"], "confs_1", (N_ZONES,))
        truth = None
        try:
            if "plane" in d and d["plane"] is not None:
                truth = Plane.from_dict(d["plane"])
            elif "pose" in d and "dist_to_plane" in d:
                truth = plane_from_pose(np.asarray(d["pose"], dtype=float), float(d["dist_to_plane"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise FrameError(f"ground truth is malformed: {exc}") from None
        known = {"hists", "reference_hist", "distances", "plane"}
        extra = {k: v for k, v in d.items() if k not in known}
        ts = d.get("timestamp")
        return cls(hists, reference, distances, confidences, None if ts is None else float(ts), truth, extra)

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
