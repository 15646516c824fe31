"""Benchmark: speed and accuracy of the recovery methods side by side, on the same frames, in one process.

Concept
-------
Each method gets one warm-up estimate (excluded from the timings: first calls pay for imports,
allocations and caches; the slow paper mode is the exception, see :data:`DEFAULT_RUNS`), then every frame is recovered with a single ``estimate`` call and
timed (``time.perf_counter``). Reported per method: per-frame latency (median, p95; ms), throughput
(frames per second of recovery time), and against ground truth the mean angular error (degrees), mean
linear error (mm) and mean point error (mm) from :mod:`place_safe.evaluation.metrics`, plus how many frames gave
no plane. The slow ``paper`` mode of the differentiable method runs on ``paper_frames`` frames spread
evenly over the set only, and the fast mode is scored again on exactly those frames (``diff-fast (same)``) so the
accuracy comparison is on the same frames; the ratio of the paper mode's median latency to the
``fast`` mode's is the speed ratio.

Memory: :func:`peak_rss_bytes` is this process's peak resident set size (``getrusage``);
:func:`measure_file_rss` writes an N-frame file and runs ``place-safe recover`` over it in a fresh
process, reporting that child's peak RSS, so it measures streaming recovery alone.
"""

from __future__ import annotations

import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from place_safe.calibration import mark
from place_safe.sensor.frame import Frame
from place_safe.evaluation.metrics import angular_error, linear_error, point_error
from place_safe.recovery import make_estimator
from place_safe.io.frame_file import write_frames
from place_safe.calibration import uncalibrated_reason

#: Methods of the benchmark: (label, CLI method, estimator options), in the order they run. The paper
#: mode runs after the fast mode, so torch is already warm, and skips its own warm-up estimate: its
#: first-call overhead (well under a second) is small against its seconds per frame.
DEFAULT_RUNS: tuple[tuple[str, str, dict], ...] = (
    ("diff-fast", "diff", {"mode": "fast"}),
    ("diff-paper", "diff", {"mode": "paper"}),
    ("peak", "peak", {}),
)


@dataclass
class MethodResult:
    """Timings (s) and errors of one method over its frames."""

    label: str
    frames: int = 0
    latencies: list[float] = field(default_factory=list)
    angular_deg: list[float] = field(default_factory=list)
    linear_mm: list[float] = field(default_factory=list)
    point_mm: list[float] = field(default_factory=list)
    failures: int = 0
    error: str | None = None   # why the method could not run at all
    calibrated: bool = True    # False: the method ran on built-in constants (the row says so)

    @property
    def latency_median(self) -> float | None:
        return float(np.median(self.latencies)) if self.latencies else None

    @property
    def latency_p95(self) -> float | None:
        return float(np.percentile(self.latencies, 95)) if self.latencies else None

    @property
    def fps(self) -> float | None:
        total = float(np.sum(self.latencies))
        return len(self.latencies) / total if total > 0 else None

    @staticmethod
    def _mean(v: list[float]) -> float | None:
        return float(np.mean(v)) if v else None

    def to_dict(self) -> dict:
        def r(v: float | None, k: int = 3) -> float | None:
            return None if v is None else round(v, k)

        return {"label": self.label, "frames": self.frames, "failures": self.failures, "error": self.error,
                "latency_ms": {"median": r(None if self.latency_median is None else self.latency_median * 1e3),
                               "p95": r(None if self.latency_p95 is None else self.latency_p95 * 1e3)},
                "fps": r(self.fps), "angular_deg": r(self._mean(self.angular_deg), 4),
                "linear_mm": r(self._mean(self.linear_mm)), "point_mm": r(self._mean(self.point_mm)),
                "calibrated": self.calibrated}


@dataclass
class BenchReport:
    """All methods' results plus memory figures."""

    results: list[MethodResult]
    frames: int
    source: str
    peak_rss_bytes: int
    file_rss: dict | None = None

    def result(self, label: str) -> MethodResult | None:
        return next((r for r in self.results if r.label == label), None)

    @property
    def speed_ratio(self) -> float | None:
        """Median latency of diff-paper over diff-fast (how many times faster the fast solver is)."""
        p, f = self.result("diff-paper"), self.result("diff-fast")
        if p and f and p.latency_median and f.latency_median:
            return p.latency_median / f.latency_median
        return None

    def to_dict(self) -> dict:
        return {"source": self.source, "frames": self.frames, "methods": [r.to_dict() for r in self.results],
                "speed_ratio_paper_over_fast": None if self.speed_ratio is None else round(self.speed_ratio, 2),
                "peak_rss_mb": round(self.peak_rss_bytes / 2**20, 1), "file_rss": self.file_rss}

    def table(self) -> str:
        def f(v: float | None, fmt: str) -> str:
            return "-" if v is None else format(v, fmt)

        head = (f"{'method':<18} {'frames':>6} {'no plane':>8} {'median ms':>10} {'p95 ms':>9} {'frames/s':>9} "
                f"{'angular deg':>11} {'linear mm':>9} {'point mm':>9}")
        lines = [f"benchmark on {self.frames} frames from {self.source} (warm-up excluded)", head,
                 "-" * len(head)]
        for r in self.results:
            if r.error:
                lines.append(f"{r.label:<18} not run: {r.error}")
                continue
            lines.append(mark(
                f"{r.label:<18} {r.frames:>6d} {r.failures:>8d} "
                f"{f(None if r.latency_median is None else r.latency_median * 1e3, '10.2f'):>10} "
                f"{f(None if r.latency_p95 is None else r.latency_p95 * 1e3, '9.2f'):>9} {f(r.fps, '9.2f'):>9} "
                f"{f(r._mean(r.angular_deg), '11.3f'):>11} {f(r._mean(r.linear_mm), '9.2f'):>9} "
                f"{f(r._mean(r.point_mm), '9.2f'):>9}", r.calibrated))
        if self.speed_ratio is not None:
            lines.append(f"speed ratio diff paper / fast (median latency): {self.speed_ratio:.1f}x")
        lines.append(f"peak RSS of this process: {self.peak_rss_bytes / 2**20:.0f} MB")
        if self.file_rss and "error" in self.file_rss:
            lines.append(f"peak RSS of recover over a file: not measured ({self.file_rss['error']})")
        elif self.file_rss:
            fr = self.file_rss
            lines.append(f"peak RSS of `place-safe recover --method {fr['method']}` over a {fr['frames']}-frame file "
                         f"({fr['file_mb']:.1f} MB): {fr['peak_rss_mb']:.0f} MB "
                         f"(over a {fr['baseline_frames']}-frame file: {fr['baseline_rss_mb']:.0f} MB; "
                         f"{fr['seconds']:.1f} s)")
        return "\n".join(lines)


def peak_rss_bytes() -> int:
    """Peak resident set size of this process (bytes; Linux reports KiB, macOS bytes)."""
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(rss if sys.platform == "darwin" else rss * 1024)


def _errors(est_plane, true_plane) -> tuple[float, float, float]:
    return (float(np.degrees(angular_error(est_plane, true_plane))), float(linear_error(est_plane, true_plane)) * 1e3,
            float(point_error(est_plane, true_plane)) * 1e3)


def bench_method(label: str, estimator, frames: Sequence[Frame], warmup: bool = True,
                 progress: bool = False) -> MethodResult:
    """Time ``estimator`` frame by frame over ``frames`` and score it against their ground truth."""
    res = MethodResult(label, frames=len(frames))
    if not frames:
        return res
    if warmup:
        estimator.estimate(frames[0])
    it = frames
    if progress:
        from tqdm import tqdm
        it = tqdm(frames, desc=label, unit="frame", file=sys.stderr, leave=False, disable=None)  # None: TTY only
    for frame in it:
        t0 = time.perf_counter()
        est = estimator.estimate(frame)
        res.latencies.append(time.perf_counter() - t0)
        if not est.ok:
            res.failures += 1
            continue
        if frame.truth is not None:
            a, lin, pt = _errors(est.plane, frame.truth)
            res.angular_deg.append(a)
            res.linear_mm.append(lin)
            res.point_mm.append(pt)
    return res


def _spread(frames: Sequence[Frame], n: int) -> list[Frame]:
    """``n`` frames spread evenly over the sequence (all of them if it is shorter)."""
    if n >= len(frames):
        return list(frames)
    return [frames[i] for i in np.round(np.linspace(0, len(frames) - 1, n)).astype(int)] if n > 0 else []


#: The defaults of :func:`run_bench`'s frames of the diff-paper run and of :func:`measure_file_rss`'s method
#: (``bench recovery`` fills its options not given with them).
PAPER_FRAMES = 5
MEMORY_METHOD = "diff"


def run_bench(frames: Sequence[Frame], calibration=None, paper_frames: int = PAPER_FRAMES,
              runs: Sequence[tuple[str, str, dict]] = DEFAULT_RUNS, source: str = "frames",
              progress: bool = False) -> BenchReport:
    """Benchmark each run (label, method, options) on ``frames`` (``diff-paper``: ``paper_frames`` spread evenly)."""

    results = []
    for label, method, options in runs:
        subset = _spread(frames, paper_frames) if options.get("mode") == "paper" else list(frames)
        if not subset:
            continue
        try:
            est = make_estimator(method, calibration, **options)
        except ImportError as exc:
            results.append(MethodResult(label, error=f"not available ({exc})"))
            continue
        results.append(bench_method(label, est, subset, warmup=options.get("mode") != "paper", progress=progress))
        results[-1].calibrated = uncalibrated_reason(method, calibration) is None
    # accuracy on the same frames: the fast solver again on exactly the paper mode's frames
    labels = [r.label for r in results]
    if "diff-paper" in labels and "diff-fast" in labels and 0 < paper_frames < len(frames):
        est = make_estimator("diff", calibration, mode="fast")
        same = bench_method("diff-fast (same)", est, _spread(frames, paper_frames), progress=progress)
        same.calibrated = uncalibrated_reason("diff", calibration) is None
        results.insert(labels.index("diff-paper") + 1, same)
    return BenchReport(results, len(frames), source, peak_rss_bytes())


#: A small launcher that runs its arguments as a grandchild and prints the grandchild's peak RSS (``ru_maxrss``, the
#: platform's unit) as its last line on stderr, with the grandchild's exit status as its own. Why not the child
#: itself: Linux counts in a process's ``ru_maxrss`` the memory it had between fork and exec, the parent's, so a
#: measurement taken from a large process (a test worker with torch loaded: 1.3 GB) read the parent's size, and two
#: such measurements differed by what the parent had grown in between; the grandchild is forked from the launcher's
#: few megabytes.
_RSS_LAUNCHER = (
    "import os, sys\n"
    "pid = os.fork()\n"
    "if pid == 0:\n"
    "    os.execv(sys.argv[1], sys.argv[1:])\n"
    "_, status, usage = os.wait4(pid, 0)\n"
    "sys.stderr.write('\\nmaxrss %d\\n' % usage.ru_maxrss)\n"
    "sys.exit(os.waitstatus_to_exitcode(status) & 255)\n")


def _child_rss(cmd: list[str], stdout_path: Path) -> tuple[int, float, int]:
    """Run ``cmd`` (its first item an executable's path) in a fresh process; return (exit status, wall seconds, that
    process's peak RSS in bytes, measured from a small launcher: :data:`_RSS_LAUNCHER`)."""
    t0 = time.perf_counter()
    with open(stdout_path, "wb") as out:
        proc = subprocess.run([sys.executable, "-c", _RSS_LAUNCHER, *cmd], stdout=out, stderr=subprocess.PIPE)
    lines = proc.stderr.decode(errors="replace").strip().splitlines()
    rss = int(lines.pop().split()[1]) if lines and lines[-1].startswith("maxrss ") else 0
    rss = rss if sys.platform == "darwin" else rss * 1024
    if proc.returncode != 0:
        last = ([ln for ln in lines if ln.strip()] or ["(no message)"])[-1]
        raise RuntimeError(f"`{' '.join(cmd[2:])}` exited with {proc.returncode}: {last}")
    return proc.returncode, time.perf_counter() - t0, int(rss)


def write_synthetic_file(path: Path, n: int, distinct: int = 16, seed: int = 0) -> int:
    """Write ``n`` synthetic frames (``distinct`` rendered ones repeated) as a JSON list; returns bytes."""
    from place_safe.evaluation.synthetic import make_frames

    base = make_frames(min(distinct, n), seed=seed)
    write_frames(path, (base[i % len(base)] for i in range(n)))
    return path.stat().st_size


def measure_file_rss(n: int, method: str = MEMORY_METHOD, calibration: str | Path | None = None,
                     baseline_frames: int = 16, workdir: str | Path | None = None) -> dict:
    """Peak RSS of ``place-safe recover --jsonl`` over an ``n``-frame synthetic file, run in a fresh process.

    Also measures a ``baseline_frames``-frame file the same way: if recovery streams, both figures are
    about the same (the interpreter, numpy and torch dominate). Both files repeat the same 16 rendered
    frames, so with ``baseline_frames >= 16`` both runs exercise the same code paths (lazy imports).
    """
    with tempfile.TemporaryDirectory(dir=workdir) as tmp:
        tmpd = Path(tmp)
        out: dict = {"method": method, "frames": n, "baseline_frames": baseline_frames}
        for key, count in (("baseline", baseline_frames), ("main", n)):
            path = tmpd / f"frames_{count}.json"
            size = write_synthetic_file(path, count)
            cmd = [sys.executable, "-m", "place_safe.cli.app", "recover", str(path), "--method", method, "--jsonl",
                   "--quiet"]
            if calibration is not None:
                cmd += ["--calibration", str(calibration)]
            _, seconds, rss = _child_rss(cmd, tmpd / "out.jsonl")
            lines = sum(1 for _ in open(tmpd / "out.jsonl"))
            if lines != count:
                raise RuntimeError(f"recover wrote {lines} lines for {count} frames")
            if key == "main":
                out.update(file_mb=size / 2**20, peak_rss_mb=rss / 2**20, seconds=seconds)
            else:
                out.update(baseline_rss_mb=rss / 2**20)
    return out


def report_json(report: BenchReport, path: str | Path) -> None:
    Path(path).write_text(json.dumps(report.to_dict(), indent=2) + "\n")


__all__ = ["BenchReport", "MethodResult", "DEFAULT_RUNS", "bench_method", "run_bench", "peak_rss_bytes",
           "measure_file_rss", "measure_recover_latency", "write_synthetic_file", "report_json"]


def measure_recover_latency(path: str | Path, method: str = "diff", calibration: str | Path | None = None,
                            batch: int = 1) -> dict:
    """Per-frame wall time of ``place-safe recover --jsonl`` over a frame file, measured from outside.

    Runs ``recover`` in a fresh process and timestamps each JSON line as it arrives on the pipe; the
    gap between consecutive lines is a frame's wall time as a caller sees it (reading and parsing the
    frame, recovery, writing its line). The first line's gap (interpreter start, imports, warm-up) is
    reported separately. With ``batch`` > 1 lines arrive in bursts, so per-frame figures are only
    meaningful with ``batch = 1`` (the default here); the mean is total / frames either way.
    """
    cmd = [sys.executable, "-m", "place_safe.cli.app", "recover", str(path), "--method", method, "--jsonl",
           "--quiet", "--batch", str(batch)]
    if calibration is not None:
        cmd += ["--calibration", str(calibration)]
    stamps, lines, used = [], [], {}
    # stderr to a file, not a pipe: a child that wrote more than a pipe holds there while this reads its stdout to
    # the end would wait for it forever
    with tempfile.TemporaryFile() as err_file:
        t0 = time.perf_counter()
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err_file)
        assert proc.stdout is not None
        for line in proc.stdout:  # only the time stamp while recover runs: on a busy machine the parsing would
            stamps.append(time.perf_counter())  # take turns with recover for a core and lengthen its gaps
            lines.append(line)
        proc.wait()
        err_file.seek(0)
        err = err_file.read().decode(errors="replace")
    if proc.returncode != 0:
        last = (err.strip().splitlines() or ["(no message)"])[-1]
        raise RuntimeError(f"recover exited with {proc.returncode}: {last}")
    for line in lines:
        m = json.loads(line).get("method_used") or "no plane"  # a frame without a plane (too close, no return)
        used[m] = used.get(m, 0) + 1
    if len(stamps) < 2:
        raise RuntimeError("recover wrote fewer than 2 lines; need 2 or more frames")
    gaps = np.diff(np.array(stamps)) * 1e3
    return {"method": method, "frames": len(stamps), "first_line_ms": round((stamps[0] - t0) * 1e3, 1),
            "median_ms": round(float(np.median(gaps)), 2), "p95_ms": round(float(np.percentile(gaps, 95)), 2),
            "mean_ms": round(float(gaps.mean()), 2), "method_used": {str(k): v for k, v in used.items()}}
