"""Speed of the simulation: the scene with the simulated sensor in lockstep (``place-safe bench sim``) and the
bare robot's physics (``place-safe bench sim --bare``). Speeds are measured here, never asserted in tests.
"""

from __future__ import annotations

import time


def bench(scene_path: str | None = None, rig: bool = False, seconds: float = 5.0, rate: float = 30.0,
          rays: int = 8) -> dict:
    """Run the scene ``seconds`` of sim time with the sensor in lockstep; returns timing figures."""
    from place_safe.sim.scene import build_scene, scene_config
    from place_safe.sim.tof import SimToF, ToFConfig

    scene = build_scene(scene_config(scene_path, not rig))
    cfg = ToFConfig(rays=rays, rate_hz=rate)
    if scene.config.with_robot:
        from place_safe.sim.robot import SimRobot

        robot = SimRobot(scene.model)
        tof = SimToF(scene, robot.data, cfg).attach(robot)
        t0 = time.perf_counter()
        robot.step(seconds)
        wall = time.perf_counter() - t0
        sim_t = seconds
    else:
        tof = SimToF(scene, None, cfg)
        t0 = time.perf_counter()
        while tof.data.time < seconds:
            tof.read(1.0)
        wall = time.perf_counter() - t0
        sim_t = float(tof.data.time)
    frames = tof._next_index
    return {"sim_seconds": sim_t, "wall_seconds": wall, "real_time_factor": sim_t / wall, "frames": frames,
            "physics_steps": int(round(sim_t / scene.model.opt.timestep)), "with_robot": scene.config.with_robot}


def benchmark(seconds: float = 2.0) -> dict[str, float]:
    """Measure simulation speed of the bare robot: physics steps per second and the real-time factor,
    idle (holding) and during a 0.1 m/s linear move."""
    from place_safe.sim.robot import SimRobot

    robot = SimRobot.load()
    h = robot.model.opt.timestep
    w0, t0 = time.perf_counter(), robot.time()
    robot.step(seconds)
    idle = (robot.time() - t0) / (time.perf_counter() - w0)
    goal = robot.tcp_pose()
    goal[:3, 3] += [0.1, 0.1, -0.1]
    w0, t0 = time.perf_counter(), robot.time()
    robot.move_linear(goal, speed=0.1, accel=0.5)
    moving = (robot.time() - t0) / (time.perf_counter() - w0)
    return {"idle_steps_per_s": idle / h, "idle_realtime_factor": idle,
            "moving_steps_per_s": moving / h, "moving_realtime_factor": moving}


__all__ = ["bench", "benchmark"]
