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
    (lambda f: setattr(f, "hists", np.ma.masked_array(f.hists, np.eye(N_ZONES, N_BINS, dtype=bool))),
     "hists is a masked array with 9 masked entries"),
    (lambda f: setattr(f, "reference", np.ma.masked_array(f.reference, np.arange(N_BINS) == 3)), "1 masked entry"),
    (lambda f: setattr(f, "hists", f.hists > 50), "hists must hold numbers, not booleans"),  # session 82
    (lambda f: setattr(f, "reference", f.reference > 10), "reference_hist must hold numbers, not booleans"),
])
def test_validate_says_what_is_wrong(change, message):
    f = _good()
    change(f)
    with pytest.raises(FrameError, match=message):
        f.validate()


def test_a_masked_array_with_nothing_masked_is_read_as_its_numbers():
    f = _good()
    f.hists = np.ma.masked_array(f.hists)
    f.validate()


def test_estimators_refuse_a_frame_whose_masked_counts_they_cannot_honour():
    """A masked zone's counts are not read into the plane as they stand (they were, before: the mask was dropped)."""
    from place_safe.evaluation.synthetic import make_frames
    from place_safe.recovery import make_estimator
    f = make_frames(1, seed=3)[0]
    assert make_estimator("peak").estimate(f).plane is not None
    mask = np.zeros((N_ZONES, N_BINS), bool)
    mask[4] = True
    f.hists = np.ma.masked_array(f.hists, mask)
    for method in ("peak", "diff"):
        est = make_estimator(method).estimate(f)
        assert est.plane is None and est.reason.startswith("hists is a masked array with 128 masked entries")


def test_proprietary_refuses_on_sensor_distances_of_booleans():
    """An array of booleans given as the on-sensor distances read as 1 m in every zone: proprietary stated a plane at
    0.98 m (session 82; a frame file's booleans are refused when read). Now the frame's reason; numbers as before."""
    from place_safe.evaluation.synthetic import make_frames
    from place_safe.recovery import make_estimator
    f = make_frames(1, seed=3)[0]
    assert make_estimator("proprietary").estimate(f).plane is not None
    for name, value in (("distances", np.ones(N_ZONES, bool)), ("confs_1", np.ones(N_ZONES, bool))):
        g = Frame(f.hists, f.reference, distances=value if name == "distances" else f.distances,
                  confidences=value if name == "confs_1" else f.confidences)
        est = make_estimator("proprietary").estimate(g)
        assert est.plane is None and est.reason == f"{name} must hold numbers, not booleans"


@pytest.mark.parametrize("entry,message", [
    ([], "JSON object"),
    ({}, "hists"),
    ({"hists": [[1, 2]]}, "shape"),
    ({"hists": "abc"}, "hists"),
    ({"hists": [[10 ** 400] * 128] * 9}, "hists"),
    ({"hists": [["12"] * 128] * 9}, "hists must hold numbers, not text"),
    ({"hists": [[True] * 128] * 9}, "not booleans"),
    ({"hists": [[None] * 128] * 9}, "numbers"),
])
def test_from_dict_rejects_malformed_entries(entry, message):
    with pytest.raises(FrameError, match=message):
        Frame.from_dict(entry)


@pytest.mark.parametrize("distances,message", [
    ([{"confs_1": [0] * 9}], "'distances' must hold a dict with 'depths_1'"),
    ("far", "'distances' must hold a dict with 'depths_1'"),
    ([{"depths_1": [True] * 9}], "depths_1 must hold numbers"),
    ([{"depths_1": [100] * 8 + [True]}], "not booleans"),
    ([{"depths_1": ["x"] * 9, "confs_1": [255] * 9}], "depths_1 must hold numbers, not text"),
    ([{"depths_1": [100] * 8}], "depths_1 has shape (8,)"),
    ([{"depths_1": [100] * 9, "confs_1": ["x"] * 9}], "confs_1 must hold numbers, not text"),
    ([{"depths_1": [100] * 9, "confs_1": [[255]] * 9}], "confs_1 has shape"),
])
def test_malformed_distances_cost_only_the_methods_that_read_them(sweep_path, distances, message):
    """Text (or a wrong shape) in ``depths_1`` / ``confs_1`` made the whole frame an error, so ``peak`` and ``diff``,
    which read only the counts, lost its plane. Per the format (docs/interfaces.md) a bad field fails only the methods
    that read it: the frame loads with its histograms, no on-sensor distances and the reason in ``distances_error``;
    ``proprietary`` refuses it with that reason, ``peak`` gives the plane it gives without the field."""
    from place_safe.recovery import make_estimator

    good = _sweep_frame(sweep_path)
    d = good.to_dict()
    d["distances"] = distances
    f = Frame.from_dict(d)
    f.validate()
    assert f.distances is None and f.confidences is None
    assert f.distances_error.startswith("on-sensor distances unusable: ") and message in f.distances_error
    np.testing.assert_array_equal(f.hists, good.hists)
    assert Frame.from_dict(good.to_dict()).distances_error is None
    peak = make_estimator("peak")
    want = peak.estimate(good)
    assert want.plane is not None
    got = peak.estimate(f)
    assert got.plane is not None and got.plane.offset == want.plane.offset
    refused = make_estimator("proprietary").estimate(f)
    assert refused.plane is None and refused.reason == f.distances_error
    assert make_estimator("proprietary").estimate(good).plane is not None


def _sweep_frame(path) -> Frame:
    """A real sweep frame both peak and proprietary read (the one nearest 21 cm)."""
    from place_safe.io.frame_file import load_frames

    return min(load_frames(path), key=lambda f: abs(f.truth.offset - 0.21))


def test_repeated_frames_finds_a_measurement_given_twice_whatever_its_truth_says():
    """A frame whose histograms, reference and on-sensor distances repeat an earlier frame's is a repeat (its ground
    truth, pose or extras may differ: a pasted copy with an edited truth is still one measurement); each repeat with
    the first frame of its measurement (session 82: 3 frames given 5 times each passed calibrate's 5-frame minimum).
    ``without_repeats`` keeps the first of each, in place, and says what it left out in one line."""
    from place_safe.sensor.frame import repeated_frames, without_repeats

    a, b = _good(), _good()
    b.hists = b.hists + 1.0
    assert repeated_frames([a, b]) == [] and repeated_frames([]) == []
    copy_a = Frame(a.hists.copy(), a.reference.copy(), truth=Plane([0.0, 0.0, 1.0], 0.3), extra={"pose": "x"})
    assert repeated_frames([a, b, copy_a, b]) == [(2, 0), (3, 1)]
    other_distances = Frame(a.hists.copy(), a.reference.copy(), distances=np.full(N_ZONES, 0.1))
    assert repeated_frames([a, other_distances]) == []  # another on-sensor result: another measurement
    assert repeated_frames([a, "not a frame", b]) == []  # (whoever reads it says what it is)
    kept, note, keep = without_repeats([a, b, copy_a, b], "counting from 0")
    assert [id(f) for f in kept] == [id(a), id(b)] and keep == [0, 1]
    assert note.startswith("frame 2 repeats frame 0 exactly (counting from 0") and "2 frames repeat" in note
    assert "\n" not in note
    kept, note, keep = without_repeats([a, b])
    assert [id(f) for f in kept] == [id(a), id(b)] and note is None and keep == [0, 1]


def test_a_reference_histogram_beyond_the_24_bit_counters_is_a_corrupt_frame_for_every_method(sweep_path):
    """peak gave its plane from a frame whose reference histogram held counts the sensor cannot report (the real
    sweep's reference times 1e30, or one bin at 2**30), where proprietary and diff refuse it (round 14). peak reads no
    reference, but the reference comes in the same measurement: :meth:`Frame.validate` refuses it, one line, for every
    method (the hists' own check stays each method's, :func:`~place_safe.sensor.histogram.beyond_count_max`)."""
    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator
    from place_safe.sensor.histogram import COUNT_MAX

    f = next(f for f in load_frames(sweep_path) if 0.15 < f.truth.offset < 0.2)
    one = np.array(f.reference, dtype=float)
    one[60] = 2.0 ** 30
    for ref in (np.array(f.reference, dtype=float) * 1e30, one):
        bad = Frame(f.hists, ref, distances=f.distances, confidences=f.confidences)
        with pytest.raises(FrameError, match=r"^reference histogram counts above the sensor's 24-bit maximum"):
            bad.validate()
        for method in ("peak", "proprietary", "diff"):
            e = make_estimator(method).estimate(bad)
            assert e.plane is None and "reference histogram counts above the sensor's 24-bit maximum" in e.reason, \
                (method, e.reason)
    at_max = np.minimum(np.array(f.reference, dtype=float), COUNT_MAX)  # at the counters' maximum: not beyond it
    Frame(f.hists, at_max).validate()
    assert make_estimator("peak").estimate(Frame(f.hists, at_max)).plane is not None


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64, np.int64, np.uint32])
def test_a_reference_histogram_of_any_number_type_is_refused_for_what_it_holds_not_for_its_type(sweep_path, dtype):
    """The reference's usual case passes on its least and largest count; a float16 reference holding infinity, NaN
    or a negative count is refused as one of any other type is (its largest count, 65504, below the counters'
    maximum: the test must not compare in float16, where that maximum is infinite), and a plain one passes without a
    warning."""
    import warnings

    from place_safe.io.frame_file import load_frames
    from place_safe.recovery import make_estimator

    f = next(f for f in load_frames(sweep_path) if 0.15 < f.truth.offset < 0.2)
    plain = np.minimum(np.array(f.reference, dtype=float), 60000.0).astype(dtype)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Frame(f.hists, plain).validate()
    bad_values = [-1.0] if np.issubdtype(dtype, np.signedinteger) else []
    if np.issubdtype(dtype, np.floating):
        bad_values += [np.inf, np.nan, -3.0]
    for value in bad_values:
        ref = plain.copy()
        ref[100] = value
        bad = Frame(f.hists, ref)
        with pytest.raises(FrameError, match=r"^reference_hist contains NaN, infinite or negative counts"):
            bad.validate()
        e = make_estimator("peak").estimate(bad)
        assert e.plane is None and "reference_hist contains" in e.reason
