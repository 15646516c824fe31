"""The adversarial corpus: the input kinds of issue 8, run through the CLI in-process.

:func:`build_corpus` writes one file per input kind (frame files, calibration files, placement and
scenario configs) and returns the runs (argv lists) that feed them to every command that reads them,
plus the command-line values the issue lists. Each run must end in one of two ways:

* exit status 2 with exactly one line on standard error (and, for ``--jsonl``, only valid JSON lines
  before it on standard output), or
* exit status 0 where every JSON line on standard output is valid JSON with a finite plane in front
  of the sensor (``n_z > 0``, ``offset > 0``) or ``null`` with a reason.

Never a traceback, never another status, never a NaN or a negative offset. ``python
tests/cli/test_adversarial_corpus.py DIR`` writes the corpus to DIR and prints the runs (one per
line, as JSON) for replaying it outside pytest.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from place_safe.cli.app import main

_GOOD_REF = [30.0] * 12 + [500.0, 3000.0, 9000.0, 3000.0, 500.0] + [30.0] * 111


def _frames() -> list[dict]:
    from place_safe.evaluation.synthetic import make_frames

    return [f.to_dict() for f in make_frames(3, seed=5)]


def _dump(entries) -> str:
    return json.dumps(entries)


def frame_kinds() -> dict[str, bytes]:
    """Frame files, by input kind."""
    good = _frames()
    text = _dump(good).encode()

    def with_first(**change) -> bytes:
        e = [dict(x) for x in good]
        for k, v in change.items():
            if v is None:
                e[0].pop(k, None)
            else:
                e[0][k] = v
        return _dump(e).encode()

    def with_truth(truth: dict) -> bytes:
        e = [dict(x) for x in good]
        e[1].pop("plane", None)
        e[1].update(truth)
        return _dump(e).encode()

    hists = np.asarray(good[0]["hists"], dtype=float)
    sat = hists.copy()
    sat[4, 20] = 2 ** 24 - 1
    eye = np.eye(4).tolist()
    horizontal = [[1, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]]
    return {
        "good": text,
        "good-jsonl": "\n".join(json.dumps(x) for x in good).encode() + b"\n",
        "bom": b"\xef\xbb\xbf" + text,
        "empty": b"",
        "blank": b"  \n\t ",
        "number": b"42",
        "string": b'"frames"',
        "list-of-numbers": b"[1, 2, 3]",
        "truncated-list": text[:-1],
        "truncated-frame": text[: len(text) // 2],
        "trailing-garbage": text + b" ]]",
        "missing-comma": text.replace(b"}, {", b"} {", 1),
        "non-utf8-frame": text.replace(b'"hists"', b'"h\xffsts"', 1),
        "non-utf8-top": b"\xff\xfe[" + text[1:],
        "deep-nesting": b"[" * 100_000 + b"]" * 100_000,
        "deep-frame": b'[{"hists": ' + b"[" * 100_000 + b"]" * 100_000 + b"}]",
        "huge-integer": b'[{"hists": ' + b"9" * 5000 + b"}]",
        "huge-float": with_first(timestamp=None).replace(b'"hists": [[', b'"hists": [[1e999, ', 1),
        "timestamp-string": with_first(timestamp="noon"),
        "timestamp-list": with_first(timestamp=[1, 2]),
        "nan-counts": with_first(hists=np.where(np.arange(128) == 3, np.nan, hists).tolist()),
        "infinite-counts": _dump(good).replace("[[", "[[Infinity, ", 1).encode(),
        "negative-counts": with_first(hists=(-hists).tolist()),
        "wrong-shape": with_first(hists=[[1, 2, 3]]),
        "hists-string": with_first(hists="abc"),
        "hists-ragged": with_first(hists=[[1, 2], [3]]),
        "hists-objects": with_first(hists=[[{"a": 1}] * 128] * 9),
        "no-reference": with_first(reference_hist=None),
        "zero-reference": with_first(reference_hist=[0] * 128),
        "flat-reference": with_first(reference_hist=[40] * 128),
        "reference-first-bin": with_first(reference_hist=[9000] + [30] * 127),
        "reference-last-bin": with_first(reference_hist=[30] * 127 + [9000]),
        "saturated": with_first(hists=sat.tolist()),
        "distances-string": with_first(distances="far"),
        "distances-nan": with_first(distances=[{"depths_1": [float("nan")] * 9, "confs_1": [200] * 9}]),
        "truth-zero-normal": with_truth({"plane": {"normal": [0, 0, 0], "offset": 0.1}}),
        "truth-nan-normal": with_truth({"plane": {"normal": [float("nan"), 0, 1], "offset": 0.1}}),
        "truth-nz-zero": with_truth({"plane": {"normal": [1, 0, 0], "offset": 0.1}}),
        "truth-negative-offset": with_truth({"plane": {"normal": [0, 0, 1], "offset": -0.1}}),
        "truth-nan-dist": with_truth({"pose": eye, "dist_to_plane": float("nan")}),
        "truth-negative-dist": with_truth({"pose": eye, "dist_to_plane": -0.2}),
        "truth-zero-pose": with_truth({"pose": np.zeros((4, 4)).tolist(), "dist_to_plane": 0.1}),
        "truth-horizontal-pose": with_truth({"pose": horizontal, "dist_to_plane": 0.1}),
        "truth-non-rotation": with_truth({"pose": (3 * np.eye(4)).tolist(), "dist_to_plane": 0.1}),
        "all-truth-bad": _dump([dict(x, plane={"normal": [0, 0, 0], "offset": 1}) for x in good]).encode(),
        "big-extra-key": with_first(meta="x" * (1 << 20)),
    }


def calibration_kinds() -> dict[str, bytes]:
    fmt = {"format": "place_safe.calibration/1"}

    def cal(**sections) -> bytes:
        return json.dumps({**fmt, **sections}).encode()

    peak = {"m": 72.0, "b": 13.0}
    return {
        "cal-good-bom": b"\xef\xbb\xbf" + cal(peak=peak),
        "cal-non-utf8": b'{"format": "\xff"}',
        "cal-deep": b"[" * 100_000 + b"]" * 100_000,
        "cal-huge-int": b'{"format": ' + b"9" * 5000 + b"}",
        "cal-not-json": b"{format",
        "cal-unknown-key": cal(peak=peak, extra=1),
        "cal-diff-list": cal(diff=[1, 2]),
        "cal-diff-string": cal(diff="x"),
        "cal-range-correction-string": cal(diff={"range_correction": "x"}),
        "cal-range-correction-minus-10m": cal(diff={"range_correction": {"coeffs": [-10.0]}}),
        "cal-coeffs-1e300": cal(peak={**peak, "residual_coeffs": [1e300]}),
        "cal-m-true": cal(peak={"m": True, "b": 13.0}),
        "cal-rays-zero": cal(forward={"rays_per_zone": 0}),
        "cal-negative-gains": cal(peak={**peak, "zone_gains": [-1.0] * 9}),
        "cal-mount-tilt-100": cal(forward={"mount_tilt": [100.0, 0.0]}),
        "cal-crosstalk-1e300": cal(forward={"crosstalk": 1e300}),
        "cal-nan-zone-offsets": json.dumps({**fmt, "forward": {"zone_offsets": [float("nan")] * 9}}).encode(),
        "cal-albedo-zero": cal(forward={"albedo": 0.0}),
        "cal-specular-exponent-zero": cal(forward={"specular_exponent": 0.0}),
        "cal-ref-time-scale-1e6": cal(forward={"ref_time_scale": 1e6}),
    }


def config_kinds() -> dict[str, bytes]:
    return {
        "placement-nan": b'{"accel": NaN}',
        "placement-string": b'{"accel": "fast"}',
        "placement-unknown": b'{"max_tilt_deg": 5}',
        "placement-binary": b"\x00\xff\xfe\x01",
        "scenario-unknown-sensor-key": json.dumps({"scene": {}, "sensor": {"rayz": 4}}).encode(),
        "scenario-bad-table": json.dumps({"scene": {"table": [1, 2]}}).encode(),
    }


#: Command-line values of the issue (and neighbours), each a full argv with ``{good}`` for a good frame file.
OPTION_RUNS = [
    ["stream", "{good}", "--rate", "nan"], ["stream", "{good}", "--rate", "inf"], ["stream", "{good}", "--rate=-1"],
    ["stream", "{good}", "--queue", "0"], ["stream", "{good}", "--max-frames", "0"],
    ["bench", "--frames=-1"], ["bench", "--memory-file=-5"], ["bench", "--frames", "1e3"],
    ["demo", "--synthetic", "--frames", "0"], ["demo", "--seed=-1"],
    ["recover", "{good}", "--method", "peak", "--batch", "0"], ["recover", "{good}", "--method", "bogus"],
    ["evaluate", "{good}", "--min-distance", "nan"], ["evaluate", "{good}", "--max-distance", "inf"],
    ["evaluate", "{good}", "--min-distance", "0.5", "--max-distance", "0.1"],
    ["calibrate", "{good}", "--method", "nope", "-o", "{tmp}/c.json"],
    ["calibrate", "{good}", "--method", "peak", "-o", "/dev/full"],  # read as an old calibration: no end, no size
    ["synth", "--frames", "100000000000000000000", "-o", "{tmp}/s.json"],  # built in memory: would never finish
]
SIM_OPTION_RUNS = [
    ["sim", "place", "--seconds", "0"], ["sim", "place", "--seconds", "nan"], ["sim", "place", "--method", "bogus"],
    ["sim", "render", "--width", "0"], ["sim", "render", "--height=-3"], ["sim", "bench", "--rays", "0"],
    ["sim", "place", "--config", "{placement-nan}"], ["sim", "place", "--config", "{placement-string}"],
    ["sim", "place", "--config", "{placement-unknown}"], ["sim", "place", "--config", "{placement-binary}"],
    ["sim", "place", "--scenario", "{scenario-unknown-sensor-key}"],
    ["sim", "place", "--scenario", "{scenario-bad-table}"],
]


def build_corpus(root: Path) -> list[tuple[str, list[str], bool]]:
    """Write the corpus under ``root``; returns (name, argv, slow) for every run."""
    root.mkdir(parents=True, exist_ok=True)
    paths: dict[str, str] = {"tmp": str(root)}
    for name, data in {**frame_kinds(), **calibration_kinds(), **config_kinds()}.items():
        p = root / f"{name}.json"
        p.write_bytes(data)
        paths[name] = str(p)
    paths["missing"] = str(root / "no-such-file.json")
    paths["directory"] = str(root)
    runs: list[tuple[str, list[str], bool]] = []
    for name in [*frame_kinds(), "missing", "directory"]:
        f = paths[name]
        runs += [
            (f"recover-peak/{name}", ["recover", f, "--method", "peak", "--jsonl", "-q"], False),
            (f"recover-proprietary/{name}", ["recover", f, "--method", "proprietary", "--jsonl"], False),
            (f"recover-diff/{name}", ["recover", f, "--method", "diff", "--jsonl", "-q"], True),
            (f"evaluate/{name}", ["evaluate", f, "--methods", "peak", "proprietary", "--no-plots", "-q"], False),
            (f"calibrate-peak/{name}", ["calibrate", f, "--method", "peak", "-o", f"{root}/out-{name}.json", "-q"],
             False),
            (f"stream-peak/{name}", ["stream", f, "--method", "peak", "--rate", "2000", "--jsonl"], False),
        ]
    for name in calibration_kinds():
        c = paths[name]
        runs += [
            (f"recover-peak-cal/{name}", ["recover", paths["good"], "--method", "peak", "--calibration", c, "--jsonl"],
             False),
            (f"recover-proprietary-cal/{name}",
             ["recover", paths["good"], "--method", "proprietary", "--calibration", c, "--jsonl", "-q"], False),
            (f"recover-diff-cal/{name}",
             ["recover", paths["good"], "--method", "diff", "--calibration", c, "--jsonl", "-q"], True),
            (f"evaluate-cal/{name}",
             ["evaluate", paths["good"], "--calibration", c, "--methods", "peak", "--no-plots", "-q"], False),
        ]
    for i, argv in enumerate(OPTION_RUNS):
        runs.append((f"option/{i}:{' '.join(argv[:1] + argv[2:])}", [a.format(**paths) for a in argv], False))
    for i, argv in enumerate(SIM_OPTION_RUNS):
        runs.append((f"sim-option/{i}:{' '.join(argv[:3])}", [a.format(**paths) for a in argv], True))
    return runs


def _no_constant(name: str):
    raise AssertionError(f"{name} in a JSON line")


def check_run(argv: list[str], status: int, out: str, err: str) -> None:
    """The corpus contract for one run (see the module docstring)."""
    assert "Traceback" not in err and "Traceback" not in out
    assert status in (0, 2), f"exit status {status}: {err!r}"
    jsonl = "--jsonl" in argv
    if jsonl:
        for line in out.splitlines():
            obj = json.loads(line, parse_constant=_no_constant)  # NaN / Infinity literals are not JSON
            if obj.get("normal") is None:
                assert obj.get("offset") is None and obj.get("reason")
            else:
                n = obj["normal"]
                assert len(n) == 3 and all(math.isfinite(v) for v in n) and n[2] > 0
                assert math.isfinite(obj["offset"]) and obj["offset"] > 0
    if status == 2:
        lines = [x for x in err.splitlines() if x.strip()]
        assert len(lines) == 1, f"expected one line on stderr, got {err!r}"
        assert lines[0].startswith("place-safe: error:")
        if not jsonl:
            assert out == ""


_ROOT: dict[str, Path] = {}


def _corpus(tmp_path_factory) -> tuple[Path, list]:
    if "root" not in _ROOT:
        _ROOT["root"] = tmp_path_factory.mktemp("corpus")
        _ROOT["runs"] = build_corpus(_ROOT["root"])
    return _ROOT["root"], _ROOT["runs"]


def _params():
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        runs = build_corpus(Path(d))
    return [pytest.param(i, id=name, marks=[pytest.mark.slow] if slow else []) for i, (name, _, slow) in
            enumerate(runs)]


@pytest.mark.parametrize("index", _params())
def test_corpus_run(tmp_path_factory, capsys, index):
    _, runs = _corpus(tmp_path_factory)
    name, argv, _ = runs[index]
    if name.startswith("sim-option"):
        pytest.importorskip("mujoco")
    status = main(argv)
    cap = capsys.readouterr()
    check_run(argv, status, cap.out, cap.err)


def test_corpus_expectations_that_must_hold(tmp_path, capsys):
    """Spot checks of what must come out, not only how: bad truth never costs recover a line."""
    runs = dict((n, a) for n, a, _ in build_corpus(tmp_path))
    for kind in ("truth-zero-normal", "truth-horizontal-pose", "truth-negative-dist", "all-truth-bad"):
        assert main(runs[f"recover-peak/{kind}"]) == 0
        lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
        assert [x["index"] for x in lines] == [0, 1, 2] and all(x["normal"] is not None for x in lines)
    assert main(runs["evaluate/truth-zero-normal"]) == 0
    assert main(runs["recover-peak-cal/cal-diff-list"]) == 0  # a bad diff section does not stop peak
    assert main(runs["recover-diff-cal/cal-diff-list"]) == 2
    capsys.readouterr()
    assert main(["evaluate", runs["evaluate/truth-zero-normal"][1], "--methods", "peak", "--no-plots"]) == 0
    assert "1 ground truth not a plane" in capsys.readouterr().err


if __name__ == "__main__":  # write the corpus and list its runs
    target = Path(sys.argv[1] if len(sys.argv) > 1 else "adversarial-corpus")
    for name, argv, _ in build_corpus(target):
        print(json.dumps({"name": name, "argv": argv}))


from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

_json = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=4),
                     lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=4), inner,
                                                                                  max_size=3), max_leaves=12)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(field=st.sampled_from(["hists", "reference_hist", "distances", "plane", "pose", "dist_to_plane",
                              "timestamp", "meta"]),
       value=_json, index=st.integers(0, 2), method=st.sampled_from(["peak", "proprietary", "peak-naive"]))
def test_any_field_of_any_frame_through_recover(tmp_path, capsys, field, value, index, method):
    """One field of one frame replaced by any JSON value: every frame keeps its line, the others keep their planes."""
    frames = _frames()
    path = tmp_path / "f.json"
    path.write_text(json.dumps(frames))
    assert main(["recover", str(path), "--method", method, "--jsonl", "-q"]) == 0
    good = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    frames[index][field] = value
    path.write_text(json.dumps(frames))
    argv = ["recover", str(path), "--method", method, "--jsonl", "-q"]
    status = main(argv)
    cap = capsys.readouterr()
    check_run(argv, status, cap.out, cap.err)
    assert status == 0
    main_lines = [json.loads(x) for x in cap.out.splitlines()]
    assert [x["index"] for x in main_lines] == [0, 1, 2]
    for i in range(3):
        if i != index:
            assert main_lines[i]["normal"] == good[i]["normal"]
