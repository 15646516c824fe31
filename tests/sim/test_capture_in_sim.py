"""Capture in MuJoCo (SimRobot + SimToF) and the mount fit on it. The planes handed to the fit are the
simulator's truth here, so this is a convention check of capture geometry + fit (frames, poses, joints,
the MuJoCo mount error), not a measurement of plane recovery."""

from __future__ import annotations

import math

import numpy as np
import pytest

from place_safe.calibration.capture import SweepPlan, capture_sweep
from place_safe.calibration.mount import fit_mount, flange_poses
from place_safe.geometry import Plane
from place_safe.io.frame_file import load_frames
from place_safe.sim.world import sim_world


@pytest.mark.slow
def test_sim_capture_then_mount_fit_recovers_a_perturbed_mount(tmp_path):
    err = [0.003, -0.003, 0.00265, math.radians(1.2), math.radians(-1.2), math.radians(1.0)]  # 5 mm, 2 deg
    world = sim_world("level_table", mount_error=err, hold_cup=False)
    plan = SweepPlan(distances=[0.1, 0.2], incidences=[0.0, math.radians(20)],
                     azimuths=[math.radians(a) for a in (0, 90, 180, 270)], settle_s=0.1, speed=0.2)
    out = tmp_path / "cap.jsonl"
    res = capture_sweep(world.robot, world.tof, plan, out, plane=world.table_plane_base(), tool=world.robot.tool,
                        progress=False)
    assert res.captured == 10 and not res.refused
    frames = load_frames(out)
    # the capture's ground truth uses the NOMINAL mount: off from the simulator's by the mount error
    off = [abs(f.truth.offset - f.extra["meta"]["source_truth"]["offset"]) for f in frames]
    assert max(off) > 0.001
    planes = [Plane.from_dict(f.extra["meta"]["source_truth"]) for f in frames]
    fit = fit_mount(flange_poses(frames), planes, world.robot.tool.flange_T_sensor)
    et, er = fit.error_to(world.true_flange_T_sensor())
    assert et < 0.001 and math.degrees(er) < 0.2, fit.summary()
    np.testing.assert_allclose(fit.plane_offset, world.table_plane_base()[1], atol=0.001)
