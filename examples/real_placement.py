"""Put the cup down with a real UR5 and a real TMF8820: the same PlacementLoop as the simulated example.

Run (on the arm's network, sensor on the host's I2C bus, after ``place-safe capture`` + ``calibrate``):

    python examples/real_placement.py robots/ur5/real.toml i2c:/dev/i2c-1@0x41 cal.json [--dry-run]

``--dry-run`` connects receive-only, prints the planned motion and commands nothing. The speeds near the
surface and the stop decelerations come from the robot file (``[motion]``, ``[limits]``). A robot, sensor or
calibration that cannot be opened ends the script with one line saying why (exit 2) before anything moves; so does an
error the placement loop raises instead of ending on. Exit 0 released, 1 refused or ended on a fault or a timeout
(as ``place-safe place``), 2 what could not be opened.
"""

import argparse
import sys

from place_safe import (Calibration, PlaceSafeError, PlacementConfig, PlacementLoop, URConfig, URRobot,
                        make_estimator, open_source, placement_config)


def place(robot, sensor, estimator, config=None, timeout=30.0):
    """One placement; the robot and the sensor are opened and closed here."""
    if config is None:
        config = placement_config(robot.config) if hasattr(robot, "config") else PlacementConfig()
    with sensor, robot:  # the sensor first: the robot's watchdog is armed by the first motion
        return PlacementLoop(robot, sensor, estimator, robot.tool, config).run(timeout=timeout)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="real_placement.py", description="Put the held cup down on the surface below, or refuse and keep "
        "holding it, with a UR5 over ur-rtde and a TMF8820. Exit 0 released, 1 refused or any other end of the "
        "placement (a fault it stopped on, a timeout), as 'place-safe place' does, 2 a robot, sensor or calibration that could not be opened, or "
        "an error the placement could not end on its own (one line).",
        epilog="example: python examples/real_placement.py robots/ur5/real.toml i2c:/dev/i2c-1@0x41 cal.json "
               "--dry-run")
    parser.add_argument("robot", help="robot file (robots/ur5/real.toml: the arm's address, limits, gripper)")
    parser.add_argument("sensor", help="sensor: i2c:/dev/i2c-1@0x41, serial:/dev/ttyACM0, emu:synthetic, file:F.json")
    parser.add_argument("calibration", help="calibration file from place-safe calibrate (--method diff)")
    parser.add_argument("--dry-run", action="store_true", help="connect receive-only and command nothing")
    parser.add_argument("--timeout", type=float, default=30.0, help="seconds for the whole placement (default 30)")
    args = parser.parse_args(argv)
    try:
        estimator = make_estimator("diff", Calibration.load(args.calibration))
        robot = URRobot(URConfig.load(args.robot), dry_run=args.dry_run)
        result = place(robot, open_source(args.sensor), estimator, timeout=args.timeout)
    except PlaceSafeError as exc:
        print(f"real_placement.py: {str(exc).splitlines()[0]}", file=sys.stderr)
        return 2
    print(f"{result.outcome}: {result.reason}")
    return 0 if result.outcome == "released" else 1


if __name__ == "__main__":
    sys.exit(main())
