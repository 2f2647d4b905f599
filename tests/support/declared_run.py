"""A run folder holding a placeholder for every file the declaration lists (``panogs_core.io.run_folder``)."""

from __future__ import annotations

from pathlib import Path

from panogs_core.io.run_folder import RUN_FILES


def write_declared_files(out: Path) -> None:
    """Each declared file with its own name as content; each declared folder with one file in it."""
    out.mkdir(parents=True, exist_ok=True)
    for spec in RUN_FILES:
        path = spec.path(out)
        if spec.is_folder:
            path.mkdir(exist_ok=True)
            (path / "placeholder").write_text("x")
        else:
            path.write_text(spec.name)
