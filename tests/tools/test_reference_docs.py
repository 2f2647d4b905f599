"""The settings reference (docs/settings.md) and the module lists of docs/architecture.md are the code's:
tools/reference_docs.py writes them, and these tests fail when either has drifted from it."""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

import pytest
from tool_modules import load_tool

from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]

tool = load_tool("reference_docs")


def _copy_docs(root: Path) -> None:
    for block in tool.blocks():
        (root / block.doc).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / block.doc, root / block.doc)


def test_the_generated_docs_are_the_codes() -> None:
    problems = tool.differences()
    assert problems == [], "\n".join(problems) + "\nrun tools/reference_docs.py --write (make docs-tables)"


def test_every_setting_has_a_row_with_its_variable_default_and_bounds() -> None:
    text = (REPO / tool.SETTINGS_DOC).read_text(encoding="utf-8")
    rows = {line.split(" | ")[0].strip("| `"): line for line in text.splitlines() if line.startswith("| `PANOGS_")}
    assert set(rows) == {f"PANOGS_{name.upper()}" for name in Settings.model_fields}
    for name, info in Settings.model_fields.items():
        cells = rows[f"PANOGS_{name.upper()}"].split(" | ")
        default = "none" if info.default is None else str(info.default).lower()
        assert default.strip('"') in cells[2].lower(), (name, cells[2])
        for bound in info.metadata:
            for kind, sign in tool.BOUNDS:
                if isinstance(bound, kind):
                    assert f"{sign} {getattr(bound, kind.__name__.lower())}" in cells[3], (name, cells[3])
    assert "| `17179869184` (`16 * GIB`) | > 0 |" in rows["PANOGS_MAX_UPLOAD_BYTES"]


def test_a_comment_above_a_field_describes_it_and_one_after_a_blank_line_heads_a_group() -> None:
    source = (
        "class S:\n"
        "    a: int = 1  # the first\n"
        "    # spread over\n"
        "    # two lines\n"
        "    b: str = 'x'\n"
        "\n"
        "    # Limits.\n"
        "    c: int | None = Field(default=None, gt=0)\n"
    )
    fields = tool.field_sources(ast.parse(source).body[0], source)
    assert fields["a"] == tool.FieldSource("int", "1", "the first", tool.FIRST_GROUP)
    assert fields["b"] == tool.FieldSource("str", "'x'", "spread over two lines", tool.FIRST_GROUP)
    assert fields["c"] == tool.FieldSource("int | None", "None", "", "Limits")


def test_a_module_list_edited_by_hand_is_found_and_written_back(tmp_path: Path) -> None:
    _copy_docs(tmp_path)
    for package in tool.PACKAGES:
        shutil.copytree(REPO / package, tmp_path / package, ignore=shutil.ignore_patterns("__pycache__", "static"))
    doc = tmp_path / tool.MODULES_DOC
    # worker/__init__.py: a module every restructuring keeps
    doc.write_text(doc.read_text(encoding="utf-8").replace("| `worker/__init__.py` |", "| `worker/init.py` |"))
    (tmp_path / "worker" / "added.py").write_text('"""A module added after the list was written. More."""\n')
    (tmp_path / "worker" / "bare.py").write_text("X = 1\n")
    problems = tool.differences(tmp_path)
    assert problems[0] == "worker/bare.py: no module docstring (its row needs one)"
    assert len(problems) == 2
    assert "-| `worker/init.py` |" in problems[1]
    assert "+| `worker/__init__.py` |" in problems[1]
    assert "+| `worker/added.py` | A module added after the list was written. |" in problems[1]
    assert tool.write(tmp_path) == [tool.MODULES_DOC]
    assert tool.differences(tmp_path) == ["worker/bare.py: no module docstring (its row needs one)"]


def test_the_summary_is_the_first_sentence_on_one_line() -> None:
    assert (
        tool.summary("Run one job: claim it,\nrecord it. Then more.\n\nDetails.") == "Run one job: claim it, record it."
    )
    assert tool.summary("Uploads (tus 1.0; see ``service.uploads``)\nresumable") == (
        "Uploads (tus 1.0; see ``service.uploads``) resumable"
    )


def test_a_cell_keeps_markdown_tables_and_tags_apart() -> None:
    assert tool._cell("``str | None`` under <data_dir>, see :mod:`service.x`") == (
        "`str \\| None` under \\<data_dir>, see `service.x`"
    )


def test_a_document_without_markers_is_refused(tmp_path: Path) -> None:
    _copy_docs(tmp_path)
    (tmp_path / tool.SETTINGS_DOC).write_text("# Settings\n")
    with pytest.raises(SystemExit, match=r"docs/settings\.md: no markers"):
        tool.differences(tmp_path)
