"""The folder listing of ``panogs_core`` and the layout table of docs/architecture.md say the same thing.

Every module is placed by a row of the table (its path, or a folder row ending in ``/`` that places everything
under it), and every row names a path that exists: adding, moving or removing a module without its row fails here.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"
ROW = re.compile(r"^\| `([^`]+)` \|")


def layout_rows(text: str) -> list[str]:
    """The paths of the rows between the layout markers of ``text``."""
    try:
        block = text.split("<!-- layout:begin -->", 1)[1].split("<!-- layout:end -->", 1)[0]
    except IndexError:
        raise AssertionError("docs/architecture.md has no <!-- layout:begin --> ... <!-- layout:end -->") from None
    return [m.group(1) for line in block.splitlines() if (m := ROW.match(line))]


def unplaced(modules: list[str], rows: list[str]) -> list[str]:
    """The modules that no row names, neither by path nor under a folder row."""
    folders = tuple(r for r in rows if r.endswith("/"))
    return [m for m in modules if m not in rows and not m.startswith(folders)]


def package_modules(root: Path = ROOT) -> list[str]:
    return sorted(p.relative_to(root).as_posix() for p in (root / "panogs_core").rglob("*.py"))


def test_every_module_of_the_core_is_placed_in_the_docs() -> None:
    rows = layout_rows(DOC.read_text(encoding="utf-8"))
    missing = unplaced(package_modules(), rows)
    assert not missing, f"modules without a row in docs/architecture.md's layout table: {missing}"


def test_every_row_of_the_layout_names_an_existing_path() -> None:
    rows = layout_rows(DOC.read_text(encoding="utf-8"))
    stale = [r for r in rows if not (ROOT / r).exists()]
    assert not stale, f"layout rows naming nothing: {stale}"
    assert len(rows) == len(set(rows)), "a path is placed twice"


@pytest.mark.parametrize(
    ("modules", "rows", "expected"),
    [
        (["panogs_core/a.py", "panogs_core/b/c.py"], ["panogs_core/a.py", "panogs_core/b/"], []),
        (["panogs_core/a.py", "panogs_core/new.py"], ["panogs_core/a.py"], ["panogs_core/new.py"]),
        (["panogs_core/bx/c.py"], ["panogs_core/b/"], ["panogs_core/bx/c.py"]),
    ],
)
def test_the_check_itself(modules: list[str], rows: list[str], expected: list[str]) -> None:
    assert unplaced(modules, rows) == expected


def test_rows_are_read_between_the_markers_only() -> None:
    text = "| `x.py` | out |\n<!-- layout:begin -->\n| path | role |\n|---|---|\n| `a.py` | in |\n<!-- layout:end -->\n"
    assert layout_rows(text) == ["a.py"]
