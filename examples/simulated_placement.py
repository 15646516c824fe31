"""Put the cup down in MuJoCo with the same PlacementLoop a real-arm script uses.

Run: ``MUJOCO_GL=egl python examples/simulated_placement.py [SCENARIO]`` (default place_level).
The robot, the sensor and the calibration are the simulation's; everything else is the real code path.
"""

import sys

import mujoco

from place_safe import PlacementConfig, PlacementLoop, make_estimator
from place_safe.sim.placement_run import oracle_calibration, scenario_path
from place_safe.sim.robot import SimRobot
from place_safe.sim.scene import build_scene, load_scenario
from place_safe.sim.tof import SimToF, ToFConfig

scene_config, sensor_config, _ = load_scenario(scenario_path(sys.argv[1] if len(sys.argv) > 1 else "place_level"))
scene_config.with_robot = True
scene = build_scene(scene_config)
robot = SimRobot(scene.model, mujoco.MjData(scene.model))
sensor = SimToF(scene, robot.data, ToFConfig(**sensor_config)).attach(robot)
estimator = make_estimator("diff", oracle_calibration())  # the simulated sensor's true parameters
with robot:
    result = PlacementLoop(robot, sensor, estimator, robot.tool, PlacementConfig()).run(timeout=20.0)
print(f"{result.outcome}: {result.reason}")
for t in result.transitions:
    print(f"  t={t['time']:6.3f} s  {t['from']:>8} -> {t['to']:<8} {t['reason']}")
sys.exit(0 if result.outcome in ("released", "refused") else 1)
