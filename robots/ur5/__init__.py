"""The UR5 (CB series) with parallel gripper, TMF8820 wrist mount and held cup.

``config.json`` is the single source of truth; ``ur5.xml`` (MJCF) and ``ur5.urdf`` are generated from it
by :mod:`place_safe.robots.ur5.generate` and committed.
"""
