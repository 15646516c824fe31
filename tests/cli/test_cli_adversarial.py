"""Property-based tests of the command line's argument checks (place_safe.cli.app, place_safe.cli.options).

Every numeric option of every command, given any text: either the parser accepts a value inside the
option's documented range, or ``main`` exits with status 2 and exactly one line on standard error
(no traceback, nothing on standard output) before any work starts.
"""

from __future__ import annotations

import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from place_safe.cli.app import build_parser, main
from place_safe.cli.common import UsageError

#: (command words, option, kind, lo, hi, lo_open): the documented range of each numeric option.
OPTIONS = [
    (["recover", "f.json", "--method", "peak"], "--batch", int, 1, 4096, False),
    (["evaluate", "f.json"], "--min-distance", float, 0.0, math.inf, False),
    (["evaluate", "f.json"], "--max-distance", float, 0.0, math.inf, True),
    (["stream", "f.json"], "--rate", float, 0.0, 10000.0, True),
    (["stream", "f.json"], "--max-frames", int, 1, math.inf, False),
    (["stream", "f.json"], "--queue", int, 1, 10000, False),
    (["bench", "recovery"], "--frames", int, 1, 100000, False),
    (["bench", "recovery"], "--paper-frames", int, 0, 10000, False),
    (["bench", "recovery"], "--memory-file", int, 1, 1000000, False),
    (["bench", "recovery"], "--seed", int, 0, math.inf, False),
    (["bench", "sim"], "--seconds", float, 0.0, 3600.0, True),
    (["bench", "sim"], "--rate", float, 1.0, 200.0, False),  # the simulated sensor's rate_hz (ToFConfig)
    (["bench", "sim"], "--rays", int, 1, 64, False),
    (["place", "--sim", "place_level"], "--timeout", float, 0.0, 3600.0, True),
    (["place", "--sim", "place_level"], "--seed", int, 0, math.inf, False),
    (["calibrate", "--sim", "nominal"], "--frames", int, 8, 1000, False),
    (["demo"], "--frames", int, 1, 100000, False),
    (["demo"], "--seed", int, 0, math.inf, False),
    # counts and sizes that ran for ever at a 20-digit value (an adversarial round, session 73)
    (["bench", "contact"], "--cycles", int, 1, 100_000_000, False),
    (["bench", "contact"], "--descents", int, 0, 100_000, False),
    (["bench", "contact"], "--touch-trials", int, 0, 100_000, False),
    (["bench", "contact"], "--height", float, 0.0, 2.0, True),
    (["bench", "contact"], "--stiffness", float, 0.0, 1e8, True),
    (["bench", "contact"], "--jobs", int, 1, 64, False),
    (["bench", "robot", "--fake"], "--seconds", float, 0.0, 3600.0, True),
    (["bench", "robot", "--fake"], "--cycles", int, 1, 100_000_000, False),
]
SIM_OPTIONS = [
    (["sim", "render"], "--width", int, 16, 4096, False),
    (["sim", "render"], "--height", int, 16, 4096, False),
    (["sim", "render"], "--elevation", float, -90.0, 90.0, False),
    (["sim", "render"], "--distance", float, 0.0, math.inf, True),
    (["sim", "validate", "f.json"], "--rays", int, 1, 64, False),
    (["sim", "validate", "f.json"], "--min-distance", float, 0.0, math.inf, False),
]

values = st.one_of(
    st.text(max_size=12),
    st.integers(-10**6, 10**6).map(str),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.sampled_from(["nan", "NaN", "inf", "-inf", "1e309", "0", "-0", "0.0", "1e-320", "9" * 5000, " 5 ", "5.",
                     "0x10", "1_000", "½", "٣", "\x00", "5\n6", ""]),
)


def _parser(sim: bool):
    return build_parser(load_sim=sim)


def _check(words, option, kind, lo, hi, lo_open, text, sim):
    parser = _parser(sim)
    argv = [*words, f"{option}={text}"]
    try:
        args = parser.parse_args(argv)
    except UsageError as exc:
        assert "\n" not in str(exc).strip()
        return
    value = getattr(args, option.lstrip("-").replace("-", "_"))
    assert isinstance(value, kind) and not isinstance(value, bool)
    assert math.isfinite(value)
    assert (value > lo if lo_open else value >= lo) and value <= hi


@settings(max_examples=400, deadline=None)
@given(spec=st.sampled_from(OPTIONS), text=values)
def test_numeric_options_accept_only_their_range(spec, text):
    _check(*spec, text, sim=False)


@pytest.mark.sim
@settings(max_examples=200, deadline=None)
@given(spec=st.sampled_from(SIM_OPTIONS), text=values)
def test_sim_numeric_options_accept_only_their_range(spec, text):
    _check(*spec, text, sim=True)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(spec=st.sampled_from(OPTIONS), text=st.sampled_from(["nan", "inf", "-1", "0", "abc", "1e309", "9" * 5000]))
def test_bad_values_exit_2_with_one_line(capsys, spec, text):
    words, option, kind, lo, hi, lo_open = spec
    try:
        kind(text)
        value = kind(text)
        ok = math.isfinite(value) and (value > lo if lo_open else value >= lo) and value <= hi
    except (ValueError, OverflowError):
        ok = False
    if ok:
        return
    assert main([*words, f"{option}={text}"]) == 2
    cap = capsys.readouterr()
    lines = [x for x in cap.err.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("place-safe: error:") and option in lines[0]
    assert cap.out == "" and "Traceback" not in cap.err


@pytest.mark.parametrize("argv", [
    ["stream", "f.json", "--method", "bogus"],
    ["evaluate", "f.json", "--min-distance", "0.3", "--max-distance", "0.1"],
    ["recover", "f.json"],
    ["nosuchcommand"],
    [],
    ["--frobnicate"],
])
def test_usage_errors_are_one_line(capsys, argv):
    assert main(argv) == 2
    cap = capsys.readouterr()
    assert len([x for x in cap.err.splitlines() if x.strip()]) == 1 and cap.out == ""


@pytest.mark.parametrize("argv", [
    ["evaluate", "{frames}", "--methods", "peak", "--no-plots", "-q", "--json", "{frames}"],
    ["evaluate", "{frames}", "--methods", "peak", "--no-plots", "-q", "--calibration", "{cal}", "--json", "{cal}"],
    ["latency", "{frames}", "--method", "peak", "--json", "{frames}"],
    # a source URI that reads the file (a review, session 74: --force then replaced the recording it read)
    ["sensor", "record", "file:{frames}", "-o", "{frames}", "--frames", "2", "--force"],
    ["sensor", "record", "emu:file:{frames}", "-o", "{frames}", "--frames", "2", "--force"],
])
def test_an_output_that_names_an_input_is_refused_and_the_input_kept(tmp_path, capsys, argv):
    """``evaluate F.json --json F.json`` replaced the frames with its report (and ``--calibration C --json C`` the
    calibration, ``latency X --json X`` its input): an adversarial round, session 74. One line, exit 2, the file as
    it was, even through another path to it."""
    import json
    import os
    from pathlib import Path

    sweep = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"
    frames, cal = tmp_path / "f.json", tmp_path / "cal.json"
    frames.write_text(json.dumps(json.loads(sweep.read_text())[10:13]))
    cal.write_text(json.dumps({"format": "place_safe.calibration/1"}))
    os.symlink(frames, tmp_path / "link.json")
    for out in ("same", "link"):
        words = [w.format(frames=frames, cal=cal) for w in argv]
        if out == "link":  # the output given by another name of the same file
            words[-1] = str(tmp_path / "link.json") if words[-1] == str(frames) else words[-1]
        before = {p: p.read_bytes() for p in (frames, cal)}
        try:
            code = main(words)
        except SystemExit as exc:  # an option the command does not have: argparse's own usage error
            code = exc.code
        cap = capsys.readouterr()
        assert code == 2, words
        assert len([x for x in cap.err.splitlines() if x.strip()]) == 1, cap.err
        assert {p: p.read_bytes() for p in (frames, cal)} == before


def test_write_may_rewrite_the_robot_file_it_reads(tmp_path):
    """``--write`` rewrites the robot file with the fitted mount or measured noise and keeps the rest of it: naming
    the ``--robot`` file there is an update in place, not an input destroyed."""
    import argparse

    from place_safe.cli.app import _input_named

    robot = tmp_path / "mine.toml"
    robot.write_text("")
    args = argparse.Namespace(command="calibrate-mount", robot=str(robot), write=str(robot), json=str(robot))
    assert _input_named(args, "write", str(robot)) is None
    assert _input_named(args, "json", str(robot)) == f"ROBOT {robot}"


def test_an_output_that_cannot_be_written_is_refused_before_the_run(tmp_path, capsys, monkeypatch):
    """``evaluate --json /proc/x.json`` said so only after the whole evaluation (minutes with diff): an adversarial
    round, session 74. The output is opened before anything runs, and a file that was not there is not left behind."""
    from pathlib import Path

    import place_safe.cli.sensing as sensing

    ran = []
    monkeypatch.setattr(sensing, "evaluate", lambda *a, **k: ran.append(1))
    sweep = Path(__file__).resolve().parents[1] / "data" / "tmf8820_ur5_sweep.json"
    assert main(["evaluate", str(sweep), "--methods", "peak", "--no-plots", "-q", "--json", "/proc/x.json"]) == 2
    err = capsys.readouterr().err
    assert "cannot be written" in err and len(err.strip().splitlines()) == 1 and not ran
    out = tmp_path / "new.json"
    assert main(["synth", "--frames", "1", "-o", str(out)]) == 0 and out.exists()  # a writable one is written
