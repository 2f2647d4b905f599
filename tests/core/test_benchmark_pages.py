"""docs/benchmarks.md holds today's figures and docs/benchmarks_history.md the dated passes they come from.

The current page copies, never measures: every figure on it is a figure of the history. Each of its sections names
the pass it was copied from, and that pass exists in the history. A citation anywhere in the repository of the form
``docs/benchmarks.md, "Section"`` names a section of the current page or of the history (the current page says
that a section it lacks is a dated pass there), and ``docs/benchmarks_history.md, "Section"`` one of the history; a
quoted name that is not a heading may be a row of a table there (a variant, ``"depth-filter"``).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
CURRENT = REPO / "docs" / "benchmarks.md"
HISTORY = REPO / "docs" / "benchmarks_history.md"
SEARCHED = ("panogs_core", "service", "worker", "bench", "tools", "tests", "docs", "web/src")
SUFFIXES = (".py", ".sh", ".md", ".js")

# A figure: a decimal (0.931, 1,625.5) or a number with thousands separators (78,565).
FIGURE = re.compile(r"(?<![\w.])\d[\d,]*\.\d+|(?<![\w.,])\d{1,3}(?:,\d{3})+(?![\d,])")
# The file, then the quoted section; a comment marker may stand between them where the citation wraps a line.
CITATION = re.compile(r'docs/(benchmarks(?:_history)?\.md)`?,?\s*(?:(?:#|//)\s*)?"([^"]+)"')
SOURCE = re.compile(r'History: "([^"]+)"')


def _headings(text: str) -> list[str]:
    return [re.sub(r"^#+\s*", "", line).strip() for line in text.splitlines() if line.startswith("#")]


def figures_not_in(current: str, history: str) -> list[str]:
    """The figures of ``current`` that ``history`` does not hold (as the same token)."""
    found = sorted(set(FIGURE.findall(current)))
    return [f for f in found if not re.search(rf"(?<![\w.]){re.escape(f)}(?![\d])", history)]


def resolves(name: str, text: str) -> bool:
    """A heading of ``text`` starts with ``name``, or a bold paragraph does, or a table row has it as a cell."""
    name = " ".join(name.split())
    return (
        any(h.startswith(name) for h in _headings(text))
        or re.search(rf"^\*\*{re.escape(name)}", text, re.M) is not None
        or f"| {name} |" in text
    )


def test_every_figure_on_the_current_page_comes_from_the_history() -> None:
    missing = figures_not_in(CURRENT.read_text(encoding="utf-8"), HISTORY.read_text(encoding="utf-8"))
    assert missing == [], f"figures on docs/benchmarks.md that no dated pass holds: {missing}"


def test_the_current_page_links_the_history_and_names_each_sections_pass() -> None:
    current, history = CURRENT.read_text(encoding="utf-8"), HISTORY.read_text(encoding="utf-8")
    assert "(benchmarks_history.md)" in current
    sections = current.split("\n## ")[1:]
    assert len(sections) >= 10
    for section in sections:
        names = SOURCE.findall(" ".join(section.split()))
        assert names, f"docs/benchmarks.md, {section.splitlines()[0]!r}: no 'History: \"...\"' naming its pass"
        for name in names:
            assert resolves(name, history), f"docs/benchmarks.md, {section.splitlines()[0]!r}: no pass {name!r}"


def _citations() -> list[tuple[str, str, str]]:
    found = []
    for root in SEARCHED:
        for path in sorted((REPO / root).rglob("*")):
            if path.suffix in SUFFIXES and path.is_file() and path != Path(__file__).resolve():
                text = path.read_text(encoding="utf-8", errors="replace")
                found += [(str(path.relative_to(REPO)), m.group(1), m.group(2)) for m in CITATION.finditer(text)]
    return found


def test_every_named_citation_of_the_benchmark_pages_resolves() -> None:
    current, history = CURRENT.read_text(encoding="utf-8"), HISTORY.read_text(encoding="utf-8")
    citations = _citations()
    assert len(citations) > 20  # the check would pass trivially if the pattern found none
    broken = [
        f"{where}: docs/{doc}, {name!r}"
        for where, doc, name in citations
        if not (resolves(name, history) or (doc == "benchmarks.md" and resolves(name, current)))
    ]
    assert broken == [], "sections cited that neither page has:\n" + "\n".join(broken)


@pytest.mark.parametrize(
    ("current", "history", "missing"),
    [
        ("mIoU 0.931, 78,565 primitives", "| 0.931 | 78,565 |", []),
        ("mIoU 0.931", "mIoU 0.9312", ["0.931"]),
        ("peak 1,210 MB", "peak 1210 MB", ["1,210"]),
        ("run 2026-12-04, seeds 0 1 2", "nothing", []),
    ],
)
def test_the_figure_check_itself(current: str, history: str, missing: list[str]) -> None:
    assert figures_not_in(current, history) == missing


def test_the_citation_pattern_reads_a_wrapped_comment() -> None:
    text = '# the field (docs/benchmarks.md,\n    # "Speed at ScanNet size, third pass").'
    assert CITATION.findall(text) == [("benchmarks.md", "Speed at ScanNet size, third pass")]
    assert resolves("Speed at ScanNet size, third pass", "## Speed at ScanNet size, third pass: `cmd`\n")
    assert not resolves("Speed at ScanNet size, fifth pass", "## Speed at ScanNet size, third pass: `cmd`\n")
