"""``benchmarks/RESULTS.md`` records each result once: the docs site links to it rather than
including it, and every link into it from the README and the docs finds its heading."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "benchmarks" / "RESULTS.md"


def _anchor(heading: str) -> str:  # GitHub's (and myst_heading_anchors') slug of a heading
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def test_docs_do_not_include_results():
    text = (ROOT / "docs" / "results.md").read_text()
    assert "{include}" not in text and "benchmarks/RESULTS.md" in text


def test_links_into_results_find_their_heading():
    text = RESULTS.read_text()
    anchors = {_anchor(line.lstrip("#")) for line in text.splitlines() if line.startswith("#")}
    sources = {RESULTS: text, ROOT / "README.md": (ROOT / "README.md").read_text()}
    sources.update({p: p.read_text() for p in (ROOT / "docs").rglob("*.md") if "_build" not in p.parts})
    broken = [
        (path.name, anchor)
        for path, body in sources.items()
        for target, anchor in re.findall(r"\]\(([^)#\s]*)#([^)\s]+)\)", body)
        if (target.endswith("RESULTS.md") or (path == RESULTS and not target)) and anchor not in anchors
    ]
    assert not broken, f"links to headings RESULTS.md does not have: {broken}"
