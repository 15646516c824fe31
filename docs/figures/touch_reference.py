"""How far a touched table is off, against what :func:`~place_safe.calibration.capture.touched_reference` states.

    python docs/figures/touch_reference.py --seeds 24        # about 8 s a seed

Touches a level table at three points 8 cm apart (the simulated user calibration's pattern,
``place_safe.sim.calibration_capture.TOUCH_OFFSETS``) with :func:`~place_safe.calibration.capture.touch_plane`, on
two stand-ins: the UR5 driver over the fake ur_rtde with a CB3's force estimate (3.6 N noise, 4 N offset: the
kinematic arm pressing a spring table; one run per seed of the fake's noise) and the MuJoCo arm (``sim_world``, the
chain ``place-safe calibrate --sim`` runs; deterministic). Prints each touch's contact heights, the touched normal's
angle from the truth and the stated ``tilt_std`` (rad, the worst direction's), and over the seeds the mean of
(error / stated)^2 / 2. For three touches in a right-angled triangle the stated direction's variance is 3/4 of the
normal's total (the trace), so an honest statement averages 2/3 on this measure; below, the contacts scatter less than
stated (by the square root of the ratio). docs/results.md, "The calibration's reference".
"""
from __future__ import annotations

import argparse
import math

import numpy as np

from place_safe.calibration.capture import touch_plane, touched_reference

TABLE_Z = 0.05  # m, the fake's table top in the base frame


def cb3_touch(seed: int, kinematics) -> tuple[np.ndarray, np.ndarray]:
    """(touched normal, contact points) on the fake CB3 with force noise seed ``seed``."""
    from place_safe.drivers.ur5 import URConfig, URRobot, fake_rtde, packaged_config
    from place_safe.drivers.ur5.kinematic_arm import KinematicArm

    arm = KinematicArm(kinematics=kinematics, contact_plane=(np.array([0.0, 0.0, 1.0]), TABLE_Z))
    fake = fake_rtde.FakeUR(arm, force_noise=3.6, force_offset=(0.0, 0.0, 4.0), seed=seed)
    robot = URRobot(URConfig.load(packaged_config("sim")), modules=fake_rtde.modules(), out=lambda s: None).connect()
    del fake
    from place_safe.sim.calibration_capture import TOUCH_OFFSETS

    pts = [(-0.46 + dx, -0.08 - dy) for dx, dy in TOUCH_OFFSETS]
    n, _, P = touch_plane(robot, pts, start_height=0.08, speed=0.005, force_threshold=15.0)
    return n, P


def mujoco_touch() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(touched normal, contact points, true normal) of the MuJoCo arm, as the simulated user calibration touches."""
    from place_safe.sim.calibration_capture import TOUCH_OFFSETS, TOUCH_START
    from place_safe.sim.scenario import Scenario
    from place_safe.sim.world import sim_world

    world = sim_world(Scenario(name="calibration_nominal", sensor={"model": "nominal", "seed": 0}), seed=0,
                      hold_cup=False)
    start = world.robot.tcp_pose()[:3, 3]
    pts = [(start[0] + dx, start[1] + dy) for dx, dy in TOUCH_OFFSETS]
    plane = world.table_plane_base()
    n, _, P = touch_plane(world.robot, pts, float(plane[1] + TOUCH_START))
    return n, P, np.asarray(plane[0], dtype=float)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=24, help="fake CB3 runs (force noise seeds 0..N-1)")
    a = ap.parse_args()
    rows = []
    n, P, truth = mujoco_touch()
    ref = touched_reference(P)
    err = math.acos(min(1.0, float(n @ truth)))
    print(f"MuJoCo arm: contacts {np.round((P[:, 2] - P[:, 2].mean()) * 1e3, 3)} mm about their mean, normal "
          f"{math.degrees(err):.3f} deg off, stated {math.degrees(ref.tilt_std):.3f} deg")
    from place_safe.robot.kinematics import Kinematics

    kinematics = Kinematics()
    for seed in range(a.seeds):
        n, P = cb3_touch(seed, kinematics)
        ref = touched_reference(P)
        err = math.acos(min(1.0, float(n[2])))
        rows.append((err, ref.tilt_std))
        print(f"CB3 seed {seed:2d}: contacts {np.round((P[:, 2] - TABLE_Z) * 1e3, 3)} mm, normal "
              f"{math.degrees(err):.3f} deg off, stated {math.degrees(ref.tilt_std):.3f} deg", flush=True)
    e = np.array(rows)
    print(f"CB3, {len(e)} touches: error mean {math.degrees(e[:, 0].mean()):.3f} deg, largest "
          f"{math.degrees(e[:, 0].max()):.3f}; (error / stated)^2 / 2 = "
          f"{np.mean((e[:, 0] / e[:, 1]) ** 2) / 2:.2f} (honest: "
          f"0.67); "
          f"beyond 2 sigma: {int(np.sum(e[:, 0] > 2 * e[:, 1]))}")


if __name__ == "__main__":
    main()
