"""place_safe: recover the plane under a robot gripper from TMF8820 transient histograms.

Conventions (see ``docs`` in the README): SI units inside (metres, radians, seconds); a plane is
``n . x = d`` in the sensor frame with unit normal ``n`` pointing away from the sensor (``n_z > 0``)
and ``d > 0`` the perpendicular distance. Degrees appear only at the command line and in reports.
"""

__version__ = "0.1.0"
