"""Put the cup down with a real UR5 and a real TMF8820: the same PlacementLoop as the simulated example.

Run (on the arm's network, sensor on the host's I2C bus, after ``place-safe capture`` + ``calibrate``):

    python examples/real_placement.py robots/ur5/real.toml i2c:/dev/i2c-1@0x41 cal.json [--dry-run]

``--dry-run`` connects receive-only, prints the planned motion and commands nothing. The speeds near the
surface and the stop decelerations come from the robot file (``[motion]``, ``[limits]``).
"""

import sys

from place_safe import (Calibration, PlacementConfig, PlacementLoop, URConfig, URRobot, make_estimator, open_source,
                        placement_config)


def place(robot, sensor, estimator, config=None, timeout=30.0):
    """One placement; the robot and the sensor are opened and closed here."""
    if config is None:
        config = placement_config(robot.config) if hasattr(robot, "config") else PlacementConfig()
    with sensor, robot:  # the sensor first: the robot's watchdog is armed by the first motion
        return PlacementLoop(robot, sensor, estimator, robot.tool, config).run(timeout=timeout)


if __name__ == "__main__":
    robot_file, sensor_uri, calibration_file = sys.argv[1:4]
    robot = URRobot(URConfig.load(robot_file), dry_run="--dry-run" in sys.argv)
    result = place(robot, open_source(sensor_uri), make_estimator("diff", Calibration.load(calibration_file)))
    print(f"{result.outcome}: {result.reason}")
    sys.exit(0 if result.outcome in ("released", "refused") else 1)
