"""``place-safe synth``: write frame files with ground truth from a test generator.

Generators: ``independent`` (:mod:`place_safe.evaluation.independent`, a separately written simulation
of the sensor with structural choices the project's model does not make; use it to measure methods on
data they did not generate) and ``model`` (:mod:`place_safe.evaluation.synthetic`, the project's own
forward model: convention checks only). Distances in metres, angles in degrees at this edge.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from place_safe.cli import options
from place_safe.cli.options import opt
from place_safe.cli.options import float_range, int_range
from place_safe.cli.common import UsageError, log, refuse_overwrite
from place_safe.io.frame_file import write_frames
from place_safe.sensor.frame import SENSOR_RANGE

EPILOG = """examples:
  # calibration frames and separate test frames of the same simulated sensor
  place-safe synth --frames 150 --seed 1 -o out/indep_cal.json
  place-safe synth --frames 300 --seed 2 -o out/indep_test.json
  place-safe calibrate out/indep_cal.json --method diff -o out/indep_calib.json
  place-safe evaluate out/indep_test.json --calibration out/indep_calib.json --methods diff peak
  # close range, the paper's structural choices
  place-safe synth --frames 50 --min-distance 0.01 --max-distance 0.05 --pulse linear \\
      --saturation shaded --crosstalk others -o out/near.json"""


def register(subparsers) -> None:
    from place_safe.evaluation.independent import CROSSTALK_MODES, PULSE_MODES, SATURATION_MODES

    options.command(
        subparsers, "synth", cmd_synth,
        "write synthetic frames with ground truth (independent generator or the project's model)",
        "Draw random planes (distance uniform in [--min-distance, --max-distance] m, angle of incidence uniform in "
        "[0, --max-angle] deg, random albedo and specular lobe) and write their frames, with the true plane, as a "
        "frame file. The simulated sensor is fixed by --sensor-seed (same seed, same sensor); --seed draws the scenes.",
        EPILOG,
        opt("--generator", choices=("independent", "model"), default="independent",
            help="independent simulation (default) or the project's forward model (convention checks)"),
        "frames", "seed",
        opt("--sensor-seed", type=int_range(0, 2 ** 32 - 1), default=None,
            help="independent: seed of the simulated sensor (default 0)"),
        opt("--min-distance", type=float_range(0.0, SENSOR_RANGE, lo_open=True), default=0.02, metavar="M",
            help=f"nearest z0, m: where the plane crosses the optical axis (default 0.02, at most {SENSOR_RANGE:g}; evaluate's "
                 "--min-distance is the perpendicular distance d)"),
        opt("--max-distance", type=float_range(0.0, SENSOR_RANGE, lo_open=True), default=0.30, metavar="M",
            help=f"farthest z0, m (default 0.30, at most {SENSOR_RANGE:g}: the sensor's range)"),
        opt("--max-angle", type=float_range(0.0, 80.0), default=30.0, metavar="DEG",
            help="largest incidence, deg (default 30, 0..80)"),
        opt("--pulse", choices=PULSE_MODES, default=None,
            help="independent: zone pulse from the reference (default gaussian soft-binning)"),
        opt("--saturation", choices=SATURATION_MODES, default=None,
            help="independent: SPAD saturation of the shaded or unshaded intensity (default unshaded)"),
        opt("--crosstalk", choices=CROSSTALK_MODES, default=None,
            help="independent: crosstalk from the other zones or all zones (default all)"),
        opt("--no-noise", action="store_true", help="expected counts, no Poisson noise"),
        "output", "force",
        frames={"default": 100, "help": "frames to write, 1-100000 (default 100; they are built in memory, about "
                                        "10 kB each)"},
        seed={"help": "seed of the scenes (default 0)"},
        output={"required": True, "help": "frame file to write (JSON list)"})


def cmd_synth(args: argparse.Namespace) -> int:

    if not args.min_distance < args.max_distance:
        raise UsageError("synth: --min-distance must be below --max-distance")
    refuse_overwrite(args.output, args.force)  # before the frames are drawn (minutes for 100,000)
    z_range = (args.min_distance, args.max_distance)
    theta_range = (0.0, math.radians(args.max_angle))
    if args.generator == "independent":
        from place_safe.evaluation.independent import IndependentGenerator, SceneSpec, SensorSpec

        overrides = {k: v for k, v in (("pulse_mode", args.pulse), ("saturation_mode", args.saturation),
                                         ("crosstalk_mode", args.crosstalk)) if v is not None}
        gen = IndependentGenerator(SensorSpec.draw(args.sensor_seed or 0, **overrides))
        frames = gen.frames(args.frames, args.seed, SceneSpec(z_range, theta_range, noise=not args.no_noise))
    else:
        # (the model's sensor is the published one: a --sensor-seed was not read, the frames the same for any seed)
        if args.pulse or args.saturation or args.crosstalk or args.sensor_seed is not None:
            raise UsageError("synth: --sensor-seed, --pulse, --saturation and --crosstalk apply to --generator "
                             "independent only")
        from place_safe.evaluation.synthetic import SyntheticSpec, make_frames

        frames = make_frames(args.frames, seed=args.seed,
                             spec=SyntheticSpec(z_range=z_range, theta_range=theta_range, noise=not args.no_noise))
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    try:
        n = write_frames(out, frames)
    except KeyboardInterrupt:  # Ctrl-C while writing: no frame file cut short (a JSON list without its ']') left behind
        if out.is_file():
            out.unlink()
        raise
    log(f"wrote {n} {args.generator} frames to {out}")
    return 0
