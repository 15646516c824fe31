"""The live view of a sensor stream in rerun: histograms, model fit, recovered plane, latency and frame rate.

Concept
-------
:class:`RerunView` logs, per estimated frame, on the timelines ``frame`` (arrival index) and
``sensor_time`` (``Frame.timestamp``, seconds):

* ``histograms/zone_<k>`` and ``histograms/reference``: bar charts of the counts;
* ``fit/zone_<k>``: the forward model's histograms of the recovered plane (when the estimator reports an
  albedo), with the frame's measured floor added, for comparison with the measurement;
* ``world/plane`` (a square patch of the plane in the sensor frame, metres, +z the optical axis),
  ``world/normal``, ``world/zones`` (where the nine zone centres meet the plane) and ``world/sensor``;
* ``plane/tilt_deg``, ``plane/distance_mm``, ``timing/latency_ms`` and ``timing/fps``: scalar series.

``save=PATH`` writes an ``.rrd`` recording (headless machines; open it later with ``rerun PATH``);
otherwise a viewer is spawned. rerun (the ``[view]`` extra, ``rerun-sdk``) is imported only here.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from place_safe.exceptions import ConfigError
from place_safe.sensor.frame import Frame
from place_safe.sensor.histogram import measure_floor
from place_safe.sensor.zones import N_ZONES, ZONE_DIRECTIONS

#: Half side (m) of the plane patch drawn in 3D.
PATCH_HALF = 0.08


def _write_error(exc: RuntimeError, path: str | Path) -> OSError:
    """rerun's failure to write the recording (a RuntimeError such as "Failed to encode LogMsg: Failed to write: No
    space left on device (os error 28)") as the OSError of ``path`` that the command line reports for every file it
    cannot write (one line naming the file and the OS error)."""
    if (m := re.search(r"os error (\d+)", str(exc))) is not None:
        return OSError(int(m.group(1)), os.strerror(int(m.group(1))), str(path))
    text = str(exc).strip().splitlines()
    return OSError(None, f"cannot write the rerun recording ({text[0] if text else type(exc).__name__})", str(path))


class RerunView:
    """Log frames and estimates to rerun (see module docstring).

    save: path of an .rrd file to write (no viewer); None spawns a viewer.
    params: forward-model parameters for the fit overlay (None: no overlay).
    """

    def __init__(self, save: str | Path | None = None, params: Any = None, name: str = "place-safe sensor") -> None:
        try:
            import rerun as rr
        except ImportError:
            raise ConfigError("the live view needs rerun (pip install 'place-safe[view]')") from None
        self.rr = rr
        rr.init(name, spawn=save is None)
        if save is not None:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            try:
                rr.save(str(save))  # writes the recording's header at once
            except RuntimeError as exc:
                raise _write_error(exc, save) from None
        self._model = None
        if params is not None:
            from place_safe.recovery.forward import ForwardModel, ZoneRays  # torch: only for the fit overlay

            self._model = ForwardModel(params, ZoneRays.stratified(4))
        self._last_t: float | None = None
        rr.log("world/sensor", rr.Points3D([[0.0, 0.0, 0.0]], radii=0.004, labels=["TMF8820"]), static=True)

    def log(self, index: int, frame: Frame, estimate: Any, latency: float) -> None:
        rr = self.rr
        rr.set_time("frame", sequence=int(index))
        if frame.timestamp is not None:
            rr.set_time("sensor_time", duration=float(frame.timestamp))
        hists = np.asarray(frame.hists, dtype=float)
        if hists.shape == (N_ZONES, 128) and np.all(np.isfinite(hists)):
            for k in range(N_ZONES):
                rr.log(f"histograms/zone_{k + 1}", rr.BarChart(hists[k]))
        if frame.reference is not None and np.all(np.isfinite(frame.reference)):
            rr.log("histograms/reference", rr.BarChart(np.asarray(frame.reference, dtype=float)))
        rr.log("timing/latency_ms", rr.Scalars(latency * 1e3))
        if frame.timestamp is not None and self._last_t is not None and frame.timestamp > self._last_t:
            rr.log("timing/fps", rr.Scalars(1.0 / (frame.timestamp - self._last_t)))
        if frame.timestamp is not None:
            self._last_t = frame.timestamp
        plane = getattr(estimate, "plane", None)
        if plane is None:
            rr.log("plane/status", rr.TextLog(f"no plane: {getattr(estimate, 'reason', '') or 'unknown'}"))
            return
        n, d = np.asarray(plane.normal, dtype=float), float(plane.offset)
        rr.log("plane/tilt_deg", rr.Scalars(math.degrees(plane.theta)))
        rr.log("plane/distance_mm", rr.Scalars(d * 1e3))
        centre = n * d
        u = np.cross(n, [0.0, 1.0, 0.0] if abs(n[1]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        corners = [centre + PATCH_HALF * (su * u + sv * v) for su, sv in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
        rr.log("world/plane", rr.Mesh3D(vertex_positions=corners, triangle_indices=[[0, 1, 2], [0, 2, 3]],
                                        vertex_colors=[[90, 160, 230]] * 4))
        rr.log("world/normal", rr.Arrows3D(origins=[centre], vectors=[-0.03 * n]))
        pts = plane.intersect(ZONE_DIRECTIONS)
        rr.log("world/zones", rr.Points3D(pts, radii=0.002, labels=[str(k + 1) for k in range(N_ZONES)]))
        albedo = getattr(estimate, "albedo", None)
        if self._model is not None and albedo is not None and math.isfinite(albedo) and frame.reference is not None:
            self._log_fit(n, d, float(albedo), frame)

    def _log_fit(self, n: np.ndarray, d: float, albedo: float, frame: Frame) -> None:
        import torch

        with torch.no_grad():
            h = self._model.render_plane(torch.as_tensor(n)[None], torch.as_tensor([d]), torch.as_tensor([albedo]),
                                         torch.as_tensor(np.asarray(frame.reference, dtype=float))[None])[0].numpy()
        fit = h - self._model.params.floor + measure_floor(np.asarray(frame.hists, dtype=float))[:, None]
        for k in range(N_ZONES):
            self.rr.log(f"fit/zone_{k + 1}", self.rr.BarChart(fit[k]))

    def close(self) -> None:
        self.rr.disconnect()


__all__ = ["RerunView", "PATCH_HALF"]
