"""Every citation in the code points at a file in ``docs/`` and, when it names one, at a section or pitfall that exists.

The one citation form: ``docs/<file>.md``, optionally followed by sections or pitfalls of that file, e.g.
``docs/method.md §4.5``, ``docs/method.md §5.1-5.4``, ``docs/method.md §3.1 and pitfall 8``,
``docs/scene_format.md §2.3``. A section exists when the file has a heading numbered so (``## 4.`` or ``### 4.5``); a
pitfall exists when the numbered list under the file's "Pitfalls" heading has that item. Documents outside the
repository (the design notes the project started from) may not be cited at all, nor the reference's section numbers
in the old form that did not say where to look.
"""

from __future__ import annotations

import re
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
CODE_DIRS = ("panogs_core", "service", "worker", "bench", "tools", "tests")
CODE_SUFFIXES = (".py", ".sh")

_REF = r"(?:§\d+(?:\.\d+)*(?:-\d+(?:\.\d+)*)?|pitfall \d+)"
CITATION = re.compile(rf"docs/(?P<file>[a-z_]+\.md)(?P<refs>(?: {_REF})(?:(?:, | and ){_REF})*)?")
SECTION_HEADING = re.compile(r"^#+ (\d+(?:\.\d+)*)[. ]", re.MULTILINE)
# An upper-case document name (the way design notes are named) that is not a file of the repository's root.
UPPER_CASE_DOCUMENT = re.compile(r"(?<![\w/.])[A-Z][A-Z0-9_]*\.md\b")
OLD_FORM = re.compile(r"\b(?:[Rr]eference (?:sections? |§)?\d|pitfalls? \d|[Rr]ef\. \d)")


def _code_files() -> list[Path]:
    return sorted(path for root in CODE_DIRS for path in (REPO / root).rglob("*") if path.suffix in CODE_SUFFIXES)


@cache
def _anchors(doc: str) -> tuple[frozenset[str], frozenset[int]]:
    """Section numbers and pitfall numbers of ``docs/<doc>``."""
    text = (REPO / "docs" / doc).read_text(encoding="utf-8")
    sections = frozenset(SECTION_HEADING.findall(text))
    pitfalls: set[int] = set()
    match = re.search(r"^#+ [\d.]* ?Pitfalls\b.*?$(?P<body>.*?)(?=^#+ |\Z)", text, re.MULTILINE | re.DOTALL)
    if match:
        pitfalls = {int(n) for n in re.findall(r"^(\d+)\. ", match.group("body"), re.MULTILINE)}
    return sections, frozenset(pitfalls)


def broken_citations(text: str, where: str) -> list[str]:
    """What is wrong with the citations in ``text`` (``where`` names it in the messages)."""
    problems = []
    for match in CITATION.finditer(text):
        doc = match.group("file")
        if not (REPO / "docs" / doc).is_file():
            problems.append(f"{where}: docs/{doc} does not exist")
            continue
        sections, pitfalls = _anchors(doc)
        for ref in re.findall(_REF, match.group("refs") or ""):
            if ref.startswith("pitfall"):
                if int(ref.split()[1]) not in pitfalls:
                    problems.append(f"{where}: docs/{doc} has no {ref}")
                continue
            for section in ref[1:].split("-"):
                if section not in sections:
                    problems.append(f"{where}: docs/{doc} has no section {section} (cited as {ref})")
    for match in UPPER_CASE_DOCUMENT.finditer(text):
        if (REPO / match.group(0)).is_file():
            continue
        problems.append(f"{where}: cites {match.group(0)}, a document outside the repository; cite docs/ instead")
    for match in OLD_FORM.finditer(CITATION.sub("", text)):  # pitfalls inside a citation are fine
        problems.append(f"{where}: {match.group(0)!r} does not say where to look; cite docs/method.md instead")
    return problems


def test_every_citation_in_the_code_resolves() -> None:
    problems = []
    for path in _code_files():
        if path == Path(__file__).resolve():
            continue
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1):
            problems += broken_citations(line, f"{path.relative_to(REPO)}:{number}")
    assert not problems, "\n".join(problems)


def test_the_code_cites_the_method_many_times() -> None:
    # The test above passes trivially if nothing is recognised as a citation: the code cites the method a lot.
    count = sum(len(CITATION.findall(path.read_text(encoding="utf-8"))) for path in _code_files())
    assert count > 100


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("see docs/method.md §4.5", None),
        ("see docs/method.md §3.1 and pitfall 8", None),
        ("see docs/method.md §5.1-5.4", None),
        ("see docs/scene_format.md §2.3", None),
        ("see docs/architecture.md", None),
        ("see docs/method.md §4.9", "has no section 4.9"),
        ("see docs/method.md §5.1-5.9", "has no section 5.9"),
        ("see docs/method.md pitfall 99", "has no pitfall 99"),
        ("see docs/method.md §4.5, pitfall 99", "has no pitfall 99"),
        ("see docs/nowhere.md", "docs/nowhere.md does not exist"),
        ("see NOTES_FROM_ELSEWHERE.md", "a document outside the repository"),
        ("see README.md", None),
        ("as the reference 4.5 says", "does not say where to look"),
        ("(pitfall 12)", "does not say where to look"),
    ],
)
def test_the_checker_finds_what_is_broken(text: str, problem: str | None) -> None:
    found = broken_citations(text, "here")
    if problem is None:
        assert found == []
    else:
        assert len(found) == 1, found
        assert problem in found[0]


def test_method_has_the_numbered_pitfalls_and_sections_the_code_relies_on() -> None:
    sections, pitfalls = _anchors("method.md")
    assert pitfalls == frozenset(range(1, 26))
    assert {"2", "3.1", "4.5", "5.4", "6.2", "7.3", "8.2", "13"} <= sections
