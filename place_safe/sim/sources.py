"""The simulation's frame sources for :func:`place_safe.sources.open_source`: ``emu:scenario:NAME`` (and
``emu:NAME``), the register-level emulator fed by the simulated sensor over a packaged scenario's scene.

The library does not import the simulation: this factory reaches ``sources`` through the ``place_safe.sources``
entry-point group (pyproject.toml), read on the first URI that names it (the package must be installed, as the
README's install does, for the group to exist).
"""
from __future__ import annotations

from collections.abc import Callable

from place_safe.exceptions import ConfigError
from place_safe.sensor.frame import Frame
from place_safe.sim.scenario import load_scenario
from place_safe.sim.scene import build_scene
from place_safe.sim.tof_mismatch import make_sensor


def scenario_feed(uri: str, name: str) -> Callable[[float], Frame]:
    """The simulated sensor rig (no robot) over scenario ``name``'s scene, as the emulator's feed (a frame
    per call, at the emulator's time)."""
    if not name:
        raise ConfigError(f"source {uri!r}: expected emu:scenario:NAME (a packaged scenario or a scenario file)")
    try:
        sc = load_scenario(name)
    except (FileNotFoundError, ValueError) as exc:
        raise ConfigError(f"source {uri!r}: {str(exc).splitlines()[0]}") from None
    scene_cfg = sc.scene_config()
    scene_cfg.with_robot = False  # the sensor rig alone over the scenario's scene
    tof = make_sensor(sc.sensor.model, build_scene(scene_cfg), None, sc.sensor.tof_config(0), sc.sensor.mismatch)
    return lambda _t: tof.measure()


__all__ = ["scenario_feed"]
