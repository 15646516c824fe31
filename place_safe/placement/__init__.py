"""Placement: the decision (state machine) and the loop that connects a frame source, an estimator,
the fusion and a robot (the same loop on the real arm, in MuJoCo and in scenario runs)."""

from place_safe.placement.config import PlacementConfig
from place_safe.placement.machine import FINAL, Command, CommandKind, Phase, PlacementMachine, RobotState, Transition

__all__ = ["Phase", "FINAL", "PlacementConfig", "PlacementMachine", "RobotState", "Command", "CommandKind",
           "Transition"]
