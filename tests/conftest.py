"""Fixtures shared by every test folder.

``synth_tiny``: one ``panogs synth --preset tiny`` per session. Each start of the CLI imports torch and loads the
MiniLM text encoder (5 to 10 s on 2 cores); the tests that upload or run the tiny room only read it, so they share
one. A test that changes the bundle copies it first.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _listing(folder: Path) -> dict[str, tuple[int, int]]:
    return {str(p.relative_to(folder)): (p.stat().st_size, p.stat().st_mtime_ns) for p in sorted(folder.rglob("*"))}


@pytest.fixture(scope="session")
def synth_tiny(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The folder ``panogs synth OUT --preset tiny`` writes (default difficulty, seed and feature space)."""
    folder = tmp_path_factory.mktemp("synth-tiny") / "scene"
    argv = [sys.executable, "-m", "panogs_core.cli", "synth", str(folder), "--preset", "tiny"]
    subprocess.run(argv, cwd=REPO, check=True, capture_output=True, timeout=300)
    before = _listing(folder)
    yield folder
    assert _listing(folder) == before, "a test changed the shared bundle: copy it first"
