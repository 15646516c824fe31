"""Contact detection against a CB3's force noise, measured: false contacts over descents, touch delays, rest noise.

Concept: the numbers issue 29 asks for, each from a function anyone can rerun (``place-safe bench
contact``, ``place-safe bench robot``):

* :func:`descents` -- placements of a held cup from ``height`` (default 40 cm) onto a table through the real
  driver path: :class:`~place_safe.drivers.ur5.rtde_robot.URRobot` on the fake ur_rtde
  (:mod:`place_safe.drivers.ur5.fake_rtde`: CB3 force noise 3.6 N per axis per cycle and an offset by
  default, the watchdog, thread conflicts) moving a kinematic UR5 over a table, the
  :class:`~place_safe.placement.loop.PlacementLoop` fed by a sensor that reports the true table plane
  (:class:`TablePlaneSource`). A *false contact* is a cycle-onset of a contact the detector reports while the
  cup does not touch anything; the outcome of each placement is counted too.
* :func:`touches` -- guarded descents (speedL down at ``speed``) onto the table until the driver reports
  contact: the delay from the first touch and the true force at that moment.
* :func:`rest_noise` -- the TCP force's spread per axis at rest on a connected arm.
* :func:`settings_report` -- the detector's false-alarm rate and detection delays for a noise level, on
  synthetic noise (:mod:`place_safe.robot.contact_detector`).

Conventions: SI units inside (N, s, m); reports print mm, ms and N.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from place_safe.exceptions import SensorTimeout
from place_safe.geometry import Plane
from place_safe.robot.kinematics import Kinematics
from place_safe.sensor.frame import Frame
from place_safe.recovery.estimator import PlaneEstimate

#: m/s^2 of the reference touch ramps the bench reports (force rate = stiffness x speed).
TOUCH_SPEEDS = (0.005, 0.01, 0.02)


class TablePlaneSource:
    """Frames with the true plane of a level table (``z = table_z`` in the base frame) under the robot's
    sensor, every ``1 / rate_hz`` s of robot time, stamped on the robot clock (no histograms: use
    ``footprint_frames = 0``)."""

    clock_domain = "robot"

    def __init__(self, robot: Any, table_z: float, rate_hz: float = 10.0) -> None:
        self.robot, self.table_z, self.rate_hz = robot, float(table_z), float(rate_hz)
        self._next = -math.inf

    def open(self) -> "TablePlaneSource":
        return self

    def close(self) -> None:
        pass

    def __enter__(self) -> "TablePlaneSource":
        return self

    def __exit__(self, *exc: Any) -> None:
        pass

    def read(self, timeout: float = 1.0) -> Any:

        t = self.robot.time()
        if t < self._next:
            raise SensorTimeout("no frame ready")
        self._next = t + 1.0 / self.rate_hz
        T = self.robot.sensor_pose()
        R, p = T[:3, :3], T[:3, 3]
        nb = np.array([0.0, 0.0, 1.0])
        n = -(R.T @ nb)
        d = -(self.table_z - float(nb @ p))
        return Frame(np.zeros((9, 128)), np.zeros(128), timestamp=t, truth=Plane(n, d))


#: (rad, m): the tilt and offset stds the truth states by default: honest (the truth does not err; any bound is),
#: and at the still test's floor (``still_offset_floor``), as a well-measured plane states.
TRUTH_SIGMA = (math.radians(0.1), 1e-4)


class TruthEstimator:
    """The frame's true plane (the driver and the decision are measured, not plane recovery) with a stated
    covariance of ``(n_x, n_y, d)``: ``sigma`` (rad, m) on each tilt component and the offset (default
    :data:`TRUTH_SIGMA`; then the fusion weights it and remembers the slope); ``sigma=None`` states none (an
    estimate the stillness test cannot judge: a placement refuses)."""

    def __init__(self, sigma: tuple[float, float] | None = TRUTH_SIGMA) -> None:
        self.sigma = sigma

    def estimate(self, frame: Any) -> PlaneEstimate:
        cov = None if self.sigma is None else np.diag([self.sigma[0] ** 2, self.sigma[0] ** 2, self.sigma[1] ** 2])
        return PlaneEstimate(frame.truth, reason=None if frame.truth is not None else "no truth", covariance=cov)


_KIN: list[Any] = []


def _kinematics() -> Any:
    """One UR5 kinematics for every stand-in of this process (building it takes seconds)."""
    if not _KIN:
        _KIN.append(Kinematics())
    return _KIN[0]


def make_stand_in(controller: str = "cb3", *, table_gap: float | None = None, seed: int = 0,
                  force_noise: float | None = None, host: str = "127.0.0.1", stiffness: float = 20000.0,
                  gripper: str = "digital") -> tuple[Any, Any]:
    """(URRobot, FakeUR): the packaged sim robot file on a fake ``controller`` whose kinematic UR5 holds the
    cup ``table_gap`` m above a level table (None: no table)."""
    from place_safe.drivers.ur5 import URConfig, URRobot, fake_rtde, packaged_config
    from place_safe.drivers.ur5.kinematic_arm import KinematicArm
    from place_safe.drivers.ur5.config import CONTROLLER_HZ, RobotiqGripperConfig

    cfg = URConfig.load(packaged_config("sim"))
    cfg.connection.controller = controller
    cfg.connection.host = host
    if gripper == "robotiq":
        cfg.gripper = RobotiqGripperConfig(host="127.0.0.1")
    arm = KinematicArm(period=1.0 / CONTROLLER_HZ[controller], kinematics=_kinematics())
    tool = cfg.tool.frames()
    if table_gap is not None:
        cup = arm.tcp_pose() @ tool.tcp_T_cup
        z = float(cup[2, 3]) - float(table_gap)
        arm.contact_plane = (np.array([0.0, 0.0, 1.0]), z)
        arm.contact_points = np.asarray([tool.tcp_T_cup[:3, 3]])
        arm.stiffness = float(stiffness)
    fake = fake_rtde.FakeUR(arm, controller=controller, host=host, seed=seed, force_noise=force_noise)
    robot = URRobot(cfg, modules=fake_rtde.modules(), out=lambda s: None)
    return robot, fake


@dataclass
class DescentReport:
    descents: int
    controller: str
    noise_std: float
    height: float
    outcomes: dict[str, int] = field(default_factory=dict)
    false_contacts: int = 0  # contact onsets the detector reported with nothing touching the cup
    descents_with_false_contact: int = 0
    cycles: int = 0  # controller cycles the detector judged in the descents
    watchdog_stops: int = 0
    script_errors: int = 0
    reasons: list[str] = field(default_factory=list)  # of runs that were not released

    def summary(self) -> str:
        out = ", ".join(f"{k} {v}" for k, v in sorted(self.outcomes.items()))
        return (f"{self.descents} descents of {self.height * 100:.0f} cm on a {self.controller} stand-in with "
                f"{self.noise_std:.1f} N force noise per axis per cycle: {out}; false contacts "
                f"{self.false_contacts} ({self.descents_with_false_contact} descents) in {self.cycles} cycles; "
                f"watchdog stops {self.watchdog_stops}, script errors {self.script_errors}")


#: The defaults of :func:`descents` (m of cup above the table, first seed, worker processes) and of :func:`touches`
#: (N/m of the table contact); ``bench contact`` fills its options not given with them.
DESCENT_HEIGHT = 0.4
DESCENT_SEED = 0
DESCENT_JOBS = 1
TOUCH_STIFFNESS = 20000.0


def descents(n: int = 200, *, height: float = DESCENT_HEIGHT, controller: str = "cb3", seed: int = DESCENT_SEED,
             force_noise: float | None = None, timeout: float = 20.0, progress: Any = None,
             jobs: int = DESCENT_JOBS) -> DescentReport:
    """Run ``n`` placements from ``height`` m above a level table (see the module docstring); ``jobs`` > 1
    splits them over worker processes (seeds ``seed .. seed + n - 1`` either way)."""
    if jobs > 1 and n > 1:
        from concurrent.futures import ProcessPoolExecutor

        parts = [list(range(seed + j, seed + n, jobs)) for j in range(min(jobs, n))]
        total = DescentReport(n, controller, math.nan, height)
        with ProcessPoolExecutor(len(parts)) as pool:
            futs = [pool.submit(_descent_seeds, seeds, height, controller, force_noise, timeout) for seeds in parts]
            for f in futs:
                r = f.result()
                total.noise_std = r.noise_std
                for k, v in r.outcomes.items():
                    total.outcomes[k] = total.outcomes.get(k, 0) + v
                for name in ("false_contacts", "descents_with_false_contact", "cycles", "watchdog_stops",
                             "script_errors"):
                    setattr(total, name, getattr(total, name) + getattr(r, name))
                total.reasons += r.reasons
        return total
    return _descent_seeds(list(range(seed, seed + n)), height, controller, force_noise, timeout, progress)


def _descent_seeds(seeds: list[int], height: float, controller: str, force_noise: float | None, timeout: float,
                   progress: Any = None) -> DescentReport:
    from place_safe.placement.loop import PlacementLoop
    from place_safe.placement.config import PlacementConfig
    from place_safe.drivers.ur5.config import placement_config

    rep = DescentReport(len(seeds), controller, math.nan, height)
    for i, sd in enumerate(seeds):
        robot, fake = make_stand_in(controller, table_gap=height, seed=sd, force_noise=force_noise)
        rep.noise_std = fake.force_noise
        cfg = placement_config(robot.config, PlacementConfig(footprint_frames=0))
        table_z = float(fake.arm.contact_plane[1])
        with robot:
            loop = PlacementLoop(robot, TablePlaneSource(robot, table_z), TruthEstimator(), config=cfg)
            loop.start()
            was, onsets, cycles = False, 0, 0
            ticks = int(timeout / loop.period)
            while not loop.finished and loop.ticks < ticks:
                loop.tick()
                cycles += 1
                touching = fake.arm.contact_force() > 0.0
                now = robot.contact_force() > 0.0
                if now and not was and not touching:
                    onsets += 1
                was = now
            loop.pipeline.stop()
            res = loop.result(timeout)
        rep.cycles += cycles
        rep.false_contacts += onsets
        rep.descents_with_false_contact += onsets > 0
        rep.outcomes[res.outcome] = rep.outcomes.get(res.outcome, 0) + 1
        if res.outcome != "released":
            rep.reasons.append(res.reason)
        rep.watchdog_stops += fake.watchdog_stops
        rep.script_errors += len(fake.errors)
        if progress is not None:
            progress(i + 1, rep)
    return rep


def touches(speeds: Any = TOUCH_SPEEDS, *, controller: str = "cb3", stiffness: float = TOUCH_STIFFNESS,
            trials: int = 20, seed: int = 100, force_noise: float | None = None) -> list[dict[str, float]]:
    """Guarded descents onto the table at each speed (m/s): per speed the median and largest delay (s) from
    the first touch to the driver's contact and the true force (N) then, and the trials missed."""
    out = []
    for v in speeds:
        delays, forces, missed = [], [], 0
        for k in range(trials):
            robot, fake = make_stand_in(controller, table_gap=0.004, seed=seed + k, force_noise=force_noise,
                                        stiffness=stiffness)
            with robot:
                robot.speed_linear([0.0, 0.0, -float(v), 0.0, 0.0, 0.0], accel=0.5)
                t_touch = None
                for _ in range(int(1.0 / robot.period)):
                    robot.step(robot.period)
                    f_true = fake.arm.contact_force()
                    if f_true > 0 and t_touch is None:
                        t_touch = robot.time()
                    if robot.contact_force() > 0 and t_touch is not None:
                        delays.append(robot.time() - t_touch)
                        forces.append(f_true)
                        break
                else:
                    missed += 1
                robot.stop(decel=0.5)
        d = np.asarray(delays) if delays else np.array([math.nan])
        F = np.asarray(forces) if forces else np.array([math.nan])
        out.append({"speed": float(v), "rate": float(v) * stiffness, "delay_median": float(np.median(d)),
                    "delay_max": float(np.max(d)), "force_median": float(np.median(F)), "force_max": float(np.max(F)),
                    "missed": missed, "trials": trials})
    return out


def rest_noise(robot: Any, seconds: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    """(offset (3,), spread (3,)) N of the TCP force of a connected URRobot at rest over ``seconds``."""
    n = max(10, int(round(seconds / robot.period)))
    robot.zero_force(samples=n)
    return robot.detector.offset.copy(), robot.detector.rest_std.copy()


def settings_report(settings: Any, noise_std: float, cycles: int = 2_000_000,
                    descent_cycles: int = 500) -> dict[str, Any]:
    """False-alarm rate and detection delays of ``settings`` for ``noise_std`` N per axis per cycle (synthetic)."""
    from place_safe.robot.contact_detector import detection_delay, false_alarm_rate

    fa = false_alarm_rate(settings, noise_std, cycles=cycles)
    upper = (fa["alarms"] + 3.0) / fa["cycles"]  # ~95 % upper bound (rule of three at zero alarms)
    rep = {"noise_std": noise_std, "threshold": settings.threshold(noise_std),
           "lateral_threshold": settings.lateral_threshold(noise_std), "window": settings.window,
           "persistence": settings.persistence, "cycles": int(fa["cycles"]), "alarms": int(fa["alarms"]),
           "false_alarms_per_cycle": fa["per_cycle"], "false_alarms_per_cycle_95": upper,
           "false_alarms_per_descent_95": upper * descent_cycles, "steps": [], "ramps": []}
    for step in (8.0, 10.0, 15.0):
        rep["steps"].append({"step": step, **detection_delay(settings, noise_std, step=step, trials=1000)})
    for ramp in (100.0, 200.0, 400.0):
        rep["ramps"].append({"ramp": ramp, **detection_delay(settings, noise_std, ramp=ramp, trials=1000)})
    return rep


def format_settings_report(rep: dict[str, Any]) -> str:
    lines = [f"noise {rep['noise_std']:.2f} N per axis per cycle -> axial threshold {rep['threshold']:.2f} N "
             f"(lateral {rep['lateral_threshold']:.2f} N), {rep['window']}-cycle average, persistence "
             f"{rep['persistence']} cycles",
             f"false alarms: {rep['alarms']} in {rep['cycles']} cycles of noise "
             f"(<= {rep['false_alarms_per_cycle_95']:.1e} per cycle, <= {rep['false_alarms_per_descent_95']:.1e} "
             f"per 500-cycle descent, 95 %)"]
    for s in rep["steps"]:
        lines.append(f"touch, a {s['step']:.0f} N step: detected after {s['delay_median'] * 1e3:.0f} ms median, "
                     f"{s['delay_p95'] * 1e3:.0f} ms 95th pct; missed {s['missed'] * 100:.1f} %")
    for r in rep["ramps"]:
        lines.append(f"touch, a {r['ramp']:.0f} N/s ramp: detected after {r['delay_median'] * 1e3:.0f} ms at "
                     f"{r['force_median']:.1f} N median, {r['delay_p95'] * 1e3:.0f} ms at {r['force_p95']:.1f} N "
                     "95th pct")
    return "\n".join(lines)


__all__ = ["TablePlaneSource", "TruthEstimator", "TRUTH_SIGMA", "make_stand_in", "DescentReport", "descents", "touches",
           "rest_noise", "settings_report", "format_settings_report"]
