"""Put the cup down in MuJoCo with the same PlacementLoop a real-arm script uses.

Run: ``MUJOCO_GL=egl python examples/simulated_placement.py [SCENARIO]`` (default place_level: a file or a name
from ``scenarios/`` or ``scenarios/set/``, e.g. place_tilted; ``place-safe scenarios`` runs the whole set). The robot,
the sensor and the calibration are the simulation's; everything else is the real code path.
"""

import argparse
import sys

from place_safe import PlaceSafeError, PlacementConfig, PlacementLoop, make_estimator, sim_world

parser = argparse.ArgumentParser(prog="simulated_placement.py", description="One placement in MuJoCo: released or "
                                 "refused, and the state machine's transitions. Exit 0 released or refused, 1 any other "
                                 "end, 2 a scenario that cannot be loaded.")
parser.add_argument("scenario", nargs="?", default="place_level",
                    help="a packaged scenario name or a scenario file (default place_level; e.g. place_tilted)")
args = parser.parse_args()
try:
    world = sim_world(args.scenario)  # scene, SimRobot, simulated TMF8820
    # the scenario's simulated unit's own calibration: a user's (capture -> place-safe calibrate, made in simulation);
    # one made on another unit misreads this one
    calibration = world.user_calibration()
except PlaceSafeError as exc:
    print(f"simulated_placement.py: {str(exc).splitlines()[0]}", file=sys.stderr)
    sys.exit(2)
robot, sensor = world.robot, world.tof
estimator = make_estimator("diff", calibration)
with robot:
    result = PlacementLoop(robot, sensor, estimator, robot.tool, PlacementConfig()).run(timeout=20.0)
print(f"{result.outcome}: {result.reason}")
for t in result.transitions:
    print(f"  t={t.time:6.3f} s  {t.source.value:>8} -> {t.target.value:<8} {t.reason}")
sys.exit(0 if result.outcome in ("released", "refused") else 1)
