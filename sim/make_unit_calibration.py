"""Calibrate another simulated unit the way a user calibrates theirs: a level sweep, then ``place-safe calibrate``.

The packaged simulated calibrations (``calibration_mismatch.json``, ``calibration_nominal.json``) are made by
``place-safe calibrate --sim`` on the default units. This script makes one for a mismatched unit whose
:class:`~place_safe.sim.tof_mismatch.MismatchConfig` differs, from a level sweep alone (the table straight below the
sensor, no tilt), which is what a user with a bench and a level table captures, or with ``--tilted N`` a few tilted
frames added, as ``calibrate``'s note asks:

    python sim/make_unit_calibration.py --zone-time-scale 0.015 -o sim/sensors/calibration_mismatch_zone_time.json

``calibration_mismatch_zone_time.json`` (unit A whose zones each keep their own time scale, +-1.5 %, as the real
sweep's zones do; docs/results.md, "Each zone's own time scale") is the calibration of the ``zone_time_*`` scenarios
in ``scenarios/set``: a level sweep sets such a unit's geometry far from nominal, and ``calibrate`` replaces it by
each zone's own time scale (``second_fit.reconsider_geometry``). The sweep: :data:`FRAMES` frames, the sensor
:data:`HEIGHTS` above the table, at operating temperature, seed :data:`SEED` (the unit scorecard's level sweep,
``docs/figures/unit_scorecard.py --units 34``). ``reports.capture`` records the unit and the sweep. About a minute
(half a minute more with the second forward fit on a machine without a spare core).

    python sim/make_unit_calibration.py --mount-tilt 1.2 -0.9 -o sim/sensors/calibration_mismatch_mount_tilt.json

``calibration_mismatch_mount_tilt.json`` (unit A mounted 1.5 deg off its nominal orientation; docs/results.md, "A
sensor mounted off its nominal orientation") is the calibration of the ``mount_tilt_*`` scenarios: there the forward
fit keeps the mount, and peak's covariance widens by it on tilted planes so that diff is not thrown away for peak.

    python sim/make_unit_calibration.py --zone-time-scale 0.015 --mount-tilt 0.8 -0.6 -o OUT.json

(``OUT.json``: ``sim/sensors/calibration_mismatch_zone_time_mount.json``)

``calibration_mismatch_zone_time_mount.json`` (the zone-time unit mounted 1.0 deg off: both things a level table
cannot tell apart in one unit, scorecard unit 39) is the calibration of the ``zone_time_mount_*`` scenarios: the
time-scale reading is kept, and the scales take up the mount as far as a level table shows it.

    python sim/make_unit_calibration.py --zone-time-scale 0.015 --mount-tilt 0.8 -0.6 --tilted 12 -o OUT.json

(``OUT.json``: ``sim/sensors/calibration_mismatch_zone_time_mount_tilts.json``) the same unit's level sweep with 12
tilted frames added, as calibrate's note asks: the tilted frames tell the zones' directions from their time, and
``calibrate`` fits both (the time scales and the mount found, docs/results.md "A few tilted frames"); the calibration
of the ``zone_time_mount_tilts_*`` scenarios.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

#: Frames of the level sweep.
FRAMES = 150
#: m, sensor-to-table heights of the level sweep.
HEIGHTS = (0.02, 0.40)
#: The sweep's seed (the pose draw and the sensor's noise).
SEED = 5


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("-o", "--output", required=True, help="calibration file to write")
    ap.add_argument("--zone-time-scale", type=float, default=0.0,
                    help="MismatchConfig.zone_time_scale: each zone's time scale within 1 +- this (default 0)")
    ap.add_argument("--unit-seed", type=int, default=None, help="MismatchConfig.seed (default: the default unit's)")
    ap.add_argument("--mount-tilt", type=float, nargs=2, default=None, metavar=("RX_DEG", "RY_DEG"),
                    help="MismatchConfig.mount_tilt in degrees: the sensor mounted off its nominal orientation "
                         "(rotation vector about x and y; default: mounted nominally)")
    ap.add_argument("--tilted", type=int, default=0, metavar="N",
                    help="add N frames of a table tilted 8-30 deg below the sensor (5-30 cm) to the level sweep, as a "
                         "user who follows calibrate's note captures them (default 0: the level sweep alone)")
    ap.add_argument("--frames-out", help="also keep the sweep's frames here")
    a = ap.parse_args(argv)
    if a.tilted < 0:
        ap.error(f"--tilted must be 0 or more frames, got {a.tilted}")

    import torch

    from place_safe.calibration import Calibration
    from place_safe.calibration.fit import fit_method
    from place_safe.io.frame_file import write_frames
    from place_safe.sim.calibration_capture import (FEW_TILTS_DEG, FEW_TILTS_HEIGHTS, FEW_TILTS_SEED,
                                                    OPERATING_TEMPERATURE, capture_few_tilts, capture_level_sweep)
    from place_safe.sim.tof_mismatch import MismatchConfig

    torch.set_num_threads(1)
    unit = {"zone_time_scale": a.zone_time_scale, **({"seed": a.unit_seed} if a.unit_seed is not None else {}),
            **({"mount_tilt": [math.radians(v) for v in a.mount_tilt]} if a.mount_tilt is not None else {})}
    try:
        mc = MismatchConfig(**unit)
    except ValueError as exc:  # pydantic's ValidationError: a unit out of the config's bounds
        lines = str(exc).splitlines()
        ap.error(f"not a unit the simulator can make: {lines[0]} ({'; '.join(x.strip() for x in lines[1:3])})")
    print(f"level sweep: {FRAMES} frames, {HEIGHTS[0] * 100:g}-{HEIGHTS[1] * 100:g} cm, unit {unit}", file=sys.stderr)
    frames = capture_level_sweep("mismatch", FRAMES, seed=SEED, temperature=OPERATING_TEMPERATURE, heights=HEIGHTS,
                                 max_tilt=0.0, mismatch=mc)
    if a.tilted:  # the tilted poses of unit_scorecard.py --few-tilts
        print(f"tilted frames: {a.tilted}, {FEW_TILTS_DEG[0]:g}-{FEW_TILTS_DEG[1]:g} deg, "
              f"{FEW_TILTS_HEIGHTS[0] * 100:g}-{FEW_TILTS_HEIGHTS[1] * 100:g} cm", file=sys.stderr)
        frames += capture_few_tilts(a.tilted, mc)
    if a.frames_out:
        write_frames(a.frames_out, frames)
    cal = Calibration()
    for method in ("diff", "proprietary"):
        fit_method(cal, frames, method, progress=True, log=lambda line: print(line, file=sys.stderr, flush=True))
    cal.reports["capture"] = {"sensor": "mismatch", "unit": unit, "seed": SEED, "frames": len(frames),
                              "chain": "capture_level_sweep (level: the table straight below, at operating "
                                       "temperature" + (f"; then {a.tilted} frames of the table tilted, 'tilted'"
                                                        if a.tilted else "")
                                       + ") -> place-safe calibrate --method diff, proprietary",
                              "distances_m": list(HEIGHTS), "max_tilt_deg": 0.0,
                              "temperature_degc": OPERATING_TEMPERATURE,
                              **({"tilted": {"frames": a.tilted, "seed": FEW_TILTS_SEED,
                                             "distances_m": list(FEW_TILTS_HEIGHTS), "tilt_deg": list(FEW_TILTS_DEG)}}
                                 if a.tilted else {})}
    out = Path(a.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    cal.save(out)
    g = cal.reports.get("forward", {}).get("geometry", {})
    print(f"wrote {out}: forward RMS {cal.reports['forward']['rms_scaled_residual_after']:.3f}, geometry "
          f"{g.get('adopted', 'nominal (no note)')}; {json.dumps(g.get('why') or g.get('note') or '')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
