"""The two readings of a level sweep, on scorecard units (docs/results.md, "Two readings of a level sweep").

For each unit calibrated by ``unit_scorecard.py`` (its ``{unit}_cal.json``, ``{unit}_level.json`` and ``{unit}_tilt.json``
in ``--out``):

- ``compare``: fit the reading ``calibrate`` did not keep (the nominal geometry with each zone's own time scale where it
  kept the fitted geometry, the free fit where it adopted the time scales; about 35 s), render the same 60 tilted planes
  (5-30 cm, 0-30 deg, the sweep's mean reference histogram) with each reading, and print the slope scale and offset bias
  (``peak_tilt_bias.summary``) of the calibrated diff's planes on both and on the unit's own tilted frames;
- ``rescore``: refit the calibration's uncertainty sections with this code (``update_calibration`` on the level sweep)
  and print diff's and peak's mean angle and NEES per dof on the tilted frames, as calibrated and refitted;
- ``residuals``: the comparison ``calibrate --readings-from`` makes (:func:`place_safe.calibration.readings.
  compare_readings`, both readings under the first fit's model error), on the unit's own tilted frames (their ground
  truth unused), and the choice it would make (docs/results.md, "Tilted frames without ground truth choose the
  reading").

    python docs/figures/two_readings.py compare 41 40 --out sc
    python docs/figures/two_readings.py rescore 39 42 34 36 --out sc
    python docs/figures/two_readings.py residuals 41 44 40 43 synth5 45 37 --out sc
"""
from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from peak_tilt_bias import summary  # noqa: E402


def compare(unit: str, out: Path) -> None:
    from place_safe.calibration import Calibration
    from place_safe.calibration.forward_fit import fit_forward
    from place_safe.calibration.second_fit import nominal_geometry_fit
    from place_safe.evaluation.synthetic import SyntheticSpec, make_frames
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    level = load_frames(str(out / f"{unit}_level.json"))
    cal = Calibration.load(out / f"{unit}_cal.json")
    kept = cal.forward()
    adopted = (cal.reports["forward"].get("geometry") or {}).get("adopted")
    other = (nominal_geometry_fit(level) if adopted == "free" else fit_forward(level, init=None, progress=False))[0]
    ref = np.mean([f.reference for f in level[:20]], axis=0)
    spec = SyntheticSpec(z_range=(0.05, 0.30), theta_range=(0.0, math.radians(30.0)), specular_weight_range=(0.0, 0.0))
    diff = make_estimator("diff", cal.without_fallback())
    print(f"{unit}: kept {adopted}; fields of view kept {kept.edge_fov_scale:.3f} / {kept.corner_fov_scale:.3f}, "
          f"other {other.edge_fov_scale:.3f} / {other.corner_fov_scale:.3f}")
    own = load_frames(str(out / f"{unit}_tilt.json"))
    for name, frames in (("kept reading's planes", make_frames(60, params=kept, spec=spec, seed=3, reference=ref)),
                         ("other reading's planes", make_frames(60, params=other, spec=spec, seed=3, reference=ref)),
                         ("the unit's own tilted frames", own)):
        s = summary(frames, diff.estimate_many(frames))
        print(f"  {name:30s} slope scale {s['slope_scale']:+.4f}  offset bias {s['offset_bias']:+.4f} z0 tan(tilt)  "
              f"angle {s['angle_deg']:.3f} deg")


def rescore(unit: str, out: Path) -> None:
    from place_safe.calibration import Calibration
    from place_safe.calibration.uncertainty import update_calibration
    from place_safe.io.frame_file import load_frames
    from place_safe.evaluation.metrics import angular_error, nees
    from place_safe.recovery import make_estimator

    level = load_frames(str(out / f"{unit}_level.json"))
    tilt = load_frames(str(out / f"{unit}_tilt.json"))
    truths = [f.truth for f in tilt]

    def score(cal) -> str:
        parts = []
        for method in ("diff", "peak"):
            ests = make_estimator(method, cal).estimate_many(tilt)
            per_dof = nees(ests, truths)  # NaN where a frame has no plane or covariance: those are left out of both
            angle = [math.degrees(angular_error(e.plane, t)) for e, t, v in zip(ests, truths, per_dof) if np.isfinite(v)]
            parts.append(f"{method} {np.mean(angle):.3f} deg, NEES {np.nanmean(per_dof):.2f}")
        return " | ".join(parts)

    cal = Calibration.load(out / f"{unit}_cal.json")
    print(f"{unit} as calibrated: {score(cal)}")
    update_calibration(cal, level, "diff")
    print(f"{unit} refitted:      {score(Calibration.from_dict(cal.to_dict()))}")


def residuals(unit: str, out: Path) -> None:
    from place_safe.calibration import Calibration
    from place_safe.calibration.readings import compare_readings, decide
    from place_safe.calibration.uncertainty import other_reading
    from place_safe.io.frame_file import load_frames

    cal = Calibration.load(out / f"{unit}_cal.json")
    other = other_reading(cal)
    if other is None:
        print(f"{unit}: its level sweep told the readings apart (or left one): nothing to compare")
        return
    # the first fit's model error, as calibrate compares them (select_model_error runs after the choice)
    kept = cal.forward().model_copy(update={"model_error": other.model_error})
    from place_safe.recovery.differentiable import SolverOptions

    options = SolverOptions(crosstalk_std=cal.diff_options().crosstalk_std)  # each frame's own crosstalk, as calibrate
    c = compare_readings(load_frames(str(out / f"{unit}_tilt.json")), kept, other, cal.peak(), options)
    choice, why = decide(c)
    print(f"{unit}: {c['compared']} of {c['frames']} frames compared, the other reading lower on "
          f"{100 * c['other_lower']:.0f} % (median ratio {c['median_ratio']:.3f}), planes {c['apart_deg']:.2f} deg apart: "
          f"{choice or 'neither'} ({why})")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("what", choices=("compare", "rescore", "residuals"))
    p.add_argument("units", nargs="+", help="scorecard units (unit_scorecard.py --units ... --out DIR made their files)")
    p.add_argument("--out", type=Path, required=True, help="the scorecard's output folder")
    args = p.parse_args(argv)
    for unit in args.units:
        {"compare": compare, "rescore": rescore, "residuals": residuals}[args.what](unit, args.out)


if __name__ == "__main__":
    main()
