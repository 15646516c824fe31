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

Saving: rerun's file sink writes into a pipe and a thread of ours copies it to PATH (:class:`_PipedFile`), so a write
that fails -- a disk that fills mid-stream -- is an OSError we see: :meth:`RerunView.log` then raises
:class:`RecordingError` (the stream stops; what was written stays in the file, and rerun reads a recording cut short),
while the thread drains the pipe so that rerun never blocks on it (rerun's own sink logged the failure, kept going,
and could hang the process when it was disconnected).
"""

from __future__ import annotations

import math
import os
import re
import select
import threading
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


#: s: how long the recording's header may take to come through the pipe before the thread writes it instead
HEADER_WAIT_S = 2.0
#: s: how long closing waits for rerun's last bytes to reach the file
CLOSE_WAIT_S = 10.0
#: bytes read from the pipe at a time
CHUNK = 1 << 16


class RecordingError(OSError):
    """Writing a recording failed after it had started (a full disk, a quota): ``errno``, ``strerror`` and
    ``filename`` as the OSError's; ``written`` bytes are in the file; ``frame`` is the index of the frame being
    logged when it was noticed (None: at the end)."""

    def __init__(self, error: OSError, path: str, written: int, frame: int | None) -> None:
        super().__init__(error.errno, error.strerror or str(error), path)
        self.written, self.frame = written, frame

    def line(self) -> str:
        """The one line that says what happened, for the command's error message."""
        at = "at the end" if self.frame is None else f"at frame {self.frame}"
        return (f"--save {self.filename}: {self.strerror} after {self.written / 1e3:.1f} kB ({at}): stopped; the "
                f"frames written before stay readable (rerun {self.filename})")


def _open_output(path: str | Path):
    """The recording's file, unbuffered (every write reaches the OS, so a failing one fails here)."""
    return open(path, "wb", buffering=0)  # noqa: SIM115 - closed by _PipedFile.close


def _write_all(out: Any, data: bytes) -> None:
    """Write all of ``data`` (a raw file may take part of it: a disk filling up takes what fits, then refuses)."""
    view = memoryview(data)
    while view:
        n = out.write(view)
        view = view[n if n is not None else len(view):]


class _PipedFile:
    """rerun's file sink through a pipe into ``path`` (see the module docstring). ``error``: the first write that
    failed (an OSError naming ``path``), after which the pipe is still drained and the rest dropped."""

    def __init__(self, rr: Any, path: str | Path) -> None:
        self.path, self.written, self.error = str(path), 0, None
        self.out = _open_output(path)
        r, w = os.pipe()
        try:
            rr.save(f"/dev/fd/{w}")  # rerun opens its own descriptor of the pipe's write end
        except RuntimeError as exc:
            os.close(r)
            self.out.close()
            raise _write_error(exc, path) from None
        finally:
            os.close(w)
        self._r = r
        if select.select([r], [], [], HEADER_WAIT_S)[0]:  # the header: a file that cannot take it fails at once
            self._copy(os.read(r, CHUNK))
            if self.error is not None:
                rr.disconnect()  # rerun ends its stream into the pipe (room enough) before the pipe closes
                os.close(r)
                self.out.close()
                raise self.error
        self._thread = threading.Thread(target=self._pump, name="rerun-save", daemon=True)
        self._thread.start()

    def _copy(self, data: bytes) -> None:
        if self.error is not None:
            return
        try:
            _write_all(self.out, data)
            self.written += len(data)
        except ValueError:  # the file was closed under us (close() gave up waiting): already reported there
            return
        except OSError as exc:
            try:
                self.written = self.out.tell()  # with the part of ``data`` that fitted
            except (OSError, ValueError):
                pass
            # published last: the stream's thread reads ``written`` as soon as it sees ``error``; in the other order a
            # loaded machine could report the bytes before this write (most likely why one CI run's message did not
            # say the 40.0 kB its test's disk took)
            self.error = OSError(exc.errno, exc.strerror or str(exc), self.path)

    def _pump(self) -> None:
        try:
            while data := os.read(self._r, CHUNK):
                self._copy(data)
        except OSError as exc:  # the pipe itself (not expected)
            if self.error is None:
                self.error = OSError(exc.errno, exc.strerror or str(exc), self.path)

    def close(self) -> None:
        """After rerun let go of the pipe (``disconnect``): wait for its last bytes, close the file."""
        self._thread.join(CLOSE_WAIT_S)
        if self._thread.is_alive():  # rerun still writing: what it writes from now on is lost, and that is said
            if self.error is None:
                self.error = OSError(None, f"the recording was still being written {CLOSE_WAIT_S:g} s after the stream "
                                           "ended: it may be cut short", self.path)
        else:
            os.close(self._r)
        try:
            self.out.close()
        except OSError as exc:
            if self.error is None:
                self.error = OSError(exc.errno, exc.strerror or str(exc), self.path)


#: The first bytes of a rerun recording (``.rrd``: "RRF" and a format digit).
RECORDING_MAGIC = b"RRF"


def not_a_recording(path: str | os.PathLike) -> bool:
    """Whether ``path`` is a file with something in it that is not a rerun recording (a frame file, a calibration):
    ``--save`` replaced such a file without a word (``sensor stream --save sweep.json`` lost the sweep; session 82).
    A recording, an empty file, a missing path or a device is not such a file."""
    try:
        if not os.path.isfile(path) or os.path.getsize(path) == 0:
            return False
        with open(path, "rb") as fh:
            return not fh.read(len(RECORDING_MAGIC)) == RECORDING_MAGIC
    except OSError:
        return False  # unreadable: writing it says why


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
        try:
            rr.init(name, spawn=save is None)
        except RuntimeError as exc:  # no viewer to spawn (rerun's "Failed to find Rerun Viewer executable in PATH")
            if save is not None:
                raise
            raise ConfigError(f"--view cannot start the rerun viewer: {str(exc).strip().splitlines()[0]} (install "
                              "it, or record with --save RUN.rrd and open it with 'rerun RUN.rrd')") from None
        self._file: _PipedFile | None = None
        self._reported: RecordingError | None = None
        if save is not None:
            Path(save).parent.mkdir(parents=True, exist_ok=True)
            if os.path.isdir("/dev/fd"):
                self._file = _PipedFile(rr, save)
            else:  # no /dev/fd to hand rerun a pipe: its own file sink (a failure mid-stream goes unnoticed)
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

    @property
    def failure(self) -> RecordingError | None:
        """The write of the recording that failed (also the one :meth:`log` raised), or None."""
        if self._reported is None and self._file is not None and self._file.error is not None:
            self._reported = RecordingError(self._file.error, self._file.path, self._file.written, None)
        return self._reported

    def log(self, index: int, frame: Frame, estimate: Any, latency: float) -> None:
        """Log one estimated frame; :class:`RecordingError` once the recording's file refused a write."""
        if self._file is not None and self._file.error is not None:
            if self._reported is None:
                self._reported = RecordingError(self._file.error, self._file.path, self._file.written, index)
            raise self._reported
        self._log(index, frame, estimate, latency)

    def _log(self, index: int, frame: Frame, estimate: Any, latency: float) -> None:
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
        """End the recording (a failed write shows in :attr:`failure`; nothing is raised here)."""
        self.rr.disconnect()
        if self._file is not None:
            self._file.close()


__all__ = ["RerunView", "RecordingError", "PATCH_HALF"]
