"""The placement machine's transition table: which phase may follow which, and on what (data, no logic).

Concept: :data:`TRANSITIONS` lists every change of phase that
:class:`~place_safe.placement.machine.PlacementMachine` can make, as ``(from_phase, to_phase, label)``;
the label is a short summary of the conditions, for people. The machine decides with its own code; this
table describes it, and ``tests/placement/test_transitions.py`` drives the machine through every row and
fails on a transition the machine makes that the table lacks, or a row the machine never takes.
:mod:`place_safe.placement.diagram` draws ``docs/placement.md``'s diagram from it.

Staying in a phase is not a transition (the survey moves inside APPROACH; see :data:`NOTES`). A phase pair
may appear once only; its label names every way the machine takes it.
"""

from __future__ import annotations

from place_safe.placement.machine import FINAL, Phase

#: The phase a new machine starts in.
INITIAL = Phase.IDLE

_REFUSE_MOVING = ("tilted / stale / no plane / no support under the footprint / obstacle contact / "
                  "travel limit / deadline")
_ABORT = "robot fault, invalid state, clock frozen/backwards, internal error"

#: Every phase change of the machine: (from, to, label).
TRANSITIONS: tuple[tuple[Phase, Phase, str], ...] = (
    (Phase.IDLE, Phase.APPROACH, "fused plane seen"),
    (Phase.IDLE, Phase.REFUSE, "no plane within acquire_timeout / sensor timeout"),
    (Phase.APPROACH, Phase.DESCEND, "clearance < slow_clearance"),
    (Phase.APPROACH, Phase.CHECK, "contact within contact_limit"),
    (Phase.DESCEND, Phase.CHECK, "clearance <= stop_clearance, or contact within contact_limit"),
    (Phase.APPROACH, Phase.REFUSE, _REFUSE_MOVING),
    (Phase.DESCEND, Phase.REFUSE, _REFUSE_MOVING),
    (Phase.CHECK, Phase.RELEASE, "release rule holds (open gripper)"),
    (Phase.CHECK, Phase.DESCEND, "still above release_clearance (at most max_checks times)"),
    (Phase.CHECK, Phase.APPROACH, "footprint points vetoed or in doubt that no second look has seen "
                                  "(once, up first)"),
    (Phase.CHECK, Phase.REFUSE, "tilted / not planar / stale by check_timeout / no support under the footprint / "
                                "obstacle / arm not at rest / too few fresh planes by check_timeout / max_checks"),
    (Phase.RELEASE, Phase.DONE, "settled and retreated (or retreat deadline, or a robot fault once released)"),
    (Phase.RELEASE, Phase.ABORTED, "the gripper did not open"),
    (Phase.REFUSE, Phase.ABORTED, "retreated holding the cup (or retreat deadline, or a robot fault)"),
    (Phase.IDLE, Phase.ABORTED, _ABORT),
    (Phase.APPROACH, Phase.ABORTED, _ABORT),
    (Phase.DESCEND, Phase.ABORTED, _ABORT),
    (Phase.CHECK, Phase.ABORTED, _ABORT),
)

#: What happens inside a phase without leaving it (drawn as notes).
NOTES: dict[Phase, str] = {
    Phase.APPROACH: "survey: while the landing footprint is not yet seen from close, move the sensor over it "
                    "and come back while descending",
}


def allowed(source: Phase, target: Phase) -> bool:
    """Whether the table has the change ``source -> target``."""
    return any(a == source and b == target for a, b, _ in TRANSITIONS)


__all__ = ["INITIAL", "FINAL", "TRANSITIONS", "NOTES", "allowed"]
