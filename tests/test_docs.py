"""Documentation the code points at exists, and the documents' own links resolve.

Every path under ``docs/`` (a Markdown document or a figure) named in the library, the simulation, the
robot and scenario folders, the examples, the tests and the README must be a file of the repository; every
relative link in the READMEs and ``docs/*.md`` must lead to a file, and every ``#anchor`` to a heading of it.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("place_safe", "sim", "robots", "scenarios", "examples", "tests")
TEXT = {".py", ".md", ".toml", ".json", ".txt", ".cfg"}
#: A repository doc path (under ``docs/``, a Markdown file or a figure), not preceded by another path component.
DOC_PATH = re.compile(r"(?<![\w/.-])docs/[\w./-]*\w\.(?:md|png)")
LINK = re.compile(r"\]\(([^)\s]+)\)")


def _files():
    yield ROOT / "README.md"
    for folder in SCANNED:
        for path in sorted((ROOT / folder).rglob("*")):
            if path.suffix in TEXT and path.is_file() and "__pycache__" not in path.parts:
                yield path


def _named_doc_paths() -> dict[str, list[str]]:
    named: dict[str, list[str]] = {}
    for path in _files():
        for n, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            for m in DOC_PATH.finditer(line):
                named.setdefault(m.group(0), []).append(f"{path.relative_to(ROOT)}:{n}")
    return named


def test_the_scan_finds_the_references_it_is_meant_to_find():
    named = _named_doc_paths()
    for doc in ("docs/interfaces.md", "docs/tmf8820.md", "docs/tmf8820-protocol.md", "docs/placement.md",
                "docs/results.md"):
        assert doc in named, f"nothing names {doc}: is the scan still looking in the right places?"


def test_every_doc_path_the_code_names_exists():
    missing = {doc: where for doc, where in _named_doc_paths().items() if not (ROOT / doc).is_file()}
    assert not missing, "doc paths named but not in the repository: " + "; ".join(
        f"{doc} (named in {', '.join(where[:3])})" for doc, where in sorted(missing.items()))


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    return {_slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, flags=re.M)}


DOCUMENTS = ["README.md", "scenarios/README.md", "robots/ur5/README.md"] + sorted(
    str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md"))


@pytest.mark.parametrize("doc", DOCUMENTS)
def test_links_in_the_documents_resolve(doc):
    path = ROOT / doc
    text = re.sub(r"```.*?```", "", path.read_text(encoding="utf-8"), flags=re.S)
    broken = []
    for target in LINK.findall(text):
        if re.match(r"[a-z]+:", target):  # http:, https:, mailto:
            continue
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        if not linked.exists():
            broken.append(f"{target} (no such file)")
        elif anchor and linked.suffix == ".md" and anchor not in _anchors(linked):
            broken.append(f"{target} (no such heading)")
    assert not broken, f"{doc}: " + "; ".join(broken)


def test_the_footprint_vetos_reaction_distance_uses_the_stop_the_arm_gives():
    """docs/placement.md's reaction distance to a footprint veto at the cruise: the machine asks for
    ``obstacle_decel``, but a stop asked harder than ``max_linear_accel`` brakes at most at the robot file's
    ``motion.emergency_decel`` (the ur_rtde driver and, since 25a, the simulated arm); the figure must use that."""
    from place_safe.drivers.ur5.config import MotionConfig
    from place_safe.placement.config import PlacementConfig
    from place_safe.robot.interface import RobotLimits

    cfg, lim = PlacementConfig(), RobotLimits()
    asked = max(cfg.accel, cfg.obstacle_decel)
    decel = asked if asked <= lim.max_linear_accel else min(asked, MotionConfig().emergency_decel)
    v = cfg.approach_speed
    react, brake = round(cfg.sensor_latency * v * 1e3), round(v * v / (2 * decel) * 1e3)
    text = " ".join((ROOT / "docs" / "placement.md").read_text(encoding="utf-8").split())
    assert f"at the {v:g} m/s cruise {react} + {brake} = {react + brake} mm" in text
