"""The README's curl session runs as written against a fresh ``panogs serve`` (tools/readme_session.py): every
line succeeds (``set -euo pipefail``, each curl with ``--fail-with-body``), and the files it downloads are a PLY
and a PNG, not an error body (the README once deleted the job before rendering it)."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest
from service_harness import under_ci
from tool_modules import load_tool

REPO = Path(__file__).resolve().parents[2]


tool = load_tool("readme_session")


def test_the_block_is_found_and_moved_to_another_port() -> None:
    block = tool.session_block()
    assert "panogs serve --port 8000 &" in block
    moved = tool.on_port(block, 54321)
    assert "8000" not in moved
    assert "--port 54321" in moved
    assert "http://127.0.0.1:54321" in moved
    # The job is deleted after everything that reads it (the render read a deleted job before).
    lines = moved.splitlines()
    delete = next(i for i, line in enumerate(lines) if "-X DELETE $API/v1/jobs/$JOB" in line)
    assert all("$JOB" not in line for line in lines[delete + 1 :])


def test_an_error_body_in_place_of_a_file_is_caught(tmp_path: Path) -> None:
    (tmp_path / "panoptic.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n")
    (tmp_path / "view.png").write_text('{"type":"not_found","message":"job x not found"}')
    assert tool.check_outputs(tmp_path) == [
        'view.png: not a PNG file: b\'{"type":"not_found","message":"job x not found"}\''
    ]


@pytest.mark.slow
def test_the_readme_session_runs_as_written(tmp_path: Path) -> None:
    missing = [name for name in ("jq", "zip", "curl") if shutil.which(name) is None]
    if missing:
        message = f"the README session needs {', '.join(missing)} (tools/check-system-deps installs them)"
        if under_ci():
            pytest.fail(message)
        pytest.skip(message)
    status, output = tool.run_session(tmp_path / "session")
    assert status == 0, output[-6000:]
