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
import os
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
        "distances-text": with_first(distances=[{"depths_1": ["far"] * 9, "confs_1": [200] * 9}]),
        "confidences-text": with_first(distances=[{"depths_1": [100] * 9, "confs_1": "high"}]),
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
        # session 82: every frame given twice (files joined): calibrate counted each twice and held it out beside its
        # own copy (3 frames 5 times each wrote a peak calibration with no floor)
        "repeated-frames": _dump(good + good).encode(),
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
        # third round: each coefficient in range, the series not (400 x 5 cm: a plane moved 20 m; 300 x 3 in the
        # log albedo: an overflow), and an uncertainty floor no covariance survives
        "cal-range-correction-400-coeffs": cal(diff={"range_correction": {"coeffs": [0.05] * 400}}),
        "cal-albedo-series-overflow": cal(diff={"range_correction": {"albedo": [3.0] * 300}}),
        "cal-uncertainty-tilt-1e308": cal(peak=peak, uncertainty={"peak": {"tilt_std": 1e308}}),
        # session 66's round: a residual domain of no width (with zone_inverse: an internal ZeroDivisionError, exit
        # 1), reversed or of rounding width; uncertainty entries that shrink every covariance (no floor, scale 1e-12)
        "cal-domain-equal": cal(peak={**peak, "residual_domain": [0.1, 0.1], "zone_inverse": [0.1] * 9}),
        "cal-domain-reversed": cal(peak={**peak, "residual_domain": [0.4, 0.03], "zone_inverse": [0.1] * 9}),
        "cal-domain-rounding": cal(peak={**peak, "residual_domain": [0.1, 0.10000000000000002],
                                         "zone_inverse": [0.1] * 9}),
        "cal-uncertainty-no-floor": cal(peak=peak, uncertainty={"peak": {"tilt_std": 0.0, "offset_std": 0.0,
                                                                         "scale": 0.95}}),
        "cal-uncertainty-scale-1e-12": cal(peak=peak, uncertainty={"peak": {"tilt_std": 3e-4, "scale": 1e-12}}),
        # session 82: a b within its field's range that puts every plane 140 m away (now no plane, with the reason)
        "cal-b-minus-10000": cal(peak={"m": 72.0, "b": -10000.0}),
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
    ["bench", "recovery", "--frames=-1"], ["bench", "recovery", "--memory-file=-5"],
    ["bench", "recovery", "--frames", "1e3"], ["bench", "sim", "--rays", "0"],
    ["demo", "--synthetic", "--frames", "0"], ["demo", "--seed=-1"],
    ["recover", "{good}", "--method", "peak", "--batch", "0"], ["recover", "{good}", "--method", "bogus"],
    ["evaluate", "{good}", "--min-distance", "nan"], ["evaluate", "{good}", "--max-distance", "inf"],
    ["evaluate", "{good}", "--min-distance", "0.5", "--max-distance", "0.1"],
    ["evaluate", "{good}", "--methods", "peak", "--out", ""],  # session 82: the plots went into the working folder
    ["calibrate", "{good}", "--method", "nope", "-o", "{tmp}/c.json"],
    ["calibrate", "{good}", "--method", "peak", "-o", "/dev/full"],  # read as an old calibration: no end, no size
    ["synth", "--frames", "100000000000000000000", "-o", "{tmp}/s.json"],  # built in memory: would never finish
]
_TMP_OUT = ["--json", "{tmp}/r.json", "--log", "{tmp}/r.jsonl"]  # place writes both (default: the working folder)
SIM_OPTION_RUNS = [
    ["place", "--sim", "place_level", "--timeout", "0", *_TMP_OUT],
    ["place", "--sim", "place_level", "--timeout", "nan", *_TMP_OUT],
    ["place", "--sim", "place_level", "--method", "bogus", *_TMP_OUT],
    ["sim", "render", "--width", "0"], ["sim", "render", "--height=-3"],
    ["place", "--sim", "place_level", "--config", "{placement-nan}", *_TMP_OUT],
    ["place", "--sim", "place_level", "--config", "{placement-string}", *_TMP_OUT],
    ["place", "--sim", "place_level", "--config", "{placement-unknown}", *_TMP_OUT],
    ["place", "--sim", "place_level", "--config", "{placement-binary}", *_TMP_OUT],
    ["place", "--sim", "{scenario-unknown-sensor-key}", *_TMP_OUT],
    ["place", "--sim", "{scenario-bad-table}", *_TMP_OUT],
]


# ---------------------------------------------------------------------------------------------------
# Second round (issue 30): scenario files, robot files, sensor URIs, capture / calibrate-mount, task files
# ---------------------------------------------------------------------------------------------------
_SWEEP = str(Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json")
_ROBOT = str(Path(__file__).resolve().parents[2] / "robots" / "ur5" / "sim.toml")
_LEVEL_30CM = str(Path(__file__).resolve().parents[2] / "scenarios" / "set" / "level_30cm.toml")


def scenario_kinds() -> dict[str, bytes]:
    """Scenario files (TOML unless the name ends in -json), each wrong in one way."""
    t = {
        "scn-scene-int": "scene = 5", "scn-scene-list": "scene = [1, 2]", "scn-scene-bool": "scene = true",
        "scn-scene-string": 'scene = "table"',
        "scn-timestep-tiny": "[scene]\ntimestep = 1e-12", "scn-timestep-nan": "[scene]\ntimestep = nan",
        "scn-timestep-string": '[scene]\ntimestep = "fast"', "scn-timestep-huge": "[scene]\ntimestep = 1e300",
        "scn-ambient-huge": "[sensor]\nambient_range = [0.0, 1e300]",
        "scn-ambient-reversed": "[sensor]\nambient_range = [200.0, 100.0]",
        "scn-ambient-short": "[sensor]\nambient_range = [1.0]",
        "scn-start-q-huge": "[robot]\nstart_q = [1e300, 0.0, 0.0, 0.0, 0.0, 0.0]",
        "scn-start-q-short": "[robot]\nstart_q = [0.0, 0.0]",
        "scn-start-q-strings": '[robot]\nstart_q = ["a", "b", "c", "d", "e", "f"]',
        "scn-protective-stop-huge": "[robot]\nprotective_stop_at = 1e300",
        "scn-rate-tiny": "[sensor]\nrate_hz = 1e-300", "scn-rate-inf": "[sensor]\nrate_hz = inf",
        "scn-rays-huge": "[sensor]\nrays = 100000", "scn-seed-negative": "[sensor]\nseed = -1",
        "scn-seed-huge": "[sensor]\nseed = 9223372036854775807000"[:-3] + "9",
        "scn-spike-huge": "[sensor]\nspike_seconds = 1e300",
        "scn-mismatch-temp": '[sensor]\nmodel = "mismatch"\n[sensor.mismatch]\ntemp_start = 1e300',
        "scn-velocity-huge": "[surface_motion]\nvelocity = 1e300",
        "scn-motion-duration-huge": "[surface_motion]\nduration = 1e300",
        "scn-square-tiny": '[scene.table.material]\npattern = "checker"\nsquare = 1e-12',
        "scn-tilt-deg-huge": "[scene.table]\ntilt_deg = 1e300",
        "scn-start-height-huge": "[scene]\nstart_height = 1e300",
        "scn-start-height-bool": "[scene]\nstart_height = true",
        "scn-clutter-int": "[scene]\nclutter = 5", "scn-table-list": "[scene]\ntable = [1, 2]",
        "scn-robot-xml-dev-zero": '[scene]\nrobot_xml = "/dev/zero"',
        "scn-placement-list": "placement = [1]", "scn-placement-nan": "[placement]\naccel = nan",
        "scn-placement-unknown": "[placement]\nwarp = 1.0",
        "scn-calibration-int": "calibration = 5", "scn-calibration-missing": 'calibration = "no-such-cal.json"',
        "scn-calibration-dir": 'calibration = "."', "scn-method-bogus": 'method = "bogus"',
        "scn-expect-negative": "[expect]\nmax_spilled = -1", "scn-expect-outcome": '[expect]\noutcome = "maybe"',
        "scn-expect-height-huge": "[expect]\nmax_release_height = 1e300",
        "scn-not-toml": "[[[", "scn-unknown-top": "warp = 9",
    }
    out = {k: v.encode() for k, v in t.items()}
    out["scn-binary"] = b"\x00\xff\xfe\x01"
    out["scn-scene-int-json"] = b'{"scene": 5}'
    out["scn-list-json"] = b"[1, 2, 3]"
    return out


def robot_kinds() -> dict[str, bytes]:
    """Robot files: the packaged sim.toml with one line changed."""
    base = Path(_ROBOT).read_text()

    def sub(old: str, new: str) -> bytes:
        assert old in base
        return base.replace(old, new, 1).encode()

    return {
        "rob-host-shell": sub('host = "127.0.0.1"', 'host = "127.0.0.1; rm -rf /"'),
        "rob-host-port": sub('host = "127.0.0.1"', 'host = "127.0.0.1:99999"'),
        "rob-host-url": sub('host = "127.0.0.1"', 'host = "http://robot/"'),
        "rob-host-space": sub('host = "127.0.0.1"', 'host = "ur 5"'),
        "rob-host-empty": sub('host = "127.0.0.1"', 'host = ""'),
        "rob-host-int": sub('host = "127.0.0.1"', "host = 5"),
        "rob-host-list": sub('host = "127.0.0.1"', 'host = ["a"]'),
        "rob-host-bad-ip": sub('host = "127.0.0.1"', 'host = "300.1.1.1"'),
        "rob-host-long": sub('host = "127.0.0.1"', f'host = "{"a" * 70}.com"'),
        "rob-xyz-huge": sub("xyz = [0.07, 0.0, 0.11]", "xyz = [1e308, 0.0, 0.11]"),
        "rob-xyz-short": sub("xyz = [0.07, 0.0, 0.11]", "xyz = [0.07]"),
        "rob-xyz-nan": sub("xyz = [0.07, 0.0, 0.11]", "xyz = [nan, 0.0, 0.11]"),
        "rob-rpy-huge": sub("rpy = [3.141592653589793, 0.0, 0.0]", "rpy = [1e308, 0.0, 0.0]"),
        "rob-rpy-string": sub("rpy = [3.141592653589793, 0.0, 0.0]", 'rpy = ["pi", 0.0, 0.0]'),
        "rob-workspace-huge": sub("workspace_max = [0.9, 0.9, 0.9]", "workspace_max = [1e300, 0.9, 0.9]"),
        "rob-speed-huge": sub("max_linear_speed = 0.5", "max_linear_speed = 1e300"),
        "rob-watchdog-zero": sub("watchdog_hz = 10.0", "watchdog_hz = 0.0"),
        "rob-timeout-huge": sub("connect_timeout_s = 2.0", "connect_timeout_s = 1e300"),
        "rob-gripper-bogus": sub('kind = "digital"', 'kind = "magnet"'),
        "rob-unknown-key": sub('name = "ur5-sim"', 'name = "ur5-sim"\nwarp = 9'),
        "rob-not-toml": b"[[[", "rob-binary": b"\x00\xff\xfe\x01", "rob-empty": b"",
    }


def truth_kinds() -> dict[str, bytes]:
    """calibrate-mount --truth files."""
    eye = np.eye(4).tolist()
    return {
        "truth-list": b"[1, 2, 3]", "truth-no-key": b'{"mount": 1}', "truth-string": b'"flange_T_sensor"',
        "truth-3x3": json.dumps({"flange_T_sensor": np.eye(3).tolist()}).encode(),
        "truth-strings": json.dumps({"flange_T_sensor": [["a"] * 4] * 4}).encode(),
        "truth-ragged": json.dumps({"flange_T_sensor": [[1, 0], [0, 1, 0, 0], [], [0, 0, 0, 1]]}).encode(),
        "truth-nan": json.dumps({"flange_T_sensor": [[float("nan")] * 4] * 4}).encode(),
        "truth-bools": json.dumps({"flange_T_sensor": [[True] * 4] * 4}).encode(),
        "truth-scaled": json.dumps({"flange_T_sensor": (3 * np.eye(4)).tolist()}).encode(),
        "truth-far": json.dumps({"flange_T_sensor": [r[:3] + [1e300 if i < 3 else 1] for i, r in
                                                     enumerate(eye)]}).encode(),
        "truth-not-json": b"{flange", "truth-deep": b"[" * 100_000 + b"]" * 100_000,
    }


def capture_kinds() -> dict[str, bytes]:
    """Captures for calibrate-mount (8 frames) whose flange poses are impossible."""
    from place_safe.evaluation.synthetic import make_frames

    frames = [f.to_dict() for f in make_frames(8, seed=5)]

    def with_all(**extra) -> bytes:
        return json.dumps([dict(f, **extra) for f in frames]).encode()

    return {
        "cap-joints-huge": with_all(joint_angles=[1e300] * 6), "cap-joints-short": with_all(joint_angles=[0.1] * 3),
        "cap-joints-string": with_all(joint_angles="abc"), "cap-joints-null-entry": with_all(joint_angles=[0.1] * 5 + [None]),
        "cap-joints-bools": with_all(joint_angles=[True] * 6), "cap-joints-nested": with_all(joint_angles=[[0.1] * 6]),
        "cap-pose-huge": with_all(pose=[[1e300] * 4] * 4), "cap-pose-last-row": with_all(pose=np.diag([1, 1, 1, 0]).tolist()),
        "cap-pose-string": with_all(pose="identity"), "cap-pose-scaled": with_all(pose=(2 * np.eye(4)).tolist()),
        "cap-no-pose": with_all(),
        "cap-repeated": json.dumps(frames + frames).encode(),  # session 82: a capture given twice
    }


def task_file_kinds() -> dict[str, bytes]:
    fmt = {"format": "place_safe.calibration/1"}
    return {
        "cal-nan-peak": json.dumps({**fmt, "peak": {"m": float("nan"), "b": 13.0}}).encode(),
        "cal-string-peak": json.dumps({**fmt, "peak": "garbage"}).encode(),
        "cal-list-forward": json.dumps({**fmt, "forward": [1, 2]}).encode(),
    }


#: Sensor URIs, each with ``{fifo}`` / ``{tmp}`` / ``{scn-...}`` placeholders filled in.
SENSOR_URIS = [
    "emu:synthetic:100000000000", "emu:synthetic:0", "emu:synthetic:-5", "emu:synthetic:1e3",
    "emu:synthetic:" + "9" * 5000, "serial:{tmp}/no-port@99999999999", "serial:{fifo}", "serial:/dev/zero@0",
    "file:{fifo}", "file:/dev/zero", "file:{tmp}", "emu:file:/dev/zero", "emu:file:{fifo}", "i2c:/dev/zero",
    "i2c:1@0x999", "i2c:1@", "i2c:@0x41", "serial:@", "bogus:x", "", ":", "file:", "emu:", "emu:sim",
    "emu:scenario:{scn-scene-int}", "emu:scenario:no-such-scenario", "emu:scenario:{fifo}",
    "emu:file:{tmp}/no-such.json", "i2c:" + "1" * 5000,
]

#: Command-line values on the newer surfaces, each a full argv.
NEW_OPTION_RUNS = [
    ["capture", "--sim", "level_table", "-o", "{tmp}/c.jsonl", "--distances", "10:1e300:1"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/c.jsonl", "--distances", "10:nan:1"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/c.jsonl", "--distances", "10:90:1e-300"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/c.jsonl", "--distances", "::"],
    ["sim"], ["scenarios", "level_30cm", _LEVEL_30CM, "--quiet"],  # session 82: given twice, run and counted twice
    ["scenarios", "--jobs", "100000"], ["scenarios", "--jobs", "0"], ["scenarios", "--random", "10" * 10],
    ["scenarios", "--seconds", "1e300"], ["scenarios", "--seed=-1"], ["scenarios", "--seconds", "nan"],
    ["place", "--sim", "place_level", "--timeout", "1e300"], ["place", "--sim", "place_level", "--seed=-1"],
    ["place", "--sim", "place_level", "--sim-mount-error", "1e300,0,0,0,0,0"],
    ["place", "--sim", "place_level", "--sim-mount-error", "0,0,0,720,0,0"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--settle", "1e300"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--poses", "1000000000"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--frames-per-pose", "1000000000"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--distances", "1e300"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--speed", "1e300"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--touch-force", "nan"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--table-height", "nan"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--table-height", "0", "--table-tilt-std", "inf"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--incidences", "90,180"],
    ["capture", "--sim", "level_table", "-o", "{tmp}/cap.jsonl", "--distances", ",".join(["100"] * 1000)],
    ["capture", "--robot", _ROBOT, "--sensor", "emu:synthetic:3", "-o", "{tmp}/cap.jsonl", "--touch", "1e300,0"],
    ["calibrate-mount", _SWEEP, "--table-height", "nan", "--method", "peak"],
    ["calibrate-mount", _SWEEP, "--sigma-angle", "1e300", "--method", "peak"],
    ["calibrate-mount", _SWEEP, "--sigma-mm", "0", "--method", "peak"],
    ["calibrate-mount", _SWEEP, "--sigma-angle", "1e-160", "--method", "peak", "--level"],  # session 82: the weighted
    ["calibrate-mount", _SWEEP, "--sigma-mm", "1e-20", "--method", "peak", "--level"],  # residuals overflowed
    ["place", "--sim", "place_level", "--seed=-1", *_TMP_OUT], ["calibrate", "--sim", "nominal", "--frames", "1000000000"],
    ["sim", "render", "--distance", "1e300"], ["sim", "render", "--azimuth", "1e300"],
    ["bench", "sensor", "--bus-hz", "1e-300"], ["bench", "sensor", "--frames", "1000000000"],
    ["sensor", "stream", "emu:synthetic:3", "--timeout", "1e300"], ["sensor", "info", "emu:synthetic:3",
                                                                     "--period-ms", "99999999"],
    ["stream", "{good}", "--rate", "1e-300"], ["synth", "--max-angle", "nan", "-o", "{tmp}/s.json"],
]


#: Commands with an output option, ``{out}`` the output (a FIFO without a reader, a directory).
OUTPUT_RUNS = [
    ["place", "--sim", "place_level", "--timeout", "0.5", "--json", "{out}", "--log", "{tmp}/r.jsonl"],
    ["place", "--sim", "place_level", "--timeout", "0.5", "--log", "{out}", "--json", "{tmp}/r.json"],
    ["capture", "--sim", "level_table", "--poses", "1", "-o", "{out}"],
    ["calibrate-mount", _SWEEP, "--method", "peak", "-q", "--json", "{out}"],
    ["calibrate-mount", _SWEEP, "--method", "peak", "-q", "--write", "{out}"],
    ["scenarios", "level_30cm", "--quiet", "--json", "{out}"],
    ["sim", "render", "-o", "{out}"], ["synth", "--frames", "2", "-o", "{out}"],
    ["sensor", "record", "emu:synthetic:3", "--frames", "2", "-o", "{out}"],
    ["evaluate", "{good}", "--methods", "peak", "--no-plots", "-q", "--json", "{out}"],
    ["calibrate", "{good}", "--method", "peak", "-q", "-o", "{out}"],
]


def _second_round(root: Path, paths: dict[str, str]) -> list[tuple[str, list[str], bool]]:
    """Write the second-round files under ``root`` (names into ``paths``) and return their runs."""
    fifo = root / "fifo"
    if not fifo.exists():
        os.mkfifo(fifo)  # a named pipe: opening it would block until a writer appears
    paths["fifo"] = str(fifo)
    paths["dev-zero"] = "/dev/zero"
    for name, data in {**scenario_kinds(), **robot_kinds(), **truth_kinds(), **task_file_kinds(),
                       **capture_kinds()}.items():
        suffix = ".json" if name.endswith("-json") or not name.startswith(("scn-", "rob-")) else ".toml"
        p = root / f"{name}{suffix}"
        p.write_bytes(data)
        paths[name] = str(p)
    out = str(root)
    runs: list[tuple[str, list[str], bool]] = []
    for name in [*scenario_kinds(), "fifo", "dev-zero", "directory"]:
        f = paths[name]
        runs += [
            (f"scenarios/{name}", ["scenarios", f, "--quiet"], True),
            (f"place-sim/{name}", ["place", "--sim", f, "--timeout", "0.5", "--json", f"{out}/r.json", "--log",
                                   f"{out}/r.jsonl"], True),
            (f"capture-sim/{name}", ["capture", "--sim", f, "-o", f"{out}/cap-{name}.jsonl", "--poses", "1"], True),
        ]
    for name in [*robot_kinds(), "fifo", "dev-zero", "directory", "missing"]:
        f = paths[name]
        runs += [
            (f"place-robot/{name}", ["place", "--robot", f, "--sensor", "emu:synthetic:3", "--dry-run", "--json",
                                     f"{out}/r.json", "--log", f"{out}/r.jsonl"], False),
            (f"place-sim-robot-file/{name}", ["place", "--sim", "place_level", "--robot-file", f, "--timeout", "0.5",
                                              "--json", f"{out}/r.json", "--log", f"{out}/r.jsonl"], True),
            (f"capture-robot/{name}", ["capture", "--robot", f, "--sensor", "emu:synthetic:3", "--dry-run",
                                       "--table-height", "0", "-o", f"{out}/cap-{name}.jsonl"], False),
            (f"calibrate-mount-robot/{name}", ["calibrate-mount", _SWEEP, "--robot", f, "--method", "peak", "-q"],
             False),
        ]
    for name in [*truth_kinds(), "fifo", "dev-zero", "directory", "missing"]:
        runs.append((f"calibrate-mount-truth/{name}", ["calibrate-mount", _SWEEP, "--truth", paths[name], "--method",
                                                       "peak", "-q"], False))
    for name in capture_kinds():
        for poses in ("joints", "recorded"):
            runs.append((f"calibrate-mount-capture-{poses}/{name}", ["calibrate-mount", paths[name], "--method", "peak",
                                                                      "--poses", poses, "-q"], False))
    for name in [*task_file_kinds(), "fifo", "dev-zero", "directory"]:
        f = paths[name]
        runs += [
            (f"place-sim-calibration/{name}", ["place", "--sim", "place_level", "--method", "peak", "--calibration",
                                               f, "--timeout", "0.5", "--json", f"{out}/r.json", "--log",
                                               f"{out}/r.jsonl"], True),
            (f"place-sim-calibration-diff/{name}", ["place", "--sim", "place_level", "--calibration", f, "--timeout",
                                                    "0.5", "--json", f"{out}/r.json", "--log", f"{out}/r.jsonl"], True),
            (f"calibrate-mount-calibration/{name}", ["calibrate-mount", _SWEEP, "--calibration", f, "--method", "peak",
                                                     "-q"], False),
            (f"scenarios-calibration/{name}", ["scenarios", "level_30cm", "--calibration", f, "--quiet"], True),
        ]
    for name in ["fifo", "dev-zero"]:
        f = paths[name]
        runs += [
            (f"place-sim-config/{name}", ["place", "--sim", "place_level", "--config", f, "--json", f"{out}/r.json",
                                          "--log", f"{out}/r.jsonl"], True),
            (f"recover/{name}", ["recover", f, "--method", "peak", "--jsonl"], False),
            (f"calibrate-mount-capture/{name}", ["calibrate-mount", f, "--method", "peak"], False),
            (f"recover-calibration/{name}", ["recover", paths["good"], "--method", "peak", "--calibration", f], False),
            (f"sim-render-scene/{name}", ["sim", "render", "--scene", f, "-o", f"{out}/x.png"], True),
        ]
    for i, uri in enumerate(SENSOR_URIS):
        u = uri.format(**paths)
        runs += [
            (f"sensor-info/{i}:{uri[:40]}", ["sensor", "info", u], False),
            (f"sensor-stream/{i}:{uri[:40]}", ["sensor", "stream", u, "--max-frames", "2", "--jsonl"], False),
        ]
    for name in ["fifo", "directory"]:  # outputs: a FIFO nobody reads would block the writer for ever
        o = paths[name]
        for i, argv in enumerate(OUTPUT_RUNS):
            runs.append((f"output-{name}/{i}:{' '.join(argv[:2])}", [a.format(out=o, **paths) for a in argv],
                         argv[0] in ("sim", "scenarios", "place", "capture")))
    for i, argv in enumerate(NEW_OPTION_RUNS):
        runs.append((f"new-option/{i}:{' '.join(argv[:2])}", [a.format(**paths) for a in argv],
                     argv[0] in ("sim", "scenarios", "place", "capture")))
    return runs


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
    return runs + _second_round(root, paths)


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
def test_corpus_run(tmp_path_factory, capsys, monkeypatch, index):
    _, runs = _corpus(tmp_path_factory)
    name, argv, _ = runs[index]
    monkeypatch.chdir(tmp_path_factory.mktemp("cwd"))  # a run's default outputs (place-result.json) land there, not in
    # the checkout, where parallel workers share the working folder
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


@pytest.mark.parametrize("kind, words", [("cal-domain-equal", "residual_domain must be"),
                                         ("cal-domain-reversed", "residual_domain must be"),
                                         ("cal-domain-rounding", "residual_domain must be"),
                                         ("cal-uncertainty-no-floor", "states no model error"),
                                         ("cal-uncertainty-scale-1e-12", "scale")])
def test_calibrations_that_shrink_or_break_the_peak_mapping_are_one_line_errors(tmp_path, capsys, kind, words):
    """Session 66's calibrations: recover refuses each with the file's one-line calibration error (exit 2), evaluate
    lists peak as unavailable with it (no internal error, exit 1, as the zero-width domain gave both)."""
    path = tmp_path / f"{kind}.json"
    path.write_bytes(calibration_kinds()[kind])
    good = tmp_path / "good.json"
    good.write_text(_dump(_frames()))
    assert main(["recover", str(good), "--method", "peak", "--calibration", str(path), "--jsonl", "-q"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and words in err and str(path) in err, err
    assert main(["evaluate", str(good), "--calibration", str(path), "--methods", "peak", "--no-plots", "-q"]) == 0
    out = capsys.readouterr().out
    assert "peak               unavailable: CalibrationError" in out and words in out, out


def test_recover_jsonl_with_a_calibration_lacking_the_method_says_so_on_stderr(tmp_path, capsys):
    """``recover --jsonl --method diff --calibration PEAK_ONLY`` said only "recovered N of N frames": standard output
    stays JSON lines ("calibrated": false), and standard error carries the UNCALIBRATED line the table mode prints first
    (not with -q, whose standard error stays empty)."""
    cal = tmp_path / "peak-only.json"
    cal.write_bytes(calibration_kinds()["cal-good-bom"])
    good = tmp_path / "good.json"
    good.write_text(_dump(_frames()))
    assert main(["recover", str(good), "--method", "proprietary", "--calibration", str(cal), "--jsonl"]) == 0
    cap = capsys.readouterr()
    assert all(json.loads(x)["calibrated"] is False for x in cap.out.splitlines())
    assert cap.err.startswith("UNCALIBRATED:") and "no proprietary section" in cap.err.splitlines()[0]
    assert main(["recover", str(good), "--method", "proprietary", "--calibration", str(cal), "--jsonl", "-q"]) == 0
    assert capsys.readouterr().err == ""


def replay(runs: list[tuple[str, list[str], bool]], timeout: float = 120.0, jobs: int = 1) -> dict[str, list[str]]:
    """Run every corpus entry as its own ``place-safe`` process (stdin closed, ``timeout`` s each) and sort the
    runs that break the contract: "traceback", "hang", "exit" (a status other than 0 / 2), "contract" (more
    than one error line, output with an error, a NaN or a plane behind the sensor)."""
    import subprocess
    from concurrent.futures import ThreadPoolExecutor

    def one(run: tuple[str, list[str], bool]) -> tuple[str, str | None]:
        name, argv, _ = run
        try:
            proc = subprocess.run([sys.executable, "-m", "place_safe.cli", *argv], stdin=subprocess.DEVNULL,
                                  capture_output=True, text=True, timeout=timeout, errors="replace")
        except subprocess.TimeoutExpired:
            return name, "hang"
        if "Traceback" in proc.stderr or "Traceback" in proc.stdout:
            return name, "traceback"
        if proc.returncode not in (0, 2):
            return name, "exit"
        try:
            check_run(argv, proc.returncode, proc.stdout, proc.stderr)
        except (AssertionError, ValueError):
            return name, "contract"
        return name, None

    bad: dict[str, list[str]] = {"traceback": [], "hang": [], "exit": [], "contract": []}
    with ThreadPoolExecutor(max(1, jobs)) as pool:
        for name, why in pool.map(one, runs):
            if why is not None:
                bad[why].append(name)
    return bad


if __name__ == "__main__":  # write the corpus and list its runs, or replay them (--replay)
    import argparse

    ap = argparse.ArgumentParser(description="Write the adversarial corpus to DIR and list its runs as JSON lines; "
                                             "with --replay run each as a place-safe process and count failures.")
    ap.add_argument("dir", nargs="?", default="adversarial-corpus")
    ap.add_argument("--replay", action="store_true", help="run every entry (a process each) and print the counts")
    ap.add_argument("--only", nargs="*", default=[], metavar="PREFIX", help="only runs whose name starts so")
    ap.add_argument("--timeout", type=float, default=120.0, help="s per run before it counts as a hang")
    ap.add_argument("--jobs", type=int, default=1, help="runs at once")
    a = ap.parse_args()
    all_runs = [r for r in build_corpus(Path(a.dir)) if not a.only or r[0].startswith(tuple(a.only))]
    if not a.replay:
        for name, argv, _ in all_runs:
            print(json.dumps({"name": name, "argv": argv}))
        sys.exit(0)
    result = replay(all_runs, a.timeout, a.jobs)
    for why, names in result.items():
        for n in names:
            print(f"{why}: {n}")
    print(f"{len(all_runs)} runs: " + ", ".join(f"{len(v)} {k}" for k, v in result.items()))
    sys.exit(1 if any(result.values()) else 0)


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


# ---------------------------------------------------------------------------------------------------
# The library API a task script uses (issue 30): constructors and loaders given the wrong kind of thing
# ---------------------------------------------------------------------------------------------------
def library_cases(root: Path) -> dict[str, object]:
    """Name -> zero-argument call. Each must return or raise a one-line TypeError / ValueError / place_safe error,
    within a bound (never block on a FIFO, never read /dev/zero until memory runs out)."""
    from place_safe.calibration import Calibration
    from place_safe.calibration.capture import SweepPlan
    from place_safe.drivers.ur5 import URConfig
    from place_safe.io.frame_file import load_frames
    from place_safe.placement.loop import PlacementLoop
    from place_safe.placement.machine import PlacementConfig
    from place_safe.recovery import make_estimator
    from place_safe.recovery.forward import ForwardParams
    from place_safe.sources import open_source

    fifo = root / "lib-fifo"
    if not fifo.exists():
        os.mkfifo(fifo)
    cal = root / "lib-cal.json"
    cal.write_text(json.dumps({"format": "place_safe.calibration/1", "peak": {"m": 72.0, "b": 13.0}}))
    cases: dict[str, object] = {
        "make_estimator-path": lambda: make_estimator("peak", str(cal)),
        "make_estimator-pathlib": lambda: make_estimator("peak", cal),
        "make_estimator-dict": lambda: make_estimator("peak", {"peak": {"m": 72.0, "b": 13.0}}),
        "make_estimator-int": lambda: make_estimator("peak", 5),
        "make_estimator-method-int": lambda: make_estimator(5),
        "make_estimator-method-bogus": lambda: make_estimator("bogus"),
        "Calibration-garbage-section": lambda: Calibration({"peak": "garbage"}),
        "Calibration-string": lambda: Calibration("calib.json"),
        "Calibration-list": lambda: Calibration([1, 2]),
        "Calibration-unknown-section": lambda: Calibration({"bogus": {}}),
        "Calibration-nan": lambda: Calibration({"peak": {"m": float("nan"), "b": 13.0}}),
        "Calibration-from_dict-list": lambda: Calibration.from_dict([1]),
        "PlacementLoop-config-string": lambda: PlacementLoop(_robot(), _source(), _estimator(), config="x"),
        "PlacementLoop-config-dict": lambda: PlacementLoop(_robot(), _source(), _estimator(), config={}),
        "PlacementLoop-robot-string": lambda: PlacementLoop("ur5", _source(), _estimator()),
        "PlacementLoop-source-uri": lambda: PlacementLoop(_robot(), "emu:synthetic", _estimator()),
        "PlacementLoop-estimator-name": lambda: PlacementLoop(_robot(), _source(), "peak"),
        "PlacementLoop-period-string": lambda: PlacementLoop(_robot(), _source(), _estimator(), period="fast"),
        "PlacementConfig-string": lambda: PlacementConfig(accel="fast"),
        "open_source-int": lambda: open_source(5),
        "open_source-huge-synthetic": lambda: open_source("emu:synthetic:100000000000"),
        "open_source-fifo": lambda: open_source(f"file:{fifo}"),
        "open_source-rate-string": lambda: open_source(f"file:{cal}", rate_hz="fast"),
        "open_source-rate-tiny": lambda: open_source(f"file:{cal}", rate_hz=1e-300),
        "open_source-unknown-option": lambda: open_source("emu:synthetic:3", warp=9),
        "SweepPlan-settle-huge": lambda: SweepPlan(settle_s=1e300),
        "SweepPlan-distances-nan": lambda: SweepPlan(distances=[float("nan")]),
        "SweepPlan-speed-string": lambda: SweepPlan(speed="fast"),
        "SweepPlan-axis-huge": lambda: SweepPlan(azimuths=[0.0] * 100_000),
        "make_estimator-bad-option": lambda: make_estimator("peak", None, warp=9),
    }
    try:
        from place_safe.sim.placement_run import run_placement
        from place_safe.sim.scenario import load_scenario
        from place_safe.sim.world import error_transform
    except ImportError:  # without the [sim] extra
        pass
    else:
        cases.update({
            "run_placement-seconds-string": lambda: run_placement("place_level", seconds="10"),
            "run_placement-seconds-huge": lambda: run_placement("place_level", seconds=1e300),
            "error_transform-huge": lambda: error_transform([1e300] * 6),
            "error_transform-string": lambda: error_transform("abc"),
            "load_scenario-fifo": lambda: load_scenario(fifo), "load_scenario-dev-zero": lambda: load_scenario("/dev/zero"),
            "load_scenario-int": lambda: load_scenario(5), "load_scenario-dir": lambda: load_scenario(root),
        })
    for name, where in (("fifo", fifo), ("dev-zero", "/dev/zero"), ("dir", root), ("int", 5)):
        cases.update({
            f"Calibration.load-{name}": lambda w=where: Calibration.load(w),
            f"PlacementConfig.load-{name}": lambda w=where: PlacementConfig.load(w),
            f"URConfig.load-{name}": lambda w=where: URConfig.load(w),
            f"ForwardParams.load-{name}": lambda w=where: ForwardParams.load(w),
            f"load_frames-{name}": lambda w=where: load_frames(w),
        })
    return cases


def _robot():
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "support"))
    from placement_fakes import KinematicRobot

    return KinematicRobot()


def _source():
    from placement_fakes import TruthSource

    return TruthSource(_robot())


def _estimator():
    from placement_fakes import TruthEstimator

    return TruthEstimator()


def _library_params():
    import tempfile

    with tempfile.TemporaryDirectory() as d:
        return sorted(library_cases(Path(d)))


@pytest.mark.parametrize("name", _library_params())
def test_library_call(tmp_path, name):
    import threading

    from place_safe.exceptions import PlaceSafeError

    call = library_cases(tmp_path)[name]
    outcome: dict[str, object] = {}

    def target():
        try:
            outcome["value"] = call()
        except BaseException as exc:  # noqa: BLE001 - judged below
            outcome["error"] = exc

    t = threading.Thread(target=target, daemon=True)
    t.start()
    t.join(60.0)
    assert not t.is_alive(), f"{name} did not return (blocked)"
    exc = outcome.get("error")
    if exc is not None:
        assert isinstance(exc, (PlaceSafeError, TypeError, ValueError)), f"{name}: {type(exc).__name__}: {exc}"
        assert not isinstance(exc, (AttributeError, KeyError)), f"{name}: {type(exc).__name__}: {exc}"
        assert str(exc).strip() and len(str(exc).strip().splitlines()) == 1, f"{name}: {exc!r}"
    else:
        assert name.startswith("make_estimator-method") is False  # a wrong method never builds an estimator
