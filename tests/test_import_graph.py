"""The import graph of place_safe, read from the source (every ``.py`` under ``place_safe/`` parsed with ``ast``).

Layers
------
library
    ``sensor``, ``io``, ``recovery``, ``calibration``, ``fusion``, ``placement``, ``robot``, ``evaluation`` and
    the top-level modules ``geometry``, ``exceptions``, ``config``, ``assets`` and ``sources``: what a task
    script and the other layers build on. They never import the simulation or the command line.
edges
    ``drivers`` (the TMF8820 and the UR5: hardware, emulators and stand-ins) and ``sim`` (MuJoCo). Drivers import
    the library only; the simulation imports the library and the drivers (and the command line's argument
    helpers, for its own sub-commands).
application
    ``cli`` and ``__main__``: the ``place-safe`` command, which may import everything.
facade
    ``place_safe`` itself (``__init__.py``): the public names, each loaded on first use; no module of the
    package imports it.

The simulation's frame sources reach the library's ``open_source`` through the ``place_safe.sources``
entry-point group (pyproject.toml), a registration at run time, not an import.

What counts as an import: ``import`` and ``from ... import`` statements anywhere in a module -- at the top, in
functions, under ``if`` or ``try`` -- and ``importlib.import_module`` / ``__import__`` calls (with a literal
name, or, for a computed one, every string in the module that names a place_safe module). ``from pkg import
name`` is an edge to ``pkg.name`` when that is a module, else to ``pkg``. The package ``__init__`` a dotted
import runs first is not counted as an edge (a package that re-exports its submodules is not a cycle).

The test fails on any cycle (two or more modules that reach each other), on a library module that imports the
simulation, the command line or the facade, and on a driver that imports the simulation or the command line.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

pytestmark = pytest.mark.fast

ROOT = Path(__file__).resolve().parents[1] / "place_safe"
LIBRARY = ("sensor", "io", "recovery", "calibration", "fusion", "placement", "robot", "evaluation",
           "geometry", "exceptions", "config", "assets", "sources")
EDGES = ("drivers", "sim")
APPLICATION = ("cli", "__main__")


def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = list(path.relative_to(ROOT.parent).with_suffix("").parts)
        package = parts[-1] == "__init__"
        if package:
            parts = parts[:-1]
        out[".".join(parts)] = (path, package)
    return out


MODULES = _modules()


def _owner(name: str) -> str | None:
    """The module ``name`` refers to: itself, or the nearest package or module above it."""
    while name and name not in MODULES:
        name = name.rpartition(".")[0]
    return name or None


def _absolute(module: str, package: bool, node: ast.ImportFrom) -> str:
    if not node.level:
        return node.module or ""
    base = module.split(".") if package else module.split(".")[:-1]
    base = base[:len(base) - node.level + 1]
    return ".".join(base + ([node.module] if node.module else []))


def _targets(module: str, path: Path, package: bool) -> set[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    names: set[str] = set()
    dynamic = False
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names.update(a.name for a in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = _absolute(module, package, node)
            for a in node.names:
                sub = f"{base}.{a.name}"
                names.add(sub if sub in MODULES else base)
        elif isinstance(node, ast.Call):
            fn = node.func
            fname = fn.attr if isinstance(fn, ast.Attribute) else getattr(fn, "id", "")
            if fname in ("import_module", "__import__"):
                arg = node.args[0] if node.args else None
                if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                    names.add(arg.value)
                else:
                    dynamic = True
    if dynamic:  # a computed name: any place_safe module the module spells out may be the one
        names.update(n.value for n in ast.walk(tree)
                     if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in MODULES)
    owners = {_owner(n) for n in names if n == "place_safe" or n.startswith("place_safe.")}
    owners.discard(None)
    owners.discard(module)
    return owners  # type: ignore[return-value]


GRAPH: dict[str, set[str]] = {m: _targets(m, p, pkg) for m, (p, pkg) in MODULES.items()}


def _layer(module: str) -> str:
    if module == "place_safe":
        return "facade"
    top = module.split(".")[1]
    if top in LIBRARY:
        return "library"
    if top in EDGES:
        return top
    if top in APPLICATION:
        return "application"
    raise AssertionError(f"{module}: in no layer; add its folder to this test's docstring and tuples")


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph.get(w, ())))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def _path(graph: dict[str, set[str]], start: str, goal: str, within: set[str]) -> list[str]:
    """A shortest import chain from ``start`` to ``goal`` inside ``within`` (for the failure message)."""
    prev: dict[str, str | None] = {start: None}
    todo = [start]
    while todo:
        nxt = []
        for v in todo:
            for w in sorted(graph[v] & within):
                if w not in prev:
                    prev[w] = v
                    nxt.append(w)
        todo = nxt
    chain, v = [], goal
    while v is not None:
        chain.append(v)
        v = prev.get(v)
    return chain[::-1]


def test_the_graph_is_read():
    """The parser sees the imports it must see (a guard against a test that passes because it reads nothing)."""
    assert len(MODULES) > 80
    assert "place_safe.placement.machine" in GRAPH["place_safe.placement.loop"]
    assert "place_safe.sensor.frame" in GRAPH["place_safe.io.frame_file"]
    assert "place_safe.cli.sensing" in GRAPH["place_safe.cli.app"]  # through importlib.import_module
    assert "place_safe.sim.cli" in GRAPH["place_safe.cli.app"]  # an import inside a function
    for m in MODULES:
        _layer(m)


def test_no_import_cycles():
    problems = []
    for comp in _cycles(GRAPH):
        within = set(comp)
        a = comp[0]
        b = next(iter(sorted(GRAPH[a] & within)))
        chain = _path(GRAPH, b, a, within)
        problems.append(f"{len(comp)} modules import each other, e.g. {' -> '.join([a, *chain])}: {', '.join(comp)}")
    assert not problems, "\n".join(problems)


def test_layers():
    forbidden = {"library": ("sim", "application", "facade"), "drivers": ("sim", "application", "facade"),
                 "sim": ("facade",)}
    problems = [f"{m} ({_layer(m)}) imports {t} ({_layer(t)})"
                for m, targets in sorted(GRAPH.items()) for t in sorted(targets)
                if _layer(t) in forbidden.get(_layer(m), ())]
    assert not problems, "\n".join(problems)


def test_the_checks_catch_a_cycle_and_a_layer_breach():
    """The checks on a made-up graph: a three-module cycle is found, a chain is not."""
    graph = defaultdict(set, {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}})
    assert _cycles(dict(graph)) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": set()}) == []
    assert _layer("place_safe.sources") == "library" and _layer("place_safe.sim.world") == "sim"
