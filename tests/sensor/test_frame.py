"""Tests of place_safe.sensor.frame: the zone table of docs/tmf8820.md and the Frame type."""

from __future__ import annotations

import numpy as np
import pytest

from place_safe.exceptions import FrameError
from place_safe.geometry import Plane
from place_safe.sensor.frame import CORNER, EDGE, CENTRE, N_BINS, N_ZONES, ZONE_DIRECTIONS, ZONE_KIND, ZONE_RECTS, Frame

#: Centre directions from the table in the shared docs/tmf8820.md (zones 1..9).
DOC_DIRECTIONS = np.array([
    [+0.1824, +0.1873, 0.9652],
    [+0.1857, +0.0000, 0.9826],
    [+0.1824, -0.1873, 0.9652],
    [+0.0000, +0.1904, 0.9817],
    [+0.0000, +0.0000, 1.0000],
    [+0.0000, -0.1904, 0.9817],
    [-0.1824, +0.1873, 0.9652],
    [-0.1857, +0.0000, 0.9826],
    [-0.1824, -0.1873, 0.9652],
])


def test_zone_directions_match_the_documented_table():
    assert ZONE_DIRECTIONS.shape == (N_ZONES, 3)
    np.testing.assert_allclose(ZONE_DIRECTIONS, DOC_DIRECTIONS, atol=1e-4)
    np.testing.assert_allclose(np.linalg.norm(ZONE_DIRECTIONS, axis=1), 1.0)


def test_zone_kinds_and_field_of_view():
    assert [i + 1 for i in np.flatnonzero(ZONE_KIND == CORNER)] == [1, 3, 7, 9]
    assert [i + 1 for i in np.flatnonzero(ZONE_KIND == EDGE)] == [2, 4, 6, 8]
    assert [i + 1 for i in np.flatnonzero(ZONE_KIND == CENTRE)] == [5]
    fov_x = np.degrees(np.arctan(ZONE_RECTS[:, 1].max()) - np.arctan(ZONE_RECTS[:, 0].min()))
    fov_y = np.degrees(np.arctan(ZONE_RECTS[:, 3].max()) - np.arctan(ZONE_RECTS[:, 2].min()))
    assert fov_x == pytest.approx(33, abs=1) and fov_y == pytest.approx(33, abs=1)


def _good() -> Frame:
    return Frame(np.full((N_ZONES, N_BINS), 100.0), np.full(N_BINS, 50.0))


def test_valid_frame_passes():
    _good().validate()


@pytest.mark.parametrize("change,message", [
    (lambda f: setattr(f, "hists", np.zeros((9, 127))), "shape"),
    (lambda f: f.hists.__setitem__((0, 0), np.nan), "NaN"),
    (lambda f: f.hists.__setitem__((3, 5), -1.0), "negative"),
    (lambda f: setattr(f, "reference", None), "reference"),
    (lambda f: setattr(f, "reference", np.zeros(64)), "shape"),
    (lambda f: f.reference.__setitem__(0, np.inf), "reference_hist"),
])
def test_validate_says_what_is_wrong(change, message):
    f = _good()
    change(f)
    with pytest.raises(FrameError, match=message):
        f.validate()


@pytest.mark.parametrize("entry,message", [
    ([], "JSON object"),
    ({}, "hists"),
    ({"hists": [[1, 2]]}, "shape"),
    ({"hists": "abc"}, "hists"),
    ({"hists": np.zeros((9, 128)).tolist(), "distances": [{"confs_1": [0] * 9}]}, "depths_1"),
    ({"hists": [[10 ** 400] * 128] * 9}, "hists"),
    ({"hists": [["12"] * 128] * 9}, "hists must hold numbers, not text"),
    ({"hists": [[True] * 128] * 9}, "not booleans"),
    ({"hists": [[None] * 128] * 9}, "numbers"),
    ({"hists": np.zeros((9, 128)).tolist(), "distances": [{"depths_1": [True] * 9}]}, "depths_1 must hold numbers"),
    ({"hists": np.zeros((9, 128)).tolist(), "distances": [{"depths_1": [100] * 8 + [True]}]}, "not booleans"),
    ({"hists": np.zeros((9, 128)).tolist(), "distances": [{"depths_1": [100] * 9, "confs_1": ["x"] * 9}]}, "confs_1"),
])
def test_from_dict_rejects_malformed_entries(entry, message):
    with pytest.raises(FrameError, match=message):
        Frame.from_dict(entry)


_POSE = np.eye(4).tolist()


@pytest.mark.parametrize("truth", [
    {"plane": {"offset": 0.1}},
    {"plane": {"normal": [0, 0, 0], "offset": 0.1}},
    {"plane": {"normal": [float("nan"), 0, 1], "offset": 0.1}},
    {"plane": {"normal": [1, 0, 0], "offset": 0.1}},
    {"plane": {"normal": [0, 0, 1], "offset": -0.1}},
    {"plane": {"normal": [0, 0, 1], "offset": "far"}},
    {"plane": [0, 0, 1]},
    {"pose": _POSE, "dist_to_plane": float("nan")},
    {"pose": _POSE, "dist_to_plane": -0.1},
    {"pose": np.zeros((4, 4)).tolist(), "dist_to_plane": 0.1},
    {"pose": (2 * np.eye(4)).tolist(), "dist_to_plane": 0.1},
    {"pose": [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]], "dist_to_plane": 0.1},  # horizontal
    {"pose": "up", "dist_to_plane": 0.1},
    {"pose": _POSE, "dist_to_plane": 1e30},  # farther than the sensor's 16-bit millimetres reach
    {"plane": {"normal": [False, False, True], "offset": 0.1}},
    {"pose": [[True, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]], "dist_to_plane": 0.1},
])
def test_bad_ground_truth_only_clears_the_truth(truth):
    """Recovery never needs ground truth: a frame whose truth is not a plane keeps its histograms."""
    f = Frame.from_dict({"hists": np.zeros((9, 128)).tolist(), "reference_hist": [1.0] * 128, **truth})
    assert f.truth is None
    assert f.truth_error and "ground truth" in f.truth_error
    f.validate()


@pytest.mark.parametrize("stamp,message", [("12:00", "must be a number of seconds, got str"),
                                           ([1.0], "must be a number of seconds, got list"),
                                           (True, "must be a number of seconds, got bool"),
                                           (float("nan"), "must be a finite number"), (10 ** 400, "must be a finite")],
                         ids=["text", "list", "bool", "nan", "huge"])
def test_a_bad_timestamp_costs_the_frame_its_stamp_only(stamp, message):
    """A timestamp that is not a finite number of seconds made the whole frame an error, so ``recover`` lost its plane;
    the field is not in the shared format and recovery does not read it: the frame is kept, unstamped (None, which the
    frame gate drops), with the reason in ``timestamp_error``, as bad ground truth clears only the truth."""
    d = _good().to_dict()
    d["timestamp"] = stamp
    f = Frame.from_dict(d)
    f.validate()
    assert f.timestamp is None and f.timestamp_error.startswith("timestamp ") and message in f.timestamp_error
    np.testing.assert_array_equal(f.hists, _good().hists)
    assert Frame.from_dict(dict(d, timestamp=12.5)).timestamp_error is None


def test_dict_round_trip_keeps_units_truth_and_extras():
    f = Frame(np.arange(N_ZONES * N_BINS, dtype=float).reshape(N_ZONES, N_BINS), np.ones(N_BINS),
              distances=np.linspace(0.05, 0.09, 9), confidences=np.full(9, 200.0), timestamp=12.5,
              truth=Plane.from_angles(0.2, 0.5, 0.1), extra={"joint_angles": [0.0] * 6})
    d = f.to_dict()
    assert d["distances"][0]["depths_1"][0] == pytest.approx(50.0)  # millimetres in the file
    g = Frame.from_dict(d)
    np.testing.assert_allclose(g.hists, f.hists)
    np.testing.assert_allclose(g.distances, f.distances)
    np.testing.assert_allclose(g.truth.normal, f.truth.normal)
    assert g.timestamp == 12.5
    assert g.extra["joint_angles"] == [0.0] * 6


def test_pose_ground_truth_from_the_sweep_format(sweep_path):
    import json

    first = json.loads(sweep_path.read_text())[0]
    f = Frame.from_dict(first)
    f.validate()
    assert f.truth is not None
    assert f.truth.offset == pytest.approx(first["dist_to_plane"])
    assert f.distances is not None and np.all(f.distances < 1.0)  # mm in the file -> m


def test_reported_distances_are_what_the_sensor_can_report():
    """A simulated range of -1 mm (2 mm noise on 0.1 mm) was written at full confidence: on-sensor distances are 0
    (no object, confidence 0) below 1 mm, past 65.535 m or not finite, the rest rounded with full confidence (the
    generators' one definition)."""
    from place_safe.sensor.frame import reported_distances

    d, c = reported_distances([-0.001, 0.0004, 0.0012, 0.25, 70.0, float("nan")], 3)
    assert d.tolist() == [0.0, 0.0, 0.001, 0.25, 0.0, 0.0] and c.tolist() == [0, 0, 255, 255, 0, 0]


def test_reported_distances_follow_the_histograms():
    """``synth`` at 4.9-5 m wrote full-confidence distances where the histograms hold no return (it lands in the bins
    only to about 1.3 m): given the histograms, a zone without a return reports no object, a zone with one its range."""
    from place_safe.sensor.frame import reported_distances

    hists = np.full((N_ZONES, N_BINS), 100.0)
    hists[:4, 40:44] += [300.0, 1000.0, 1000.0, 300.0]  # a return in zones 1-4 only
    d, c = reported_distances(np.full(N_ZONES, 0.5), 3, hists=hists)
    assert d.tolist() == [0.5] * 4 + [0.0] * 5 and c.tolist() == [255] * 4 + [0] * 5
