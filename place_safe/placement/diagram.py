"""The placement machine's diagram, generated from its transition table.

Concept: :func:`mermaid` renders :data:`place_safe.placement.transitions.TRANSITIONS` (with the initial
phase, the final phases and the notes) as a Mermaid ``stateDiagram-v2`` block, the one in
``docs/placement.md``; a test checks that the document holds exactly this block.

Run ``python -m place_safe.placement.diagram`` to print it (paste it over the block in the document
after changing the table).
"""

from __future__ import annotations

from place_safe.placement.transitions import FINAL, INITIAL, NOTES, TRANSITIONS


def mermaid() -> str:
    """The diagram as a fenced Mermaid block (text, ending in a newline)."""
    lines = ["```mermaid", "stateDiagram-v2", f"    [*] --> {INITIAL.name}"]
    lines += [f"    {a.name} --> {b.name}: {label}" for a, b, label in TRANSITIONS]
    lines += [f"    {phase.name} --> [*]" for phase in FINAL]
    lines += [f"    note right of {phase.name}: {text}" for phase, text in NOTES.items()]
    lines.append("```")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(mermaid(), end="")
