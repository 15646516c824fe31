"""Put the cup down in MuJoCo with the same PlacementLoop a real-arm script uses.

Run: ``MUJOCO_GL=egl python examples/simulated_placement.py [SCENARIO]`` (default place_level).
The robot, the sensor and the calibration are the simulation's; everything else is the real code path.
"""

import sys

from place_safe import PlacementConfig, PlacementLoop, make_estimator, sim_world, simulated_calibration

world = sim_world(sys.argv[1] if len(sys.argv) > 1 else "place_level")  # scene, SimRobot, simulated TMF8820
robot, sensor = world.robot, world.tof
calibration = simulated_calibration("nominal")  # a user's: capture -> place-safe calibrate, made in simulation
estimator = make_estimator("diff", calibration)
with robot:
    result = PlacementLoop(robot, sensor, estimator, robot.tool, PlacementConfig()).run(timeout=20.0)
print(f"{result.outcome}: {result.reason}")
for t in result.transitions:
    print(f"  t={t.time:6.3f} s  {t.source.value:>8} -> {t.target.value:<8} {t.reason}")
sys.exit(0 if result.outcome in ("released", "refused") else 1)
