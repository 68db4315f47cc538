"""The project's documents link correctly: every relative link of README.md and docs/*.md names a
file that exists, and every ``#anchor`` a heading of the file it points into.

Anchors are GitHub's: the heading text lower-cased, every character that is not a letter, digit,
space, hyphen or underscore dropped, spaces made hyphens. Headings and links inside fenced code
blocks do not count (a ``# comment`` in a shell block is not a heading).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCUMENTS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_LINK = re.compile(r"\]\(([^)\s]+)\)")


def _prose_lines(path: Path) -> list[str]:
    """The lines of ``path`` outside fenced code blocks."""
    lines, fenced = [], False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor of a heading's text."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of every heading of ``path``."""
    return {slug(line.lstrip("#")) for line in _prose_lines(path) if re.match(r"#{1,6} ", line)}


def links(path: Path) -> list[str]:
    """Every link target written in ``path``'s prose."""
    return [target for line in _prose_lines(path) for target in _LINK.findall(line)]


def test_slugs_are_githubs() -> None:
    assert slug("Latency: skeleton published → command published") == "latency-skeleton-published--command-published"
    assert slug("The safety layer (paper §III, architecture §4)") == "the-safety-layer-paper-iii-architecture-4"
    assert slug("One machine: `make demo`") == "one-machine-make-demo"


@pytest.mark.parametrize("document", DOCUMENTS, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_and_anchor_resolves(document: Path) -> None:
    broken = []
    for target in links(document):
        if re.match(r"[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: …
            continue
        path, _, anchor = target.partition("#")
        linked = (document.parent / path).resolve() if path else document
        if not linked.exists():
            broken.append(f"{target}: no such file")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(f"{target}: no such heading")
    assert not broken, broken


def test_the_documents_link_to_each_other() -> None:
    """The README names the documents beside it, and the measurements file is reachable from it."""
    targets = {target.partition("#")[0] for target in links(ROOT / "README.md")}
    assert {"docs/architecture.md", "docs/benchmarks.md", "docs/safety-measurements.md"} <= targets
