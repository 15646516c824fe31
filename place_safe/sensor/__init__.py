"""The sensor: the TMF8820's zone layout, the Frame type and histogram helpers (one definition each)."""

from place_safe.sensor.frame import Frame
from place_safe.sensor.histogram import COUNT_MAX, FLOOR_BINS, find_peaks, first_return, measure_floor
from place_safe.sensor.zones import (CENTRE, CORNER, EDGE, N_BINS, N_ZONES, ZONE_DIRECTIONS, ZONE_KIND, ZONE_RECTS,
                                     zone_centre_directions)

__all__ = ["Frame", "N_ZONES", "N_BINS", "ZONE_RECTS", "ZONE_KIND", "ZONE_DIRECTIONS", "CENTRE", "EDGE", "CORNER",
           "zone_centre_directions", "COUNT_MAX", "FLOOR_BINS", "measure_floor", "find_peaks", "first_return"]
