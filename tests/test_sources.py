"""open_source: every scheme, and one-line errors for bad URIs and options."""

from __future__ import annotations

import numpy as np
import pytest

from place_safe.drivers.tmf8820.bench import random_frames
from place_safe.drivers.tmf8820.emulated import EmulatedTMF8820
from place_safe.drivers.tmf8820.serial_bridge import BridgeSource
from place_safe.exceptions import ConfigError, FrameFileError, SensorError
from place_safe.io.frame_file import write_frames
from place_safe.io.replay import FileReplaySource
from place_safe.sources import open_source


@pytest.fixture
def frame_file(tmp_path):
    path = tmp_path / "frames.json"
    write_frames(path, random_frames(4, seed=3))
    return path


def test_file_source(frame_file):
    with open_source(f"file:{frame_file}", realtime=False) as src:
        assert isinstance(src, FileReplaySource) and src.clock_domain == "monotonic"
        assert len(list(src.frames())) == 4


def test_emulated_file_source_delivers_the_file_through_the_driver(frame_file):
    with open_source(f"emu:file:{frame_file}", realtime=False, bus_hz=1e6) as src:
        assert isinstance(src, EmulatedTMF8820) and src.clock_domain == "emulator"
        got = list(src.frames(2.0))
    fed = random_frames(4, seed=3)
    assert len(got) == 4
    for g, f in zip(got, fed):
        np.testing.assert_array_equal(g.hists, f.hists)
    assert src.stats["frames"] == 4


def test_emulated_synthetic_in_real_time_is_on_the_monotonic_clock():
    import time

    with open_source("emu:synthetic:2", bus_hz=1e6) as src:
        f = src.read(2.0)
        assert src.clock_domain == "monotonic"
        assert abs(time.monotonic() - f.timestamp) < 0.5


def test_serial_log_source(tmp_path):
    log = tmp_path / "bridge.log"
    log.write_text("#Vers,1\n")
    with open_source(f"serial:{log}") as src:
        assert isinstance(src, BridgeSource)
        with pytest.raises(StopIteration):
            src.read(0.1)


@pytest.mark.parametrize("uri, match", [
    ("frames.json", "not a source URI"),
    ("ftp:x", "unknown scheme"),
    ("emu:", "nothing after"),
    ("i2c:/dev/i2c-1@zz", "not a number"),
    ("i2c:/dev/i2c-1@0x90", "not a 7-bit"),
    ("i2c:/dev/i2c-1@", "expected i2c:BUS@ADDRESS"),
    ("serial:/dev/ttyX@fast", "not a number"),
    ("emu:sim", "needs the simulated sensor"),
    ("emu:synthetic:0", ">= 1"),
    ("emu:synthetic:", "expected emu:synthetic or emu:synthetic:N"),  # (read as the default 100 frames: round 15)
    ("emu:file:", "expected emu:file:PATH"),
])
def test_bad_uris_are_one_line_config_errors(uri, match):
    with pytest.raises(ConfigError, match=match) as info:
        open_source(uri)
    assert "\n" not in str(info.value)


def test_unknown_options_are_config_errors(frame_file):
    with pytest.raises(ConfigError, match="does not take option"):
        open_source(f"file:{frame_file}", bus_hz=1e6)
    with pytest.raises(ConfigError, match="only for emu:sim"):
        open_source("emu:synthetic:1", tof=object())


def test_missing_devices_and_files():
    with pytest.raises(SensorError, match="cannot open I2C bus"):
        open_source("i2c:/dev/i2c-does-not-exist@0x41")
    with pytest.raises(FrameFileError):
        open_source("file:/nonexistent/frames.json")


# -- feeds other packages register (the simulation registers emu:scenario: the library never imports it) -----
def test_a_registered_feed_is_opened_through_the_emulator(monkeypatch):
    from place_safe import sources

    monkeypatch.setattr(sources, "FEEDS", {})
    seen = []

    def feed(uri, arg):
        seen.append((uri, arg))
        return random_frames(3, seed=1)

    sources.register_feed("canned", feed)
    with open_source("emu:canned:three", realtime=False) as src:
        assert isinstance(src, EmulatedTMF8820) and src.read(1.0).hists.shape == (9, 128)
    assert seen == [("emu:canned:three", "three")]


@pytest.mark.parametrize("kind, factory", [("file", lambda u, a: []), ("sim", lambda u, a: []), ("two words", len),
                                           ("ok", "not callable")])
def test_register_feed_refuses_built_in_kinds_and_non_callables(kind, factory):
    from place_safe.sources import register_feed

    with pytest.raises(ConfigError):
        register_feed(kind, factory)


def test_the_simulation_is_found_through_its_entry_point(monkeypatch):
    """``emu:scenario:`` and ``emu:NAME`` reach the simulation's feed through the ``place_safe.sources`` group."""
    from importlib.metadata import entry_points

    from place_safe import sources

    eps = {ep.name: ep.value for ep in entry_points(group=sources.FEED_GROUP)}
    assert eps.get("scenario") == "place_safe.sim.sources:scenario_feed"
    monkeypatch.setattr(sources, "FEEDS", {})
    monkeypatch.setattr(sources, "_loaded_entry_points", [])
    pytest.importorskip("mujoco")
    with pytest.raises(ConfigError, match="no_such_scenario"):  # the simulation's own one-line error
        open_source("emu:no_such_scenario")
    assert "scenario" in sources.FEEDS
