"""The robot: the narrow interface placement drives (real UR5 over ur-rtde, or MuJoCo), its limits,
and UR5 kinematics (pytorch-kinematics, imported lazily)."""

from place_safe.robot.interface import Robot, RobotLimits, TrapezoidProfile, check_pose, check_twist

__all__ = ["Robot", "RobotLimits", "TrapezoidProfile", "check_pose", "check_twist"]
