"""The placement rules as plain functions (place_safe/placement/rules.py): each fails closed on bad input and
says why in one line; the machine's decisions rest on them (tests/placement/test_machine.py and
test_release_rule_properties.py exercise them through the machine)."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from place_safe.fusion.plane_filter import FusedPlane
from place_safe.placement import rules
from place_safe.placement.machine import PlacementConfig

CFG = PlacementConfig()


def _plane(tilt=0.0, std_angle=0.001, std_offset=0.0005, stamp=1.0, n=7):
    normal = np.array([math.sin(tilt), 0.0, math.cos(tilt)])
    return FusedPlane(normal, 0.0, tilt, std_angle, std_offset, n, stamp, n,
                      stamps=tuple(stamp - 0.1 * i for i in range(n)))


def test_a_level_fresh_plane_passes_every_rule():
    p = _plane()
    assert rules.plane_problem(p, 1.05, None, CFG, 0.008, lambda: False) is None
    assert rules.level_problem(p, CFG) is None and rules.planar_problem(p, CFG) is None
    assert rules.confidently_tilted(p, CFG) is None
    assert rules.check_frames_needed(p, CFG) == CFG.check_frames


@given(st.sampled_from(["nan_normal", "nan_offset", "long_normal", "bad_tilt", "negative_spread", "future",
                        "stale", "none", "malformed"]))
def test_a_bad_plane_is_a_problem_in_one_line(kind):
    p = _plane()
    now = 1.05
    if kind == "nan_normal":
        p = dataclasses.replace(p, normal_base=np.array([math.nan, 0.0, 1.0]))
    elif kind == "nan_offset":
        p = dataclasses.replace(p, offset_base=math.nan)
    elif kind == "long_normal":
        p = dataclasses.replace(p, normal_base=np.array([0.0, 0.0, 2.0]))
    elif kind == "bad_tilt":
        p = dataclasses.replace(p, tilt_rad=0.3)
    elif kind == "negative_spread":
        p = dataclasses.replace(p, std_offset=-1.0)
    elif kind == "future":
        now = 0.5
    elif kind == "stale":
        now = 1.0 + CFG.plane_timeout + 0.1
    elif kind == "none":
        p = None
    elif kind == "malformed":
        p = object()
    why = rules.plane_problem(p, now, "a note", CFG, 0.008, lambda: False)
    assert isinstance(why, str) and why and "\n" not in why


def test_the_too_close_hold_keeps_an_older_plane_only_while_blind():
    p = _plane()
    now = 1.0 + CFG.plane_timeout + 0.1
    assert rules.plane_problem(p, now, None, CFG, 0.008, lambda: True) is None
    assert "stale" in rules.plane_problem(p, now, None, CFG, 0.008, lambda: False)
    assert rules.too_close("frame 3: " + rules.TOO_CLOSE_REASON) and not rules.too_close(None)


@given(st.floats(math.radians(5.5), math.radians(40)))
def test_steeper_than_max_tilt_is_never_level(tilt):
    assert rules.level_problem(_plane(tilt=tilt), CFG) is not None


def test_sensor_timeout_counts_from_the_first_tick_until_a_frame_arrives():
    assert rules.sensor_problem(None, CFG.sensor_timeout - 0.01, 0.0, None, CFG) is None
    assert "sensor timeout" in rules.sensor_problem(None, CFG.sensor_timeout + 0.01, 0.0, None, CFG)
    assert rules.sensor_problem(5.0, 5.0 + CFG.sensor_timeout - 0.01, 0.0, None, CFG) is None


@given(st.one_of(st.none(), st.text(), st.floats(allow_nan=True), st.booleans(), st.integers(-5, 10)))
def test_footprint_evidence_from_garbage_is_none(value):
    class Verdict:
        supported = value
        problem = None
    seen = rules.footprint_seen(Verdict())
    assert isinstance(seen, int)
    if value is None or isinstance(value, (str, bool)) or (isinstance(value, float) and not math.isfinite(value)):
        assert seen == 0
    assert rules.footprint_problem(Verdict(), CFG) is None
    Verdict.problem = "step under the rim"
    assert "step under the rim" in rules.footprint_problem(Verdict(), CFG)


def test_only_distinct_post_stop_stamps_up_to_now_count():
    p = dataclasses.replace(_plane(stamp=2.0), stamps=(1.0, 1.5, 1.5, 1.9, 2.0, 3.0))
    assert rules.post_stop_stamps(p, 2.0, 1.4, CFG) == [1.5, 1.9, 2.0]
    assert rules.post_stop_stamps(p, 2.0, None, CFG) == []
