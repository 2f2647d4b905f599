"""The run folder's declaration and the documents generated from it: README.md's and docs/architecture.md's
tables are the declaration's (tools/run_folder_docs.py), docs/service.md names the files the API serves, and every
module the declaration names exists."""

from __future__ import annotations

import shutil
from pathlib import Path

from tool_modules import load_tool

from panogs_core.io.run_folder import DOWNLOADABLE, RUN_FILES

REPO = Path(__file__).resolve().parents[2]

tool = load_tool("run_folder_docs")


def test_the_tables_are_the_declarations() -> None:
    problems = tool.table_differences()
    assert problems == [], "\n".join(problems) + "\nrun tools/run_folder_docs.py --write (make docs-tables)"


def test_the_service_doc_names_the_files_the_api_serves() -> None:
    assert tool.service_doc_differences() == []


def test_a_table_edited_by_hand_is_found_and_written_back(tmp_path: Path) -> None:
    for name in (*tool.DOCS, tool.SERVICE_DOC):
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(REPO / name, tmp_path / name)
    readme = tmp_path / "README.md"
    readme.write_text(readme.read_text().replace("| `cameras.json` |", "| `camera.json` |"))
    problems = tool.table_differences(tmp_path)
    assert len(problems) == 1
    assert "-| `camera.json` |" in problems[0]
    assert "+| `cameras.json` |" in problems[0]
    assert tool.write(tmp_path) == ["README.md"]
    assert tool.table_differences(tmp_path) == []


def test_a_download_missing_from_the_service_doc_is_named(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    text = (REPO / tool.SERVICE_DOC).read_text()
    (tmp_path / tool.SERVICE_DOC).write_text(text.replace(", cameras.json)", ")"))
    assert tool.service_doc_differences(tmp_path) == [
        f"{tool.SERVICE_DOC}: the artifacts row lacks ['cameras.json'] and lists [] that the API does not serve"
    ]


def _module_file(module: str) -> Path:
    path = REPO / module.replace(".", "/")
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def test_the_declaration_is_well_formed() -> None:
    names = [f.name for f in RUN_FILES]
    assert len(set(names)) == len(names)
    for spec in RUN_FILES:
        for module in (spec.writer, *spec.readers):
            assert _module_file(module).is_file(), f"{spec.name}: no module {module}"
        assert "|" not in spec.content, f"{spec.name}: its content must fit one table cell"
        if spec.is_folder:
            assert not spec.downloadable, f"{spec.name}: the API serves files, not folders"
    assert {f.media_type for f in DOWNLOADABLE.values()} <= {"application/json", "application/octet-stream"}
