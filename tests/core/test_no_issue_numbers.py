"""No text of the repository cites a numbered issue, pull request or ticket.

The tracker those numbers pointed at is not in the repository, so "issue 8" or "(#12)" tells a reader nothing and
stays behind when the work it named has moved on. Say what the work was instead ("the hostile-input hardening",
"the labelling rules of docs/method.md §7.5"), or leave it out. ``tests/core/test_doc_citations.py`` does the same
for documents outside the repository.

Refused: ``issue 8``, ``issues 7-10``, ``issue #3``, ``issue-8``, ``issue_8``, ``Issue8`` (a name such as
``TestIssue8Rules``), ``(#12)``, ``PR #12``, ``fixes #12``, ``see #12``, ``GH-12``, ``ticket 12``. Allowed: the
word itself ("known issues", "the issue is"), CSS colours (``#101418``), and a link to another project's
tracker (``https://github.com/owner/name/issues/123``): that is a source a reader can open, cited like a paper.
A bare "upstream issue #123" is refused; cite its link.

Every file git tracks is read, and the files not yet added that git does not ignore, whatever their kind (code,
docs, tests, Makefile, Dockerfile, CI scripts, the web app); binary files are skipped.
"""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]

# "issue" in lower case must not follow a letter (so "tissue 3" is not one); "Issue" may, which finds camel-case
# names. The separator before the number: none, spaces (a line break included), "#", "-" or "_".
_SEPARATOR = r"(?:\s*\#\s*|\s+|[_-])?"
ISSUE_NUMBER = re.compile(
    rf"(?:(?<![A-Za-z])(?:issues?|ISSUES?)|Issues?){_SEPARATOR}\d+"
    r"|\(\#\d+\)"
    r"|(?<![A-Za-z])(?i:PR|pull\s+request|fix(?:es|ed)?|close[sd]?|resolve[sd]?|see|GH)\s*\#\d+"
    r"|(?<![A-Za-z])GH-\d+"
    rf"|(?<![A-Za-z])(?i:tickets?){_SEPARATOR}\d+"
)

# Files allowed to hold mentions, with how many: none. Kept so that a file can be let through while its rewrite is
# under way (test_the_allow_list_is_not_stale says when an entry has become too generous).
ALLOWED: dict[str, int] = {}

# Used only where git is not available (a source archive): the folders a checkout ignores.
_SKIPPED_DIRS = {".git", ".venv", "node_modules", "__pycache__", ".pytest_cache", ".ruff_cache", ".mypy_cache"}


def _repository_files() -> list[Path]:
    """What git tracks, plus the files not added yet that it does not ignore."""
    try:
        listed = subprocess.run(
            ["git", "-C", str(REPO), "ls-files", "-z", "--cached", "--others", "--exclude-standard"],
            capture_output=True,
            check=True,
        ).stdout.decode("utf-8")
    except (OSError, subprocess.CalledProcessError):
        found = []
        for root, dirs, files in os.walk(REPO):
            dirs[:] = [d for d in dirs if d not in _SKIPPED_DIRS and Path(root, d) != REPO / "service" / "static"]
            found += [Path(root, name) for name in files]
        return sorted(found)
    return sorted(REPO / name for name in listed.split("\0") if name)


def _text(path: Path) -> str | None:
    """The file's text, or None for a binary file (or one a listing named that is gone)."""
    try:
        data = path.read_bytes()
    except (FileNotFoundError, IsADirectoryError):
        return None
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def issue_mentions(text: str) -> list[tuple[int, str]]:
    """``(line, what)`` for every mention of a numbered issue in ``text``."""
    return [(text.count("\n", 0, m.start()) + 1, m.group(0)) for m in ISSUE_NUMBER.finditer(text)]


def _mentions_by_file() -> dict[str, list[tuple[int, str]]]:
    found = {}
    for path in _repository_files():
        if path == Path(__file__).resolve():
            continue
        text = _text(path)
        if text is not None and (mentions := issue_mentions(text)):
            found[path.relative_to(REPO).as_posix()] = mentions
    return found


def test_no_text_mentions_a_numbered_issue() -> None:
    problems = []
    for name, mentions in _mentions_by_file().items():
        if len(mentions) <= ALLOWED.get(name, 0):
            continue
        problems += [
            f"{name}:{line}: {what!r} cites a numbered issue; say what the work was" for line, what in mentions
        ]
    assert not problems, "\n".join(problems)


def test_the_allow_list_is_not_stale() -> None:
    found = _mentions_by_file()
    stale = {name: len(found.get(name, [])) for name, count in ALLOWED.items() if len(found.get(name, [])) < count}
    assert not stale, f"lower or remove these entries of ALLOWED (mentions left): {stale}"


def test_the_repository_is_read() -> None:
    # The tests above pass trivially if no file is read: the listing holds the code, the docs and this file.
    names = {path.relative_to(REPO).as_posix() for path in _repository_files()}
    assert {"Makefile", "docs/method.md", "panogs_core/pipeline/run.py", "tests/core/test_no_issue_numbers.py"} <= names


@pytest.mark.parametrize(
    ("text", "found"),
    [
        ("the labelling rules of issue 8", "issue 8"),
        ("(issue 14 item 10)", "issue 14"),
        ("before issues 7-10", "issues 7"),
        ("the targets of issue #3", "issue #3"),
        ("the issue-8 rules", "issue-8"),
        ("def test_issue_8() -> None:", "issue_8"),
        ("class TestIssue8Rules:", "Issue8"),
        ("Issue 8 measured them", "Issue 8"),
        ("the labelling of issue\n8", "issue\n8"),
        ("speed work (#12)", "(#12)"),
        ("merged in PR #12", "PR #12"),
        ("this fixes #12", "fixes #12"),
        ("GH-12", "GH-12"),
        ("ticket 12", "ticket 12"),
        ("upstream issue #1234", "issue #1234"),
        ("known issues of the reference", None),
        ("the issue is that 2 frames", None),
        ("tissue 3", None),
        ("color: #101418; border: 1px solid #0006", None),
        ("https://github.com/pytorch/pytorch/issues/1234", None),
        ("https://github.com/nerfstudio-project/gsplat/pull/123", None),
        ("docs/method.md pitfall 12, §4.5", None),
    ],
)
def test_the_pattern(text: str, found: str | None) -> None:
    mentions = issue_mentions(text)
    if found is None:
        assert mentions == []
    else:
        assert [what for _, what in mentions] == [found]
