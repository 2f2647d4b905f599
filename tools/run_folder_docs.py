"""Write the tables of a run's files into README.md and docs/architecture.md from the run folder's declaration.

``panogs_core/io/run_folder.py`` declares every file of a run (``RUN_FILES``). Both tables stand between the
run-folder markers and are generated from it: README.md's "Outputs" (file and content, for users) and
docs/architecture.md's "Outputs of a run" (also the writer, the readers, whether a run may lack it and what the
API serves it as). ``--check`` fails when a table differs from the declaration, or when docs/service.md lists
other downloads than the declaration's.

    .venv/bin/python tools/run_folder_docs.py --write    # make docs-tables
    .venv/bin/python tools/run_folder_docs.py --check
"""

from __future__ import annotations

import difflib
import re
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from generated_docs import write_or_check  # tools/generated_docs.py: the script's own folder is on sys.path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))  # this checkout's declaration, whichever checkout the environment installed


from panogs_core.io.run_folder import DOWNLOADABLE, RUN_FILES, RunFile  # noqa: E402

BEGIN = "<!-- run-folder:begin (written by tools/run_folder_docs.py from panogs_core/io/run_folder.py) -->"
END = "<!-- run-folder:end -->"
SERVICE_DOC = "docs/service.md"
# The row of docs/service.md's endpoint table that names the downloads, and the list in it.
DOWNLOAD_LIST = re.compile(r"^\| GET \| `/v1/jobs/\{id\}/artifacts`.*?download with `Range` \(([^)]*)\)", re.M)


def _module_path(module: str) -> str:
    return f"`{module.replace('.', '/')}.py`"


def _file_cell(f: RunFile) -> str:
    return f"`{f.name}`"


def readme_table(files: Sequence[RunFile] = RUN_FILES) -> list[str]:
    """README.md's table: what a user finds in the ``--out`` folder."""
    rows = ["| file | content |", "|---|---|"]
    rows += [f"| {_file_cell(f)} | {f.content} |" for f in files]
    return rows


def architecture_table(files: Sequence[RunFile] = RUN_FILES) -> list[str]:
    """docs/architecture.md's table: the same files with who writes and reads them, and what the API serves."""
    rows = ["| file | content | written by | read by | optional | download |", "|---|---|---|---|---|---|"]
    for f in files:
        readers = ", ".join(_module_path(m) for m in f.readers) or "-"
        download = f"`{f.media_type}`" if f.downloadable else "-"
        optional = "yes" if f.optional else "no"
        rows.append(
            f"| {_file_cell(f)} | {f.content} | {_module_path(f.writer)} | {readers} | {optional} | {download} |"
        )
    return rows


DOCS: dict[str, Callable[[], list[str]]] = {"README.md": readme_table, "docs/architecture.md": architecture_table}


def block(lines: list[str]) -> str:
    return "\n".join([BEGIN, *lines, END])


def current_block(text: str, where: str) -> str:
    """The text between (and with) the markers; refuses a file without them."""
    start, end = text.find(BEGIN), text.find(END)
    if start < 0 or end < start:
        raise SystemExit(f"{where}: no run-folder markers ({BEGIN} ... {END})")
    return text[start : end + len(END)]


def table_differences(root: Path = REPO) -> list[str]:
    """A unified diff per document whose table is not the declaration's."""
    problems = []
    for name, table in DOCS.items():
        text = (root / name).read_text()
        old, new = current_block(text, name), block(table())
        if old != new:
            diff = difflib.unified_diff(old.splitlines(), new.splitlines(), f"{name} (now)", f"{name} (declared)", n=0)
            problems.append("\n".join(diff))
    return problems


def service_doc_downloads(text: str) -> list[str]:
    """The file names docs/service.md's endpoint table gives for ``/v1/jobs/{id}/artifacts/{name}``."""
    match = DOWNLOAD_LIST.search(text)
    if match is None:
        raise SystemExit(f"{SERVICE_DOC}: no artifacts row listing the downloads (pattern {DOWNLOAD_LIST.pattern})")
    return [name.strip() for name in match.group(1).split(",")]


def service_doc_differences(root: Path = REPO) -> list[str]:
    """docs/service.md's downloads against the declaration's (prose: checked, not written)."""
    listed = set(service_doc_downloads((root / SERVICE_DOC).read_text()))
    if listed == set(DOWNLOADABLE):
        return []
    missing, extra = sorted(set(DOWNLOADABLE) - listed), sorted(listed - set(DOWNLOADABLE))
    return [f"{SERVICE_DOC}: the artifacts row lacks {missing} and lists {extra} that the API does not serve"]


def write(root: Path = REPO) -> list[str]:
    """Rewrite each document's table; returns the names of those that changed."""
    changed = []
    for name, table in DOCS.items():
        path = root / name
        text = path.read_text()
        new = text.replace(current_block(text, name), block(table()))
        if new != text:
            path.write_text(new)
            changed.append(name)
    return changed


def main(argv: list[str] | None = None) -> int:
    return write_or_check(
        argv,
        description=__doc__.splitlines()[0],
        what="the tables between the markers",
        source="the declaration",
        write=write,
        differences=lambda: table_differences() + service_doc_differences(),
        after_write=service_doc_differences,
        hint=f"run tools/run_folder_docs.py --write ({SERVICE_DOC}: edit its artifacts row)",
    )


if __name__ == "__main__":
    raise SystemExit(main())
