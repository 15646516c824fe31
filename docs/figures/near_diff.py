"""Diff's own plane against peak's at 2-5 cm (and 1.5-2 cm, 5-40 cm as a check), held out, from one calibration.

Simulated mismatched units (``MismatchConfig`` seeds), as ``near_nees.py`` makes them: each calibrated by
``calibrate --method diff`` on its own level sweep (100 frames 5 mm-40 cm) and read on a second sweep (80 frames)
plus a dense near sweep (40 frames 19-51 mm); ``--close`` adds 20 frames 12-21 mm, ``--tilted`` 30 frames 2-5 cm
tilted 0-20 deg. "diff own" is diff with its fallback limits null in a copy of the calibration (docs/results.md,
step 6); peak is read from the same calibration. A variant lowers the forward fit's ``min_distance`` (the
monkeypatch of step 7's commands), ``+rc`` lowers the plane correction's and the model error's as well, ``+unit``
fits the cover-glass return, crosstalk grid and echo too, ``+int`` starts the forward fit with the soft binning
integrated over each bin (``ForwardParams.soft_bin_integrated`` 1). Bands 1.5-2, 2-5 (2-3.5, 3.5-5) and 5-40 cm; for the level
frames also the share of diff's 2-5 cm slope error (times z0) that one sinusoid in z0 of period 0.5, 1 and 2 bins explains.

    python docs/figures/near_diff.py --units 11 21 --variants default ff0.02 ff0.02+rc --data DIR --cals DIR
    python docs/figures/near_diff.py --real --variants default ff0.02+rc --cals DIR   # the real halves
    python docs/figures/near_diff.py ... --frames      # each frame closer than 5 cm: depth, both errors, residual

Calibrations are kept in ``--cals`` (made when missing). The NEES interval is near_nees.py's.
"""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from near_nees import interval  # noqa: E402  (the NEES figure with its 90 % interval)

from place_safe.calibration import Calibration, fit
from place_safe.calibration import forward_fit as ff, model_error, plane_correction
from place_safe.evaluation.metrics import angular_error, nees
from place_safe.io.frame_file import load_frames, write_frames
from place_safe.recovery import make_estimator
from place_safe.recovery.forward import ForwardParams
from pydantic import Field

ROOT = Path(__file__).resolve().parents[2]
SWEEP = ROOT / "tests" / "data" / "tmf8820_ur5_sweep.json"
BANDS = (("1.5-2 cm", 0.015, 0.02), ("2-5 cm", 0.02, 0.05), ("2-3.5 cm", 0.02, 0.035), ("3.5-5 cm", 0.035, 0.05),
         ("5-40 cm", 0.05, 0.40))
ORIGINAL = (fit.fit_forward, fit.fit_range_correction, fit.select_model_error, fit.reconsider_geometry)


class IntegratedSoftBin(ForwardParams):
    """The forward fit's starting parameters with the soft binning integrated over each bin (``+int``)."""

    soft_bin_integrated: float = Field(1.0, ge=0.0, le=1.0)


def calibrate(frames, variant: str) -> Calibration:
    """``calibrate --method diff`` on ``frames``; ``variant``: ``default``, ``ffD`` (the forward fit from D m),
    ``ffD+rc`` (and the plane correction and model error from D m); ``+unit`` adds the unit terms (crosstalk grid,
    cover-glass return, echo: ``forward_fit.UNIT_TERMS``) to the forward fit."""
    fit.fit_forward, fit.fit_range_correction, fit.select_model_error, fit.reconsider_geometry = ORIGINAL
    if "+int" in variant:  # the soft binning integrated over each bin from the start of the forward fit (step 8)
        ff.ForwardParams = IntegratedSoftBin
        variant = variant.replace("+int", "")
    if variant != "default":
        d = float(variant[2:].split("+")[0])
        extra = {"fitted": {**ff.FITTED, **ff.UNIT_TERMS}} if "+unit" in variant else {}
        fit.fit_forward = lambda frames, **kw: ff.fit_forward(frames, **{**kw, "min_distance": d, **extra})
        # the variant's own fit, kept: calibrate's second fit (the zones' time scales) would not see the variant
        fit.reconsider_geometry = lambda frames, params, report, **kw: (params, report)
        if "+rc" in variant:
            fit.fit_range_correction = lambda *a, **kw: plane_correction.fit_range_correction(*a, **{**kw, "min_distance": d})
            fit.select_model_error = lambda *a, **kw: model_error.select_model_error(*a, **{**kw, "min_distance": d})
    cal = Calibration()
    try:
        fit.fit_method(cal, frames, "diff", progress=False, log=None)
    finally:
        fit.fit_forward, fit.fit_range_correction, fit.select_model_error, fit.reconsider_geometry = ORIGINAL
        ff.ForwardParams = ForwardParams
    return cal


def own(cal: Calibration) -> Calibration:
    """A copy of ``cal`` with diff's fallback limits null: diff's own plane wherever it solves."""
    return cal.without_fallback()


def rows_of(est, frames) -> list[dict]:
    out = []
    for f, e in zip(frames, est.estimate_many(frames)):
        v = float(nees([e], [f.truth])[0]) if e.ok else math.nan
        ds = np.subtract(e.plane.slopes[:2], f.truth.slopes[:2]) if e.ok else None
        out.append({"depth": f.truth.z0, "plane": e.ok, "used": e.method_used, "res": e.residual, "dslopes": ds,
                    "deg": math.degrees(angular_error(e.plane, f.truth)) if e.ok else None,
                    "nees": v if math.isfinite(v) else None})
    return out


def band_line(name: str, rows: list[dict], lo: float, hi: float) -> str | None:
    r = [x for x in rows if lo <= x["depth"] < hi]
    if not r:
        return None
    p = [x for x in r if x["plane"]]
    deg = [x["deg"] for x in p]
    own_n = sum(x["used"] in ("diff", "diff+peak") for x in p)  # its own plane, or its blend with peak's
    acc = f"mean {np.mean(deg):5.2f} max {np.max(deg):6.2f} deg" if deg else "no planes"
    return (f"  {name:9s} n {len(r):3d} no plane {len(r) - len(p):2d} own {own_n:3d}  {acc}  "
            f"NEES/dof {interval([x['nees'] for x in p])}")


def phase_share(rows: list[dict], period: float) -> tuple[float, float]:
    """Per slope axis, the share of the 2-5 cm slope errors (times z0: a range error across the zones) that one
    sinusoid of ``period`` (m) in z0 explains: a timing error that repeats with the return's sub-bin position."""
    r = [x for x in rows if 0.02 <= x["depth"] < 0.05 and x["dslopes"] is not None]
    z = np.array([x["depth"] for x in r])
    design = np.c_[np.cos(2 * np.pi * z / period), np.sin(2 * np.pi * z / period), np.ones_like(z)]
    out = []
    for k in range(2):
        y = np.array([x["dslopes"][k] for x in r]) * z
        fit_ = design @ np.linalg.lstsq(design, y, rcond=None)[0]
        out.append(1.0 - float(np.sum((y - fit_) ** 2) / max(np.sum((y - y.mean()) ** 2), 1e-300)))
    return out[0], out[1]


def report(title: str, cal: Calibration, sets: dict, show: bool) -> None:
    print(title, flush=True)
    peak = make_estimator("peak", cal)
    diff = make_estimator("diff", own(cal))
    for set_name, frames in sets.items():
        rp, rd = rows_of(peak, frames), rows_of(diff, frames)
        for band, lo, hi in BANDS:
            a, b = band_line("peak", rp, lo, hi), band_line("diff own", rd, lo, hi)
            if a:
                print(f" {set_name} {band}\n{a}\n{b}", flush=True)
        if set_name == "level" and sum(0.02 <= x["depth"] < 0.05 for x in rd) >= 8:
            size = cal.forward().bin_size
            shares = "; ".join(f"{m:.1f} bin {phase_share(rd, m * size)[0]:.2f} / {phase_share(rd, m * size)[1]:.2f}"
                               for m in (0.5, 1.0, 2.0))
            print(f"  diff own, 2-5 cm: share of its slope error (x / y) that one sinusoid in z0 of period {shares}")
        if show:
            for x, y in zip(rp, rd):
                if x["depth"] < 0.05:
                    print(f"    {x['depth'] * 1e3:6.2f} mm  peak {x['deg'] if x['deg'] is not None else math.nan:6.2f} "
                          f"NEES {x['nees'] or math.nan:7.3f}  diff {y['deg'] if y['deg'] is not None else math.nan:6.2f} "
                          f"NEES {y['nees'] or math.nan:7.3f} res {y['res'] or math.nan:5.2f} {y['used']}")


def cached(path: Path, frames, variant: str) -> Calibration:
    if path.exists():
        return Calibration.load(path)
    cal = calibrate(frames, variant)
    cal.save(path)
    return cal


def unit_frames(seed: int, data: Path, close: bool, tilted: bool) -> tuple[list, dict]:
    from place_safe.sim.calibration_capture import capture_level_sweep
    from place_safe.sim.tof_mismatch import MismatchConfig
    u = MismatchConfig(seed=seed)
    spec = {"level": (100, 3, (0.005, 0.40), 0.0), "test": (80, 5, (0.005, 0.40), 0.0),
            "near": (40, 7, (0.019, 0.051), 0.0)}
    if close:
        spec["close"] = (20, 9, (0.012, 0.021), 0.0)
    if tilted:
        spec["tilted"] = (30, 8, (0.02, 0.05), math.radians(20.0))
    out = {}
    for k, (n, s, h, t) in spec.items():
        p = data / f"u{seed}_{k}.json"
        if not p.exists():
            write_frames(p, capture_level_sweep("mismatch", n, s, heights=h, max_tilt=t, mismatch=u,
                                                temperature=45.0))
        out[k] = load_frames(p)
    level = out.pop("level")
    sets = {"level": out.pop("test") + out.pop("near") + out.pop("close", [])}
    sets.update(out)
    return level, sets


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--units", type=int, nargs="*", default=[])
    ap.add_argument("--real", action="store_true", help="the real halves, both ways")
    ap.add_argument("--variants", nargs="+", default=["default", "ff0.02+rc"])
    ap.add_argument("--data", default=os.environ.get("NEAR_NEES_DATA", "."), help="the simulated frames' folder")
    ap.add_argument("--cals", default=".", help="folder for the calibrations (made when missing)")
    ap.add_argument("--close", action="store_true", help="and 20 frames 12-21 mm per unit")
    ap.add_argument("--tilted", action="store_true", help="and 30 frames 2-5 cm tilted 0-20 deg per unit")
    ap.add_argument("--frames", action="store_true", help="each frame closer than 5 cm")
    a = ap.parse_args()
    cals = Path(a.cals)
    cals.mkdir(parents=True, exist_ok=True)
    if a.real:
        sweep = load_frames(SWEEP)
        halves = {"even": sweep[0::2], "odd": sweep[1::2]}
        for v in a.variants:
            for src, dst in (("even", "odd"), ("odd", "even")):
                cal = cached(cals / f"real_{src}_{v}.json", halves[src], v)
                report(f"real {src} -> {dst}, {v}", cal, {dst: halves[dst]}, a.frames)
    for s in a.units:
        level, sets = unit_frames(s, Path(a.data), a.close, a.tilted)
        for v in a.variants:
            report(f"unit {s}, {v}", cached(cals / f"u{s}_{v}.json", level, v), sets, a.frames)
    return 0


if __name__ == "__main__":
    sys.exit(main())
