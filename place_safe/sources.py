"""Frame sources by name: ``open_source(uri, **options)`` turns a source URI into a FrameSource.

URIs
----
``file:PATH``
    Replay a frame file (:class:`~place_safe.io.replay.FileReplaySource`; options ``rate_hz``, ``loop``,
    ``realtime``, ``clock``).
``i2c:BUS[@ADDRESS]``
    A TMF8820 on Linux I2C, e.g. ``i2c:/dev/i2c-1@0x41`` or ``i2c:1`` (address default 0x41;
    :class:`~place_safe.drivers.tmf8820.i2c.TMF8820Source`; options ``patch`` (Intel HEX path),
    ``period_ms``, ``kilo_iterations``, ``short_range``, ``calibration_dir``, ``int_line``
    (``"CHIP:OFFSET"``, e.g. ``"/dev/gpiochip0:17"``, or an object with ``wait``), ``clock``, ``start``).
``serial:PORT[@BAUD]``
    The Arduino bridge on a serial port (baud default 115200), or a recorded bridge log when PORT is a
    regular file (:class:`~place_safe.drivers.tmf8820.serial_bridge.BridgeSource`; option ``address``;
    BAUD 300..4000000).
``emu:SOURCE``
    The I2C driver over the register-level emulator
    (:class:`~place_safe.drivers.tmf8820.emulated.EmulatedTMF8820`) fed by SOURCE: ``file:PATH`` (a
    frame file), ``synthetic[:N]`` (N synthetic frames, 1..100000, default 100), ``sim`` (the simulated
    sensor passed as option ``tof``, clocked by its simulation: ``clock_domain`` "robot"), or a feed
    another package registers (:func:`register_feed`): the simulation registers ``scenario:NAME`` (the
    simulated sensor over a packaged scenario's table, needs the [sim] extra; ``NAME`` alone means the same). Options
    ``bus_hz`` (default 400 kHz), ``realtime`` (default True: frames at the pace of the emulated bus on
    the host clock; False: virtual time), ``loop``, ``faults``, ``patch``, ``record``, ``clock``, and
    the driver's options (``period_ms``, ``kilo_iterations``, ...).

A malformed URI or an option the source does not take raises a one-line
:class:`~place_safe.exceptions.ConfigError`; a device that cannot be opened raises
:class:`~place_safe.exceptions.SensorError`.
"""

from __future__ import annotations

from collections.abc import Callable
from importlib.metadata import entry_points
from pathlib import Path
from typing import Any

from place_safe.exceptions import ConfigError
from place_safe.io.source import FrameSource
from place_safe.drivers.tmf8820.emulated import EmulatedTMF8820
from place_safe.drivers.tmf8820.hexfile import load_patch
from place_safe.drivers.tmf8820.i2c import GpiodIntLine, TMF8820Source
from place_safe.drivers.tmf8820.registers import DEFAULT_ADDRESS
from place_safe.drivers.tmf8820.serial_bridge import BridgeSource
from place_safe.io.replay import FileReplaySource

SCHEMES = ("file", "i2c", "serial", "emu")
#: Frames an ``emu:synthetic:N`` source may make (they are built in memory before the first read).
MAX_SYNTHETIC = 100_000
#: Baud rates a serial port is opened with (bit/s): what USB-serial bridges offer.
BAUD_RANGE = (300, 4_000_000)
#: ``emu:KIND`` feeds this module makes itself.
_BUILT_IN_FEEDS = ("file", "synthetic", "sim")
#: Makes an emulator feed from (the whole URI, for messages; the text after ``emu:KIND:``).
FeedFactory = Callable[[str, str], Any]
#: ``emu:KIND`` feeds registered by other packages (:func:`register_feed`): kind -> factory.
FEEDS: dict[str, FeedFactory] = {}
#: Entry-point group of feed factories (name = kind), read once, when a URI names a kind not registered.
FEED_GROUP = "place_safe.sources"
#: The kind of ``emu:NAME`` when NAME is no registered kind: ``emu:place_level`` is ``emu:scenario:place_level``.
DEFAULT_FEED = "scenario"
_loaded_entry_points: list[str] = []
_unavailable: dict[str, str] = {}
_DRIVER_OPTIONS = {"patch", "period_ms", "kilo_iterations", "short_range", "calibration_dir", "int_line", "clock",
                   "start", "retries", "poll_s"}


def _check(uri: str, options: dict, allowed: set[str]) -> None:
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ConfigError(f"source {uri!r} does not take option(s) {', '.join(unknown)}; "
                          f"it takes {', '.join(sorted(allowed)) or 'none'}")


def _split_at(rest: str, uri: str, what: str) -> tuple[str, str | None]:
    if "@" in rest:
        left, right = rest.rsplit("@", 1)
        if not left or not right:
            raise ConfigError(f"source {uri!r}: expected {what}")
        return left, right
    return rest, None


def _int(text: str, uri: str, what: str) -> int:
    if len(text) > 20:  # no count, address or rate has more digits (and int() of a huge one is slow)
        raise ConfigError(f"source {uri[:80]!r}: {what} {text[:20]!r}... is too long a number")
    try:
        return int(text, 0)
    except ValueError:
        raise ConfigError(f"source {uri!r}: {what} {text!r} is not a number") from None


def _int_line(spec: Any) -> Any:
    if spec is None or hasattr(spec, "wait"):
        return spec
    chip, _, offset = str(spec).rpartition(":")
    if not chip or not offset.isdigit():
        raise ConfigError(f"int_line {spec!r}: expected CHIP:OFFSET, e.g. /dev/gpiochip0:17")
    return GpiodIntLine(chip, int(offset))


def open_source(uri: str, **options: Any) -> FrameSource:
    """The frame source named by ``uri`` (see module docstring), opened and ready to ``read``."""
    if not isinstance(uri, str) or ":" not in uri:
        raise ConfigError(f"source {uri!r} is not a source URI; expected one of "
                          + ", ".join(f"{s}:..." for s in SCHEMES))
    scheme, rest = uri.split(":", 1)
    if scheme not in SCHEMES:
        raise ConfigError(f"source {uri!r}: unknown scheme {scheme!r}; expected one of "
                          + ", ".join(f"{s}:" for s in SCHEMES))
    if not rest:
        raise ConfigError(f"source {uri!r}: nothing after '{scheme}:'")
    if scheme == "file":
        _check(uri, options, {"rate_hz", "loop", "realtime", "clock"})
        return FileReplaySource(rest, **options)
    if scheme == "i2c":
        _check(uri, options, _DRIVER_OPTIONS)
        bus, addr = _split_at(rest, uri, "i2c:BUS@ADDRESS, e.g. i2c:/dev/i2c-1@0x41")
        address = DEFAULT_ADDRESS if addr is None else _int(addr, uri, "address")
        if not 0 < address < 0x78:
            raise ConfigError(f"source {uri!r}: 0x{address:x} is not a 7-bit device address")
        bus_arg: int | str = int(bus) if bus.isdigit() else bus
        opts = dict(options)
        opts["int_line"] = _int_line(opts.get("int_line"))
        return TMF8820Source(bus_arg, address, **opts)
    if scheme == "serial":
        _check(uri, options, {"address", "clock"})
        if Path(rest).is_file():
            return BridgeSource.open_log(rest, **options)
        port, baud = _split_at(rest, uri, "serial:PORT@BAUD, e.g. serial:/dev/ttyACM0@115200")
        rate = 115200 if baud is None else _int(baud, uri, "baud rate")
        if not BAUD_RANGE[0] <= rate <= BAUD_RANGE[1]:
            raise ConfigError(f"source {uri!r}: baud rate {rate} outside {BAUD_RANGE[0]}..{BAUD_RANGE[1]}")
        return BridgeSource.open_serial(port, rate, **options)
    return _open_emulated(uri, rest, options)


def _open_emulated(uri: str, inner: str, options: dict) -> FrameSource:
    _check(uri, options, _DRIVER_OPTIONS | {"bus_hz", "realtime", "loop", "faults", "record", "tof", "emulator"})
    opts = dict(options)
    emu_kw = {k: opts.pop(k) for k in ("bus_hz", "faults", "record", "clock") if k in opts}
    realtime = bool(opts.pop("realtime", True))
    loop = bool(opts.pop("loop", False))
    tof = opts.pop("tof", None)
    emulator_kw = opts.pop("emulator", None)
    patch = opts.pop("patch", None)
    if isinstance(patch, (str, Path)):
        patch = load_patch(patch)
    kind, _, arg = inner.partition(":")
    if kind == "file":
        if not arg:
            raise ConfigError(f"source {uri!r}: expected emu:file:PATH")
        feed: Any = FileReplaySource(arg, realtime=False, loop=loop)
    elif kind == "synthetic":
        from place_safe.evaluation.synthetic import make_frames

        if inner.endswith(":") and not arg:  # "emu:synthetic:" read as the default count hid a count left out
            raise ConfigError(f"source {uri!r}: expected emu:synthetic or emu:synthetic:N (N frames, 1..{MAX_SYNTHETIC})")
        n = _int(arg, uri, "frame count") if arg else 100
        if not 1 <= n <= MAX_SYNTHETIC:
            raise ConfigError(f"source {uri!r}: the frame count must be >= 1 and <= {MAX_SYNTHETIC}")
        frames = make_frames(n)
        feed = _cycle(frames) if loop else frames
    elif kind == "sim":
        if tof is None:
            raise ConfigError(f"source {uri!r}: emu:sim needs the simulated sensor as option tof=SimToF")
        emu_kw.setdefault("clock", lambda: float(tof.data.time))
        feed = lambda _t: tof.measure()  # noqa: E731 - the simulated sensor at the current sim state
    elif kind in FEEDS or kind == DEFAULT_FEED:
        feed = _feed_factory(uri, kind)(uri, arg)
    else:  # emu:NAME: a name for the default feed (a packaged scenario)
        feed = _feed_factory(uri, DEFAULT_FEED)(uri, inner)
    if tof is not None and kind != "sim":
        raise ConfigError(f"source {uri!r}: option tof is only for emu:sim")
    return EmulatedTMF8820(feed, realtime=realtime, patch=patch, driver=opts, emulator=emulator_kw, **emu_kw)


def _cycle(frames: list):
    while True:
        yield from frames


def register_feed(kind: str, factory: FeedFactory) -> None:
    """Make ``emu:KIND:ARG`` feed the emulator with ``factory(uri, arg)`` (a frame list, an iterator or a
    function of the emulator's time returning a frame). Packages that provide feeds (the simulation: ``scenario``)
    register them here, or name them in the ``place_safe.sources`` entry-point group, which is read on the first
    URI whose kind is not registered. Registering a kind again replaces it."""
    if not (isinstance(kind, str) and kind.isidentifier()) or kind in _BUILT_IN_FEEDS:
        raise ConfigError(f"register_feed: kind must be a name other than {', '.join(_BUILT_IN_FEEDS)}, got {kind!r}")
    if not callable(factory):
        raise ConfigError(f"register_feed: factory for {kind!r} must be callable, got {type(factory).__name__}")
    FEEDS[kind] = factory


def _feed_factory(uri: str, kind: str) -> FeedFactory:
    """The registered factory of ``kind``, loading the entry-point group once if it is not registered yet."""
    if kind not in FEEDS and not _loaded_entry_points:
        _loaded_entry_points.append(FEED_GROUP)
        for ep in entry_points(group=FEED_GROUP):
            if ep.name in FEEDS or ep.name in _BUILT_IN_FEEDS:
                continue
            try:
                FEEDS[ep.name] = ep.load()
            except ImportError as exc:  # an optional extra that is not installed: say so when it is asked for
                _unavailable[ep.name] = f"needs {exc.name or 'a package'} that is not installed ({exc})"
    if kind in FEEDS:
        return FEEDS[kind]
    if kind in _unavailable:
        raise ConfigError(f"source {uri!r}: emu:{kind} {_unavailable[kind]}; for scenarios install the [sim] extra")
    raise ConfigError(f"source {uri!r}: no emulator feed {kind!r}; expected one of "
                      + ", ".join(f"emu:{k}" for k in (*_BUILT_IN_FEEDS, *sorted(FEEDS))))


__all__ = ["open_source", "register_feed", "SCHEMES", "FEEDS", "FEED_GROUP", "DEFAULT_FEED"]
