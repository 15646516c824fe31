"""The placement's time budget, check sizing from the fused uncertainty, speeds within the robot's limits
and the liquid's lateral acceleration on every sideways command."""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from place_safe.fusion.plane_filter import FusedPlane
from place_safe.fusion.surface_map import FootprintVerdict
from place_safe.placement.budget import BEFORE_RELEASE, BUCKETS, budget_limits, format_budget, median_budget
from place_safe.placement.loop import within_robot_limits
from place_safe.placement.machine import CommandKind, Phase, PlacementConfig, PlacementMachine
from place_safe.robot.interface import RobotLimits
from tests.placement.test_machine import FakeWorld, run


def test_the_budget_accounts_for_the_whole_placement():
    w = FakeWorld(height=0.3)
    m = run(w)
    assert m.outcome == "released"
    assert set(m.budget) <= set(BUCKETS)
    t_end = m.log[-1].time
    assert abs(sum(m.budget.values()) - t_end) < 0.02  # every tick's time went to one part
    t_release = next(tr.time for tr in m.log if tr.target == Phase.RELEASE)
    before = sum(m.budget.get(b, 0.0) for b in BEFORE_RELEASE)
    assert abs(before - t_release) < 0.02
    for part in ("cruise", "brake", "slow band", "stop", "check frames", "release", "retreat"):
        assert m.budget.get(part, 0.0) > 0.0, part


def test_budget_table_names_every_part_and_its_limit():
    cfg = PlacementConfig()
    limits = budget_limits(cfg, 1 / 30, 0.094)
    assert set(limits) == set(BUCKETS) and all(limits.values())
    med = median_budget([{"cruise": 1.0, "brake": 0.5}, {"cruise": 2.0}])
    assert med["cruise"] == 1.5 and med["brake"] == 0.25 and med["survey"] == 0.0
    text = format_budget(med, limits, 2)
    assert "cruise" in text and "to release" in text and "lateral_accel" in text
    assert format_budget({}, limits, 0) == "time budget: no releases"


def _plane(std_angle, std_offset, tilt=0.0):
    n = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    return FusedPlane(n, 0.0, tilt, std_angle, std_offset, 7, 1.0, 7, stamps=tuple(0.1 * i for i in range(7)))


@given(st.floats(0.0, math.radians(6)), st.floats(0.0, 0.004), st.floats(0.0, math.radians(4)))
def test_the_check_waits_for_more_frames_the_less_certain_the_plane(std_angle, std_offset, tilt):
    m = PlacementMachine()
    cfg = m.config
    need = m.check_frames_needed(_plane(std_angle, std_offset, tilt))
    assert cfg.check_frames <= need <= max(cfg.check_frames, cfg.max_check_frames)
    # sized from the fused uncertainty: the tilt must clear max_tilt by twice its confidence margin
    from place_safe.placement.rules import confidence_margin, tilt_sigma

    p = _plane(std_angle, std_offset, tilt)
    near = tilt + 2.0 * confidence_margin(tilt_sigma(p), cfg) > cfg.max_tilt
    if std_angle > 0.5 * cfg.max_std_angle or std_offset > 0.5 * cfg.max_std_offset or near:
        assert need == max(cfg.check_frames, cfg.max_check_frames)
    else:
        assert need == cfg.check_frames


def test_a_well_measured_tilted_plane_needs_no_extra_check_frames_a_doubtful_one_does():
    cfg = PlacementConfig()
    m = PlacementMachine(cfg)
    assert m.check_frames_needed(_plane(math.radians(0.05), 0.0002, math.radians(4.0))) == cfg.check_frames
    assert m.check_frames_needed(_plane(math.radians(0.05), 0.0002, math.radians(4.97))) == cfg.max_check_frames
    assert m.check_frames_needed(_plane(math.radians(1.5), 0.0002, math.radians(1.0))) == cfg.max_check_frames


def test_a_malformed_plane_needs_the_most_check_frames():
    m = PlacementMachine()
    assert m.check_frames_needed(object()) == max(m.config.check_frames, m.config.max_check_frames)


class _Arm:
    def __init__(self, limits):
        self.limits = limits


@given(st.floats(0.01, 3.0), st.floats(0.01, 50.0))
def test_the_loop_plans_within_the_robot_limits(v, a):
    cfg = within_robot_limits(PlacementConfig(), _Arm(RobotLimits(max_linear_speed=v, max_linear_accel=a)))
    for name in ("approach_speed", "descend_speed", "survey_speed", "retreat_speed", "near_surface_speed"):
        assert getattr(cfg, name) <= v + 1e-12
    assert cfg.accel <= a + 1e-12 and cfg.lateral_accel <= a + 1e-12


def test_a_robot_without_readable_limits_is_planned_at_the_default_limits():
    cfg = PlacementConfig(approach_speed=0.5)  # a cruise sized for an arm that states it can
    default = within_robot_limits(cfg, _Arm(RobotLimits()))
    assert default.approach_speed == RobotLimits().max_linear_speed < cfg.approach_speed

    class Broken:
        @property
        def limits(self):
            raise RuntimeError("no limits")

    assert within_robot_limits(cfg, Broken()) == default
    assert within_robot_limits(cfg, object()) == default
    assert within_robot_limits(cfg, _Arm(None)) == default


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(height=st.floats(0.08, 0.4), shift=st.floats(0.0, 0.08), angle=st.floats(-math.pi, math.pi))
def test_every_sideways_command_respects_the_liquids_lateral_acceleration(height, shift, angle):
    # the footprint must be surveyed from a pose `shift` sideways: the machine moves out and back
    w = FakeWorld(height=height)
    move = np.array([shift * math.cos(angle), shift * math.sin(angle), 0.0])
    state = {"n": 0}

    def verdict():
        state["n"] += 1
        seen = 3 if state["n"] > 60 else 0
        return FootprintVerdict(observed=seen, supported=seen, in_view=seen > 0 or shift == 0.0, view_margin=1.0,
                                look_shift=move if seen == 0 else np.zeros(3), certify_margin=0.0)

    m = PlacementMachine()
    while not m.finished and w.t < 20.0:
        w.apply(m.step(w.state(), w.plane(), None, verdict()))
    for c in w.commands:
        if c.kind == CommandKind.SPEED and np.linalg.norm(c.twist[:2]) > 0:
            assert c.accel <= m.config.lateral_accel + 1e-12
    assert m.finished


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(height=st.floats(0.22, 0.45), shift=st.floats(0.02, 0.08), angle=st.floats(-math.pi, math.pi))
def test_the_survey_shares_the_speed_limit_and_keeps_above_unseen_ground(height, shift, angle):
    """Out to see the footprint while descending and back over the landing spot: no command asks the arm
    for more than approach_speed in all (sideways and down together), and after the footprint was certified
    the cup goes below traverse_clearance only within OVER_FOOTPRINT of the margin of the landing spot."""
    from place_safe.placement.machine import OVER_FOOTPRINT

    w = FakeWorld(height=height)
    start = w.pos.copy()
    target = start + np.array([shift * math.cos(angle), shift * math.sin(angle), 0.0])
    seen = {"n": 0}

    def verdict():
        off = target - w.pos
        off[2] = 0.0
        if float(np.linalg.norm(off)) < 0.003 and w.pos[2] <= 0.2:  # close and centred: frames certify it
            seen["n"] += 1
        n = min(seen["n"], 3)
        return FootprintVerdict(observed=n, supported=n, in_view=True, view_margin=1.0, look_shift=off,
                                certify_margin=float(w.pos[2]) - 0.2)

    m = PlacementMachine()
    cfg = m.config
    low_and_away = []
    farthest = 0.0
    while not m.finished and w.t < 20.0:
        w.apply(m.step(w.state(), w.plane(), None, verdict()))
        away = float(np.linalg.norm((w.pos - start)[:2]))
        farthest = max(farthest, away)
        if seen["n"] >= 3 and away > OVER_FOOTPRINT * cfg.footprint_margin + 1e-3 \
                and w.pos[2] < cfg.traverse_clearance - 1e-3:
            low_and_away.append((w.t, away, float(w.pos[2])))
    for c in w.commands:
        if c.kind == CommandKind.SPEED:
            assert float(np.linalg.norm(c.twist[:3])) <= cfg.approach_speed + 0.002  # (twists rounded to mm/s)
    assert seen["n"] >= 3 and farthest > shift - 0.003  # it did go out and certify the footprint
    assert not low_and_away, low_and_away[:3]
    assert m.outcome == "released", m.reason
