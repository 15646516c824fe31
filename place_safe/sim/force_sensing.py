"""Contact and force sensing of the simulated UR5: the physics (MuJoCo's contact forces on the gripper and the
held cup), the force a UR controller reports (truth + a constant offset + white noise, read once a control
period into a :class:`~place_safe.robot.contact_detector.ContactDetector`) and the protective stop's force test.

Units: N, base frame for vectors (the physics is summed in the world frame). ``controller`` ``cb3``: 3.6 N per
axis, the CB3's motor-current estimate; ``e-series``: 1 N (:data:`place_safe.drivers.ur5.fake_rtde.FORCE_NOISE`).
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from place_safe.drivers.ur5.fake_rtde import FORCE_NOISE, FORCE_OFFSET
from place_safe.robot.contact_detector import ContactDetector, DetectorSettings
from place_safe.sim.arm_model import ARM, CUP, ENVIRONMENT, GRIPPER, ArmModel
from place_safe.sim.payload import HeldCup

#: N, how far above the larger of the limit and the force at the stop a cleared contact stop re-arms
REARM_MARGIN = 5.0


class ForceSensing:
    """What the arm feels. :meth:`contact_forces` is the physics; :meth:`force_reading` the controller's noisy
    estimate; :meth:`tick` feeds the detector once every ``sense_ticks`` physics steps; :meth:`overload` is
    the protective stop's test (with the grace a cleared stop leaves: :meth:`rearm`)."""

    def __init__(self, arm: ArmModel, cup: HeldCup, *, controller: str, control_period: float, sense_ticks: int,
                 force_noise: float | None = None, force_offset: Any = None, force_seed: int = 0,
                 detector: DetectorSettings | None = None) -> None:
        self.arm, self.cup = arm, cup
        self.force_noise = float(FORCE_NOISE[controller] if force_noise is None else force_noise)
        self.force_offset = np.asarray(FORCE_OFFSET if force_offset is None else force_offset, dtype=float)
        self._rng = np.random.default_rng(force_seed)
        self.detector = ContactDetector(detector if detector is not None else DetectorSettings.for_controller(
            controller, period=control_period))
        self.sense_ticks = sense_ticks
        self._sense_left = sense_ticks
        self.true_force_peak = 0.0  # N, the largest net contact force since construction
        self.last_force = 0.0  # N, the larger of the net and the largest single contact force, last step
        self.grace = 0.0  # N, the stop threshold while a cleared stop's force lasts (0: none)

    def contact_forces(self) -> tuple[np.ndarray, float]:
        """(net force on gripper + held cup from the environment (3,), world frame; max single-contact force on
        any robot part)."""
        arm = self.arm
        d = arm.data
        n = d.ncon
        if n == 0:
            return np.zeros(3), 0.0
        g = d.contact.geom[:n]
        c1, c2 = arm.geom_class[g[:, 0]], arm.geom_class[g[:, 1]]
        held = self.cup.holding()
        ours = (c1 == ARM) | (c1 == GRIPPER) | ((c1 == CUP) & held)
        ours2 = (c2 == ARM) | (c2 == GRIPPER) | ((c2 == CUP) & held)
        env1, env2 = c1 == ENVIRONMENT, c2 == ENVIRONMENT
        sel = np.flatnonzero((ours & env2) | (ours2 & env1))
        net = np.zeros(3)
        worst = 0.0
        f6 = np.zeros(6)
        for i in sel:
            mujoco.mj_contactForce(arm.model, d, int(i), f6)
            fw = d.contact.frame[i].reshape(3, 3).T @ f6[:3]  # force of geom1 on geom2, world frame
            on_ours = fw if ours2[i] else -fw
            worst = max(worst, float(np.linalg.norm(fw)))
            if (c2[i] if ours2[i] else c1[i]) >= GRIPPER:
                net += on_ours
        return net, worst

    def true_contact_vector(self) -> np.ndarray:
        """N: the net force of the environment on the gripper and the held cup (physics, base frame)."""
        R = self.arm.world_T_base()[:3, :3]
        return R.T @ self.contact_forces()[0]

    def force_reading(self) -> np.ndarray:
        """One TCP force reading as the controller gives it (N, base frame): truth + offset + noise."""
        f = self.true_contact_vector() + self.force_offset
        if self.force_noise:
            f = f + self._rng.normal(0.0, self.force_noise, 3)
        return f

    def zero(self, samples: int) -> np.ndarray:
        """Take the rest reading (``samples`` readings, at least 2, at the current state) for the detector."""
        offset, _ = self.detector.zero([self.force_reading() for _ in range(max(2, int(samples)))])
        return offset

    def tick(self) -> None:
        """One physics step: every ``sense_ticks`` steps one controller cycle of the force estimate goes into the
        detector (approach direction: the tool axis)."""
        self._sense_left -= 1
        if self._sense_left <= 0:
            self._sense_left = self.sense_ticks
            self.detector.update(self.force_reading(), self.arm.base_T_site(self.arm.tcp)[:3, 2])

    def overload(self, limit: float) -> str | None:
        """The protective stop's reason when the net force or any single contact exceeds ``limit`` N (or the
        grace a cleared stop left, until the force drops below ``limit``), else None. Keeps the peak."""
        net, worst = self.contact_forces()
        f = float(np.linalg.norm(net))
        self.last_force = max(f, worst)
        self.true_force_peak = max(self.true_force_peak, f)
        thr = limit
        if self.grace > 0:
            if self.last_force < thr:
                self.grace = 0.0
            else:
                thr = max(thr, self.grace)
        if f > thr or worst > thr:
            return (f"protective stop: contact force {max(f, worst):.1f} N exceeds {thr:.1f} N "
                    "(collision or pressing too hard); holding position and object")
        return None

    def rearm(self, limit: float) -> None:
        """After a stop is cleared: stop again only above the force that stopped it (so the arm can move away
        from what it pressed on), until the force drops below ``limit``."""
        self.grace = max(limit, self.last_force) + REARM_MARGIN


__all__ = ["ForceSensing", "REARM_MARGIN"]
