"""Fixtures shared by every test folder.

``synth_tiny``: one ``panogs synth --preset tiny`` per session. Each start of the CLI imports torch and loads the
MiniLM text encoder (5 to 10 s on 2 cores); the tests that upload or run the tiny room only read it, so they share
one. A test that changes the bundle copies it first.

The pipeline runs that tests of several folders read are made once per session too: the tilted capture's run
(tests/core and tests/web), the small building and its tiled and untiled runs (tests/core and tests/worker).
Each is run with one torch thread, as the modules that read them run theirs (torch_threads.py), so that a test
comparing its own run with one of them byte for byte compares like with like.
"""

from __future__ import annotations

import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from shared_runs import BUILDING_NO_FIT, BUILDING_SPACE, BUILDING_TILED_ARGV

REPO = Path(__file__).resolve().parents[1]


@contextmanager
def _one_torch_thread() -> Iterator[None]:
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(before)


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


@pytest.fixture(scope="session")
def tilted_tum_run(synth_tiny: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny room as a TUM sequence in a world tilted 55 degrees (``capture_room.TILTED_55``; TUM records no
    gravity), every 2nd frame imported (``bundle/``) and run without the fit (``run/``): the up-direction tests and
    the viewer's share this one run. Only read: a test writes its renders elsewhere."""
    from capture_room import TILTED_55, import_tilted_tum

    from panogs_core.gaussians.config import AppearanceConfig
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import run_pipeline

    root = tmp_path_factory.mktemp("tilted-tum")
    no_fit = PipelineConfig(appearance=AppearanceConfig(enabled=False))
    with _one_torch_thread():
        run_pipeline(import_tilted_tum(synth_tiny, root, TILTED_55), root / "run", no_fit)
    return root


@pytest.fixture(scope="session")
def tiny_building(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two tiny rooms side by side, joined by a doorway (about 17k points, 28 frames). Only read."""
    from panogs_core.synthetic import make_building

    folder = tmp_path_factory.mktemp("building") / "b"
    return make_building(folder, rooms=(2, 1), room="tiny", feature_space=BUILDING_SPACE)


@pytest.fixture(scope="session")
def tiny_building_tiled_run(tiny_building: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``panogs run BUILDING --tiles 2x1 --set appearance.enabled=false``, tiles one after another (the default),
    in this process: the run folder. Only read; a test that runs it again copies it first."""
    from panogs_core.cli import main as cli_main

    out = tmp_path_factory.mktemp("building-tiled") / "run"
    with _one_torch_thread():
        assert cli_main(["run", str(tiny_building), "--out", str(out), *BUILDING_TILED_ARGV]) == 0
    return out


@pytest.fixture(scope="session")
def tiny_building_plain_run(tiny_building: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The building run whole by the library (``run_pipeline``, appearance fit off): the run folder. Only read."""
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import run_pipeline

    out = tmp_path_factory.mktemp("building-plain") / "run"
    with _one_torch_thread():
        run_pipeline(tiny_building, out, PipelineConfig().with_overrides(BUILDING_NO_FIT))
    return out
