"""Fusion: per-frame sensor-frame plane estimates + the sensor pose at each frame's measurement time
-> one robust surface in the robot base frame."""

from place_safe.fusion.plane_filter import FusedPlane, PlaneFilter, clearance_along, plane_to_base

__all__ = ["FusedPlane", "PlaneFilter", "clearance_along", "plane_to_base"]
