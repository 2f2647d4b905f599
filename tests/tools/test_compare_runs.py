"""tools/compare_runs.py: two run folders are the same result, or the difference is named down to the array."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from tool_modules import load_tool

compare_runs = load_tool("compare_runs")


def _run(folder: Path, semantic: list[int], instances: str = "[]", report: str = "{}") -> Path:
    folder.mkdir()
    np.savez(folder / "labels.npz", semantic=np.array(semantic), instance=np.array([0, 0, 1]))
    (folder / "instances.json").write_text(instances)
    (folder / "report.json").write_text(report)
    return folder


def test_the_same_result_is_identical_whatever_the_report(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", [1, 2, 3], report='{"wall_s": 1}')
    b = _run(tmp_path / "b", [1, 2, 3], report='{"wall_s": 2}')
    assert compare_runs.compare(a, b) == []
    assert compare_runs.main([str(a), str(b)]) == 0


def test_a_moved_label_names_its_array(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", [1, 2, 3])
    b = _run(tmp_path / "b", [1, 2, 4], instances='[{"id": 0}]')
    assert compare_runs.compare(a, b) == ["instances.json: differs", "labels.npz: arrays differ: semantic"]
    assert compare_runs.main([str(a), str(b)]) == 1


def test_a_file_in_one_run_only_is_a_difference(tmp_path: Path) -> None:
    a = _run(tmp_path / "a", [1, 2, 3])
    b = _run(tmp_path / "b", [1, 2, 3])
    (b / "metrics.json").write_text("{}")
    assert compare_runs.compare(a, b) == [f"metrics.json: only in {b}"]
