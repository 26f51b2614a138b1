"""docs/architecture.md's walk of a frame from replay to `map.bt`: the count it states is the count of
the module paths it names, so the figure stays true as the code and the walk change."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
MODULE = re.compile(r"`((?:kit|schemas|recorder|replay|tracker|mapper|shell)/[\w/]+\.py)")
STATED = re.compile(r"The walk above passes (\d+) modules in (\d+) hops, (\d+) of them back into a module already visited")


def walk_count(text: str) -> tuple[int, int, int]:
    """(modules, hops, revisits) of the module paths a walk names in order; a module named again
    right after itself is no hop."""
    path: list[str] = []
    for module in MODULE.findall(text):
        if not path or path[-1] != module:
            path.append(module)
    revisits = sum(module in path[:i] for i, module in enumerate(path) if i)
    return len(set(path)), max(0, len(path) - 1), revisits


def test_walk_count_counts_hops_and_revisits() -> None:
    text = "`kit/a.py` `kit/a.py: X` `mapper/b.py` `kit/a.py` `shell/c.py`"
    assert walk_count(text) == (3, 3, 1)


def test_the_walk_states_its_own_count() -> None:
    doc = (ROOT / "docs" / "architecture.md").read_text()
    start = doc.index("## A frame's way")
    walk = doc[start:doc.index("\n## ", start + 1)]
    stated = STATED.search(doc)
    assert stated, "docs/architecture.md: the sentence stating the walk's count is missing"
    assert tuple(int(g) for g in stated.groups()) == walk_count(walk)
