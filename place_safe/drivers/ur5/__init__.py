"""The UR5 over ur_rtde: robot driver, grippers, robot configuration files and a faithful CI stand-in.

* :class:`~place_safe.drivers.ur5.rtde_robot.URRobot` -- the :class:`~place_safe.robot.interface.Robot` on
  ``rtde_control`` / ``rtde_receive`` / ``rtde_io`` (imported only when connecting).
* :class:`~place_safe.drivers.ur5.config.URConfig` -- ``robots/ur5/real.toml`` / ``sim.toml``.
* :mod:`~place_safe.drivers.ur5.gripper` -- digital-output and Robotiq URCap-socket grippers.
* :mod:`~place_safe.drivers.ur5.fake_rtde` -- fake ur_rtde interfaces over a kinematic or MuJoCo arm.
"""

from place_safe.drivers.ur5.config import URConfig, packaged_config
from place_safe.drivers.ur5.rtde_robot import URRobot

__all__ = ["URConfig", "URRobot", "packaged_config"]
