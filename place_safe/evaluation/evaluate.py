"""Evaluation of plane-recovery methods on frames with ground truth (the paper's Table I).

:func:`evaluate` runs each method (built by :func:`place_safe.recovery.make_estimator`) on every
frame that has a ground-truth plane and collects the paper's errors (:mod:`place_safe.evaluation.metrics`):
angular (reported in degrees), linear and point (reported in millimetres), plus failures (frames
without a plane) and the mean recovery time per frame. Methods that cannot be built (e.g. an
optional method whose module is missing) are listed as unavailable with the reason. A frame that repeats an earlier
one exactly (:func:`place_safe.sensor.frame.without_repeats`: the same histograms and on-sensor distances) is one
measurement and counts once, as in ``calibrate``: the repeats are left out, counted among the skipped frames, and
:attr:`EvaluationReport.repeats_note` says so in one line (given twice, a sweep's means, percentiles and NEES weighted
every frame it repeated double).
With ``out_dir``, PNG plots (matplotlib, Agg backend) show the errors against the angle of incidence
and the distance, and the recovered albedo against distance for methods that return one.
"""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from place_safe.calibration import mark
from place_safe.evaluation.metrics import angular_errors, linear_errors, nees, point_errors, summarise
from place_safe.sensor.frame import Frame, without_repeats
from place_safe.recovery import make_estimator
from place_safe.calibration import uncalibrated_reason
from place_safe.recovery.too_close import TOO_CLOSE_REASON


#: Methods that may return another method's plane: their fallback rate is always printed (0 % too).
FALLBACK_METHODS = ("diff",)


@dataclass
class MethodResult:
    """Per-frame results of one method over the evaluated frames (NaN where it gave no plane)."""

    method: str
    angular: np.ndarray  # rad
    linear: np.ndarray  # m
    point: np.ndarray  # m
    albedo: np.ndarray
    seconds: np.ndarray
    reasons: list[str | None]
    nees: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per frame, per degree of freedom (NaN: none)
    used: list[str | None] = field(default_factory=list)  # method_used per frame

    @property
    def failures(self) -> int:
        return int(np.sum(~np.isfinite(self.point)))

    @property
    def too_close(self) -> int:
        """Frames without a plane because they were too close to read (:mod:`place_safe.recovery.too_close`)."""

        return sum(1 for r in self.reasons if isinstance(r, str) and r.startswith(TOO_CLOSE_REASON))

    @property
    def fallback_rate(self) -> float | None:
        """Fraction of the frames with a plane on which the method returned another method's plane alone (diff's
        fallback to peak; a blend of its own with another's, ``diff+peak``, is not one); None when it returned
        none."""
        used = [u for u in self.used if u is not None]
        return sum(u != self.method and not u.startswith(self.method + "+") for u in used) / len(used) if used else None

    def albedo_spread(self) -> dict[str, float] | None:
        """Mean, standard deviation and coefficient of variation (per cent) of the recovered albedos, or None
        without any. Over frames of one surface (the real sweep: one table) the CV says how well the method
        reads one albedo over distance and angle."""
        a = self.albedo[np.isfinite(self.albedo)]
        if a.size == 0:
            return None
        mean, std = float(a.mean()), float(a.std(ddof=1)) if a.size > 1 else 0.0
        return {"mean": mean, "std": std, "cv_percent": 100.0 * std / mean if mean > 0 else float("nan"),
                "count": int(a.size)}

    def summary(self) -> dict[str, Any]:
        return {"angular_deg": {k: (v * 180 / np.pi if k != "count" else v) for k, v in summarise(self.angular).items()},
                "linear_mm": {k: (v * 1e3 if k != "count" else v) for k, v in summarise(self.linear).items()},
                "point_mm": {k: (v * 1e3 if k != "count" else v) for k, v in summarise(self.point).items()},
                "failures": self.failures, "too_close": self.too_close, "frames": len(self.point),
                "nees_per_dof": ({"mean": float(np.nanmean(self.nees)), "median": float(np.nanmedian(self.nees)),
                                  "count": int(np.isfinite(self.nees).sum())} if np.isfinite(self.nees).any() else None),
                "method_used": {k: self.used.count(k) for k in sorted({u for u in self.used if u is not None})},
                "fallback_rate": self.fallback_rate,
                "albedo": self.albedo_spread(),
                "ms_per_frame": float(np.mean(self.seconds) * 1e3) if len(self.seconds) else float("nan")}


@dataclass
class EvaluationReport:
    """Results of :func:`evaluate`: per-method results, unavailable methods, frame geometry."""

    results: dict[str, MethodResult] = field(default_factory=dict)
    unavailable: dict[str, str] = field(default_factory=dict)
    z0: np.ndarray = field(default_factory=lambda: np.zeros(0))  # true axis distance per frame (m)
    theta: np.ndarray = field(default_factory=lambda: np.zeros(0))  # true angle of incidence (rad)
    skipped: int = 0  # frames without ground truth, or whose ground truth is not a plane (given or skipped before)
    #: every frame left out, by reason (those :func:`evaluate` was given without ground truth, and what its caller
    #: skipped before: ``evaluate``'s file reader counts unreadable frames, frames without or with a broken ground truth
    #: and frames outside the distance limits)
    skipped_reasons: dict[str, int] = field(default_factory=dict)
    plots: list[str] = field(default_factory=list)
    #: methods that ran on built-in constants, not on the calibration (their rows say so)
    uncalibrated: set[str] = field(default_factory=set)
    #: one line saying which frames were left out as exact repeats of an earlier one (None: none was)
    repeats_note: str | None = None

    def table(self) -> str:
        """A text table like the paper's Table I (mean / median / p95 per error)."""
        head = (f"{'method':<18} {'angular (deg)':^23} {'linear (mm)':^23} {'point (mm)':^23} {'fail':>5} {'ms':>8}\n"
                f"{'':<18} {'mean':>7} {'median':>7} {'p95':>7} {'mean':>7} {'median':>7} {'p95':>7} "
                f"{'mean':>7} {'median':>7} {'p95':>7} {'':>5} {'':>8}")
        lines = [head, "-" * len(head.splitlines()[1])]
        for name, res in self.results.items():
            s = res.summary()
            cells = []
            for key in ("angular_deg", "linear_mm", "point_mm"):
                cells += [f"{s[key][k]:7.2f}" if math.isfinite(s[key][k]) else f"{'-':>7}"  # every frame failed
                          for k in ("mean", "median", "p95")]
            lines.append(mark(f"{name:<18} " + " ".join(cells) + f" {s['failures']:>5d} {s['ms_per_frame']:8.3f}",
                              name not in self.uncalibrated))
        for name, res in self.results.items():
            s = res.summary()
            notes = []
            if s["nees_per_dof"]:
                notes.append(f"NEES per dof mean {s['nees_per_dof']['mean']:.2f} (median {s['nees_per_dof']['median']:.2f})")
            if s["method_used"] and (set(s["method_used"]) != {name} or name in FALLBACK_METHODS):  # 0 % said too
                notes.append("used " + ", ".join(f"{k} {v}" for k, v in s["method_used"].items())
                             + f" (fallback rate {100 * s['fallback_rate']:.0f} %)")
            if s["too_close"]:
                notes.append(f"{s['too_close']} of the failures too close to read (the return overlaps the internal "
                             "return)")
            if s["albedo"] is not None:
                notes.append(f"albedo {s['albedo']['mean']:.4g}, CV {s['albedo']['cv_percent']:.1f} %")
            if notes:
                lines.append(mark(f"{name:<18} " + "; ".join(notes), name not in self.uncalibrated))
        for name, why in self.unavailable.items():
            lines.append(f"{name:<18} unavailable: {why}")
        lines.append(f"({len(self.z0)} frames with ground truth"
                     + (f"; {sum(self.skipped_reasons.values())} skipped: "
                        + ", ".join(f"{n} {why}" for why, n in self.skipped_reasons.items()) + ")"
                        if self.skipped_reasons else ")"))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        return {"frames": int(len(self.z0)), "skipped_without_truth": self.skipped,
                "skipped": dict(self.skipped_reasons),
                "methods": {k: {**v.summary(), "calibrated": k not in self.uncalibrated}
                            for k, v in self.results.items()},
                "unavailable": dict(self.unavailable), "plots": list(self.plots)}


#: Reasons of skipped frames (:attr:`EvaluationReport.skipped_reasons`) that count as without ground truth.
WITHOUT_TRUTH = ("no ground truth", "ground truth not a plane")
#: The reason (:attr:`EvaluationReport.skipped_reasons`) of frames left out as exact repeats of an earlier one.
REPEATED = "repeats of an earlier frame"


def evaluate(frames: Sequence[Frame], calibration: Any = None, methods: Sequence[str] = ("peak",),
             out_dir: str | Path | None = None, progress: bool = True,
             estimator_options: dict[str, dict] | None = None,
             skipped: dict[str, int] | None = None) -> EvaluationReport:
    """Run ``methods`` on the frames with ground truth; see the module docstring.

    ``estimator_options`` maps a method name to keyword options for its estimator
    (e.g. ``{"diff": {"mode": "paper"}}``). ``skipped``: frames the caller left out before, by reason (the report
    counts them with the frames given without ground truth: ``skipped_without_truth`` those of :data:`WITHOUT_TRUTH`).
    """
    from tqdm import tqdm

    use = [f for f in frames if f.truth is not None]
    reasons = {str(k): int(v) for k, v in (skipped or {}).items() if int(v) > 0}
    own = {"ground truth not a plane": sum(1 for f in frames if f.truth is None and getattr(f, "truth_error", None))}
    own["no ground truth"] = len(frames) - len(use) - own["ground truth not a plane"]
    with_truth = len(use)
    use, repeats_note, _ = without_repeats(use, "counting the frames with ground truth from 0")
    own[REPEATED] = with_truth - len(use)  # one measurement, counted once (as calibrate does)
    for why, n in own.items():
        if n:
            reasons[why] = reasons.get(why, 0) + n
    report = EvaluationReport(skipped=sum(reasons.get(k, 0) for k in WITHOUT_TRUTH), skipped_reasons=reasons,
                              repeats_note=repeats_note)
    report.z0 = np.array([f.truth.z0 for f in use])
    report.theta = np.array([f.truth.theta for f in use])
    tn = np.array([f.truth.normal for f in use]).reshape(-1, 3)
    td = np.array([f.truth.offset for f in use])
    options = estimator_options or {}
    for method in methods:
        try:
            est = make_estimator(method, calibration, **options.get(method, {}))
        except Exception as exc:  # noqa: BLE001 - any failure to build a method makes it unavailable
            report.unavailable[method] = f"{type(exc).__name__}: {exc}"
            continue
        n = np.full((len(use), 3), np.nan)
        d = np.full(len(use), np.nan)
        albedo = np.full(len(use), np.nan)
        secs = np.zeros(len(use))
        reasons: list[str | None] = []
        ests = []
        for i, f in enumerate(tqdm(use, desc=method, unit="frame", disable=None if progress else True, leave=False,
                                   file=sys.stderr)):
            e = est.estimate(f)
            ests.append(e)
            secs[i] = e.seconds
            reasons.append(e.reason)
            if e.plane is not None:
                n[i], d[i] = e.plane.normal, e.plane.offset
            if e.albedo is not None:
                albedo[i] = e.albedo
        ok = np.isfinite(d)
        ang = np.full(len(use), np.nan)
        lin = np.full(len(use), np.nan)
        pt = np.full(len(use), np.nan)
        if ok.any():
            ang[ok] = angular_errors(n[ok], tn[ok])
            lin[ok] = linear_errors(n[ok], d[ok], tn[ok], td[ok])
            pt[ok] = point_errors(n[ok], d[ok], tn[ok], td[ok])
        if uncalibrated_reason(method, calibration) is not None:
            report.uncalibrated.add(method)
        report.results[method] = MethodResult(method, ang, lin, pt, albedo, secs, reasons,
                                              nees(ests, [f.truth for f in use]), [e.method_used for e in ests])
    if out_dir is not None and report.results:
        report.plots = plot_report(report, out_dir)
    return report


#: Plots: errors below this are drawn at it (a log axis has no zero); medians over this many bins of x.
PLOT_FLOOR = 1e-3
PLOT_BINS = 8


def _binned_medians(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Median of the finite ``y`` in each bin of ``x`` between ``edges`` (bins without data left out)."""
    centres, medians = [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        m = (x >= lo) & ((x <= hi) if hi == edges[-1] else (x < hi)) & np.isfinite(y)
        if m.any():
            centres.append(0.5 * (lo + hi))
            medians.append(float(np.median(y[m])))
    return np.array(centres), np.array(medians)


def plot_report(report: EvaluationReport, out_dir: str | Path) -> list[str]:
    """Write the error and albedo plots as PNG files into ``out_dir``; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    errors = (("angular", 180 / np.pi, "angular error (deg)"), ("linear", 1e3, "linear error (mm)"),
              ("point", 1e3, "point error (mm)"))
    for xname, x, xlabel in (("angle", np.degrees(report.theta), "angle of incidence (deg)"),
                             ("distance", report.z0 * 1e3, "distance z0 (mm)")):
        fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
        edges = np.unique(np.quantile(x[np.isfinite(x)], np.linspace(0.0, 1.0, PLOT_BINS + 1))) if np.isfinite(x).any() \
            else np.zeros(0)
        for ax, (key, scale, label) in zip(axes, errors):
            for name, res in report.results.items():
                y = getattr(res, key) * scale
                dots = ax.scatter(x, np.maximum(y, PLOT_FLOOR), s=8, alpha=0.45)
                centres, medians = _binned_medians(x, y, edges)
                ax.plot(centres, np.maximum(medians, PLOT_FLOOR), "-o", ms=4, color=dots.get_facecolor()[0][:3],
                        label=f"{name} (median per bin)")
            ax.set_xlabel(xlabel)
            ax.set_ylabel(label)
            ax.set_yscale("log")
            ax.grid(True, which="both", alpha=0.3)
        axes[0].legend(fontsize=8)
        fig.tight_layout()
        path = out / f"error_vs_{xname}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(str(path))
    with_albedo = {k: r for k, r in report.results.items() if np.isfinite(r.albedo).any()}
    if with_albedo:
        fig, ax = plt.subplots(figsize=(6, 4.2))
        for name, res in with_albedo.items():
            ax.scatter(report.z0 * 1e3, res.albedo, s=10, label=name)
        ax.set_xlabel("distance z0 (mm)")
        ax.set_ylabel("recovered albedo")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out / "albedo_vs_distance.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(str(path))
    return written


__all__ = ["EvaluationReport", "MethodResult", "evaluate", "plot_report"]
