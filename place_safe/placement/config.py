"""Placement settings: the thresholds, speeds and deadlines of :class:`~place_safe.placement.machine.PlacementMachine`.

Concept: one :class:`PlacementConfig` is every number a placement is decided by, each declared once with its
physical range and unit (``Field(gt/ge/lt/le, description=unit)``, :class:`~place_safe.config.ParamModel`), so
construction, the placement JSON file and the robot file's ``[placement]`` overrides are all checked the same
way, one line naming the field and its range. SI units (m, m/s, m/s^2, rad, s, N).
"""

from __future__ import annotations

import math
from typing import ClassVar

from pydantic import Field, model_validator

from place_safe.config import ParamModel


class PlacementConfig(ParamModel):
    """Thresholds and speeds of a placement (SI units; the JSON file holds the same numbers)."""

    what: ClassVar[str] = "placement config"

    # m/s at most while the surface is far (slower near it: placement/speed.py); the loop caps it at the robot
    # file's max_linear_speed (sim.toml 0.5, real.toml 0.1), which then sets the cruise
    approach_speed: float = Field(0.5, gt=0.0, le=1.0, description="m/s")
    # m/s in the slow band (a touch of a mis-sensed surface at this speed stays gentle)
    descend_speed: float = Field(0.025, gt=0.0, le=0.5, description="m/s")
    # m/s^2 for speed changes and stops along the tool axis (the loop caps it at the robot's limit)
    accel: float = Field(1.2, gt=0.0, le=10.0, description="m/s^2")
    # m/s^2 at most sideways (survey): the liquid's lateral acceleration (speed.slosh_rise)
    lateral_accel: float = Field(1.2, gt=0.0, le=10.0, description="m/s^2")
    # m: reacting sensor_latency late and braking at accel still stops this far above the surface (the slow band:
    # a box the map missed is met slowly)
    brake_margin: float = Field(0.010, ge=0.0, le=0.1, description="m")
    # m/s^2: the hard stop when the cup touches something above the surface
    obstacle_decel: float = Field(4.0, gt=0.0, le=50.0, description="m/s^2")
    # m: APPROACH -> DESCEND below this cup clearance
    slow_clearance: float = Field(0.010, gt=0.0, le=1.0, description="m")
    # m: DESCEND -> CHECK at or below this clearance
    stop_clearance: float = Field(0.003, ge=0.0, le=0.1, description="m")
    # m: release only at or below this clearance (or in contact)
    release_clearance: float = Field(0.005, gt=0.0, le=0.1, description="m")
    # rad: steepest surface a cup may be put on
    max_tilt: float = Field(math.radians(5.0), gt=0.0, le=math.pi / 4, description="rad")
    # rad: refuse already while approaching above this
    early_refuse_tilt: float = Field(math.radians(10.0), gt=0.0, le=math.pi / 2, description="rad")
    # rad: spread of the fused normals ("planar and consistent")
    max_std_angle: float = Field(math.radians(2.0), gt=0.0, le=math.pi / 4, description="rad")
    # m: spread of the fused anchors about the plane
    max_std_offset: float = Field(0.003, gt=0.0, le=0.1, description="m")
    # distinct planes measured after stopping that CHECK needs at least
    check_frames: int = Field(2, ge=1, le=1000, description="frames")
    # ... and waits for (if more than check_frames) when the fused plane is near a limit (rules.check_frames_needed)
    max_check_frames: int = Field(5, ge=1, le=1000, description="frames")
    check_timeout: float = Field(1.5, gt=0.0, le=60.0, description="s")  # s to gather them
    max_checks: int = Field(3, ge=1, le=100, description="retries")  # CHECK -> DESCEND retries
    # s: a fused plane whose newest frame is older is stale (4 frames at 10 Hz)
    plane_timeout: float = Field(0.5, gt=0.0, le=10.0, description="s")
    sensor_timeout: float = Field(0.5, gt=0.0, le=10.0, description="s")  # s without any frame
    acquire_timeout: float = Field(1.5, gt=0.0, le=60.0, description="s")  # s in IDLE to get a first plane
    # N: contact with the surface (well under the robot's protective stop)
    contact_force: float = Field(5.0, gt=0.0, le=200.0, description="N")
    # m: clearance this far below zero without contact = estimate is wrong
    max_penetration: float = Field(0.01, ge=0.0, le=0.1, description="m")
    # m: descent limit: a surface seen deeper than this below the start pose (along the cup's axis) is refused at
    # once, and the TCP never moves farther than this from the start pose
    max_travel: float = Field(0.6, gt=0.0, le=2.0, description="m")
    retreat_distance: float = Field(0.10, gt=0.0, le=1.0, description="m")  # m up after release or refusal
    retreat_speed: float = Field(0.05, gt=0.0, le=1.0, description="m/s")  # m/s
    release_settle: float = Field(0.3, ge=0.0, le=10.0, description="s")  # s between opening the gripper and retreating
    # m, radius of the cup bottom (rim touches first on a tilted surface)
    cup_radius: float = Field(0.035, ge=0.0, le=0.5, description="m")
    # m: contact counts as arrival only this close to the sensed surface, and never higher than what can tilt the
    # cup beyond max_tilt when it stands on it (rules.contact_limit: cup_radius tan(max_tilt) less the travel while the
    # touch is detected, 1.9 mm for 35 mm, 5 deg, 25 mm/s and 48 ms)
    contact_clearance: float = Field(0.005, gt=0.0, le=0.1, description="m")
    # s from a touch to the force reading over contact_force (the CB3 detector's 95th percentile: 48 ms; the arm moves on
    # meanwhile, so the clearance read at contact is that much travel below the touch); on the arm the robot file's own
    # detector sets it unless the placement file does (drivers.ur5.config.placement_config: e-Series 14 ms)
    contact_latency: float = Field(0.048, ge=0.0, le=1.0, description="s")
    # s after the stop command before planes count for CHECK (arm at rest)
    check_settle: float = Field(0.04, ge=0.0, le=10.0, description="s")
    # s: deadline of APPROACH + DESCEND together
    descent_timeout: float = Field(30.0, gt=0.0, le=600.0, description="s")
    # s: deadline of the retreat after a release or refusal
    retreat_timeout: float = Field(6.0, gt=0.0, le=600.0, description="s")
    # m the TCP may move in CHECK once stopped (more: the arm did not stop)
    rest_tolerance: float = Field(0.001, gt=0.0, le=0.05, description="m")
    # the surface must be flatter than max_tilt with this confidence
    level_confidence: float = Field(0.99, ge=0.5, le=0.999999, description="(probability)")
    # a still surface passes the stillness and clearance tests (rules.still_problem) with this probability
    still_confidence: float = Field(0.999, ge=0.5, le=0.999999, description="(probability)")
    # m: each plane's offset std is taken as at least this in those tests (model error the covariance omits)
    still_offset_floor: float = Field(0.0001, gt=0.0, le=0.01, description="m")
    # s from a measurement to the machine acting on it (transfer + frame + estimate)
    sensor_latency: float = Field(0.15, ge=0.0, le=5.0, description="s")
    # frames that saw the landing footprint on one surface (0: no footprint rule*)
    footprint_frames: int = Field(3, ge=0, le=1000, description="frames")
    # m around the cup bottom that must be seen supported
    footprint_margin: float = Field(0.01, ge=0.0, le=0.2, description="m")
    # m a zone over the footprint may lie off the fused surface
    footprint_tolerance: float = Field(0.008, gt=0.0, le=0.1, description="m")
    # m/s sideways while bringing the footprint into view and back
    survey_speed: float = Field(0.25, gt=0.0, le=1.0, description="m/s")
    # s for a second look at footprint points only mixed zones saw (0: none)
    recheck_timeout: float = Field(2.0, ge=0.0, le=30.0, description="s")
    # m the cup stays above the surface while it moves back sideways
    traverse_clearance: float = Field(0.06, ge=0.0, le=1.0, description="m")
    # m/s at most within near_surface_distance (the arm's robot file sets 0.05)
    near_surface_speed: float = Field(0.25, gt=0.0, le=1.0, description="m/s")
    # m of cup clearance that counts as near the surface
    near_surface_distance: float = Field(0.05, ge=0.0, le=1.0, description="m")
    # s a fused plane may age while the newest frames are too close to read (0: never)
    too_close_hold: float = Field(3.0, ge=0.0, le=30.0, description="s")
    # m: ... and only with the cup at most this far above that plane (farther
    too_close_clearance: float = Field(0.03, ge=0.0, le=1.0, description="m")
    # away, a sensor too close to read sees something in front of it, not the surface: the plane goes stale)
    # s a contact far above the surface must last with the arm at rest
    obstacle_confirm: float = Field(0.1, ge=0.0, le=5.0, description="s")
    # contacts far above the surface that vanished before the descent is refused
    max_unconfirmed: int = Field(3, ge=0, le=100, description="contacts")
    # * footprint_frames = 0 is for sources without histograms (test doubles); it extrapolates the
    #   surface beside the cup to where it lands, which edges and clutter defeat

    @model_validator(mode="after")
    def _consistent(self) -> "PlacementConfig":
        if self.stop_clearance > self.release_clearance:
            raise ValueError("stop_clearance must not exceed release_clearance "
                             f"({self.stop_clearance} > {self.release_clearance} m)")
        if self.slow_clearance <= self.release_clearance:
            raise ValueError("slow_clearance must exceed release_clearance")
        if self.contact_clearance < self.release_clearance:
            raise ValueError("contact_clearance must be >= release_clearance")
        if self.early_refuse_tilt < self.max_tilt:
            raise ValueError("early_refuse_tilt must be >= max_tilt")
        return self

    @classmethod
    def load(cls, path):
        """Read a JSON file written by :meth:`save` (one :attr:`error` line naming the file for any problem), holding
        only settings a file may hold (:meth:`check_file_settings`)."""
        cfg = super().load(path)
        cfg.check_file_settings(f"{cls.what} {path}")
        return cfg

    def check_file_settings(self, where: str) -> None:
        """Raise one :attr:`error` line naming ``where`` (if given) for a setting that code may give and a file may not:
        ``footprint_frames = 0`` turns the landing-footprint rule off, for test doubles whose frames carry no
        histograms; from a user's file it would release over an edge the rule exists to see (an adversarial
        review's scenario did: the cup tipped off a table edge, session 89)."""
        if self.footprint_frames == 0:
            raise self.error(f"{where + ': ' if where else ''}footprint_frames: 0 turns the landing-footprint check "
                             "off (for test doubles whose frames carry no histograms); a placement file must keep it on "
                             "(1 or more frames)")

