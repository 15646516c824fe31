"""The transition table against the machine, and the diagram in docs/placement.md against the table.

The machine is driven through the real PlacementLoop with the kinematic fakes of ``placement_fakes``: a
clean release, refusals in every phase (tilt, obstacles, a dead sensor), robot faults injected in every
phase, a table that drops during the check, a gripper that does not open and contact at the very start.
Every transition the runs log must be a row of :data:`TRANSITIONS`, and every row must be taken by some run.
"""

from __future__ import annotations

import ast
import re
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from place_safe.placement.diagram import mermaid
from place_safe.placement.loop import PlacementLoop
from place_safe.placement.machine import Phase
from place_safe.placement.transitions import FINAL, INITIAL, TRANSITIONS, allowed

from placement_fakes import KinematicRobot, TruthEstimator, TruthSource, tilted

pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning")

ROOT = Path(__file__).resolve().parents[2]
TABLE = {(a, b) for a, b, _ in TRANSITIONS}


class HookedRobot(KinematicRobot):
    """A kinematic robot that calls ``hook(robot, phase)`` every control period (the loop's phase then)."""

    def __init__(self, hook=None, **kw) -> None:
        super().__init__(**kw)
        self.hook = hook
        self.loop: PlacementLoop | None = None

    def step(self, dt: float) -> None:
        super().step(dt)
        if self.hook is not None and self.loop is not None:
            self.hook(self, self.loop.machine.phase)


def run(robot: HookedRobot, source=None, timeout: float = 20.0) -> list[tuple[Phase, Phase]]:
    """The (from, to) phase pairs of one placement, in order."""
    robot.loop = PlacementLoop(robot, source if source is not None else TruthSource(robot), TruthEstimator())
    res = robot.loop.run(timeout=timeout)
    return [(t.source, t.target) for t in res.transitions]


def fault_in(phase: Phase, after: int = 1):
    """A hook that latches a protective stop on the ``after``-th period spent in ``phase``."""
    seen = [0]

    def hook(robot, now):
        if now == phase:
            seen[0] += 1
            if seen[0] == after:
                robot._fault = "protective stop"
    return hook


def drop_table_at_check(robot, now):
    """The table drops 4 mm once the machine checks (the surface moved away under the cup)."""
    if now == Phase.CHECK and not getattr(robot, "dropped", False):
        robot.dropped = True
        robot.surface_z -= 0.004


def broken_gripper(robot: HookedRobot) -> HookedRobot:
    def gripper(open):
        raise RuntimeError("gripper I/O error")
    robot.gripper = gripper
    return robot


def askew(robot: HookedRobot, deg: float) -> HookedRobot:
    tilted(robot, deg)
    return robot


def doubt_at_check(robot: HookedRobot) -> HookedRobot:
    """The surface map doubts footprint points at the first check only (the plane refined at rest moved a zone's
    reading over the line): the machine goes back up to look again from over them, then places the cup."""
    def hook(robot, now):
        loop = robot.loop
        if getattr(loop, "_doubt_hooked", False):
            return
        loop._doubt_hooked = True
        verdict = loop._footprint_verdict

        def doubtful(fused, tcp):
            v = verdict(fused, tcp)
            if loop.machine.phase != Phase.CHECK or loop.machine._recheck is not None or v is None:
                return v
            return replace(v, problem="zone 7 over the cup's footprint +3 mm off the surface (part of it covered: "
                                      "clutter or step)", recheck_shift=np.array([0.0, 0.0, 0.1]),
                           close_frames=v.close_frames or 0)
        loop._footprint_verdict = doubtful
    robot.hook = hook
    return robot


def scenario_runs() -> dict[str, list[tuple[Phase, Phase]]]:
    runs = {
        "release": run(HookedRobot(height=0.12)),
        "tilted": run(askew(HookedRobot(height=0.12), 15.0)),
        "obstacle in approach": run(HookedRobot(height=0.12, obstacle_z=0.03)),
        "obstacle in descend": run(HookedRobot(height=0.12, obstacle_z=0.009)),  # 9 mm: in the slow band
        "contact at the start": run(HookedRobot(height=0.0)),
        "table drops at the check": run(HookedRobot(drop_table_at_check, height=0.12)),
        "gripper does not open": run(broken_gripper(HookedRobot(height=0.1))),
        "footprint in doubt at the check": run(doubt_at_check(HookedRobot(height=0.12))),
    }
    dead = HookedRobot(height=0.12)
    runs["dead sensor"] = run(dead, TruthSource(dead, error_after=0.0))
    for phase in (Phase.IDLE, Phase.APPROACH, Phase.DESCEND, Phase.CHECK, Phase.RELEASE, Phase.REFUSE):
        robot = HookedRobot(fault_in(phase), height=0.12)
        if phase == Phase.REFUSE:
            tilted(robot, 15.0)
        runs[f"fault in {phase.value}"] = run(robot)
    return runs


@pytest.fixture(scope="module")
def runs():
    return scenario_runs()


@pytest.mark.slow  # 17 placements through the loop, about 17 s together
def test_every_transition_the_machine_makes_is_in_the_table(runs):
    for name, pairs in runs.items():
        unknown = [f"{a.name} -> {b.name}" for a, b in pairs if (a, b) not in TABLE]
        assert not unknown, f"{name}: transitions missing from TRANSITIONS: {unknown}"


@pytest.mark.slow  # 17 placements through the loop, about 17 s together
def test_every_row_of_the_table_is_taken_by_the_machine(runs):
    taken = {pair for pairs in runs.values() for pair in pairs}
    never = sorted(f"{a.name} -> {b.name}" for a, b in TABLE - taken)
    assert not never, f"rows of TRANSITIONS the machine never takes: {never}"


@pytest.mark.slow  # 17 placements through the loop, about 17 s together
def test_runs_start_in_the_initial_phase_and_end_in_a_final_one(runs):
    for name, pairs in runs.items():
        assert pairs and pairs[0][0] == INITIAL and pairs[-1][1] in FINAL, name
        assert all(b == c for (_, b), (c, _) in zip(pairs, pairs[1:])), name  # a chain


@pytest.mark.slow
@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(height=st.floats(0.02, 0.3), tilt=st.floats(0.0, 12.0), fault_phase=st.sampled_from(list(Phase)),
       after=st.integers(1, 200), drop=st.floats(-0.02, 0.02), obstacle=st.none() | st.floats(0.0, 0.05))
def test_random_placements_take_only_transitions_of_the_table(height, tilt, fault_phase, after, drop, obstacle):
    fault = fault_in(fault_phase, after)

    def hook(robot, now):
        fault(robot, now)
        if now == Phase.CHECK and not getattr(robot, "dropped", False):
            robot.dropped = True
            robot.surface_z += drop

    robot = askew(HookedRobot(hook, height=height, obstacle_z=obstacle), tilt)
    pairs = run(robot, timeout=15.0)
    assert all(p in TABLE for p in pairs), [f"{a.name} -> {b.name}" for a, b in pairs if (a, b) not in TABLE]


def test_each_phase_pair_has_one_row_and_final_phases_have_none():
    pairs = [(a, b) for a, b, _ in TRANSITIONS]
    assert len(pairs) == len(set(pairs))
    assert not any(a in FINAL for a, _ in pairs)
    assert all(label.strip() and ":" not in label for _, _, label in TRANSITIONS)  # a colon ends a Mermaid label
    assert allowed(Phase.CHECK, Phase.RELEASE) and not allowed(Phase.APPROACH, Phase.RELEASE)


def test_only_check_releases_in_the_table_and_in_the_code():
    """The release rule's only door: the table has one way into RELEASE, and the machine's code names
    RELEASE as a target once (in the CHECK handler)."""
    assert [a for a, b, _ in TRANSITIONS if b == Phase.RELEASE] == [Phase.CHECK]
    tree = ast.parse((ROOT / "place_safe/placement/machine.py").read_text())
    handlers = [f.name for f in ast.walk(tree) if isinstance(f, ast.FunctionDef)
                for c in ast.walk(f) if isinstance(c, ast.Call) and getattr(c.func, "attr", "") == "_go"
                and ast.unparse(c.args[0]) == "Phase.RELEASE"]
    assert handlers == ["_on_check"]


def test_docs_placement_holds_exactly_the_generated_diagram():
    doc = (ROOT / "docs/placement.md").read_text()
    blocks = re.findall(r"```mermaid\n.*?```\n", doc, flags=re.S)
    assert blocks == [mermaid()], "docs/placement.md: run `python -m place_safe.placement.diagram` and paste it"
