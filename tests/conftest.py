"""Fixtures shared by every test folder.

``synth_tiny``: one ``panogs synth --preset tiny`` per session. Each start of the CLI imports torch and loads the
MiniLM text encoder (5 to 10 s on 2 cores); the tests that upload or run the tiny room only read it, so they share
one. A test that changes the bundle copies it first.

The pipeline runs that tests of several folders read are made once per session too: the tilted capture's run
(tests/core and tests/web), the small building and its tiled and untiled runs (tests/core and tests/worker).
Each is run with one torch thread, as the modules that read them run theirs (torch_threads.py), so that a test
comparing its own run with one of them byte for byte compares like with like.

"Once per session" is once per test run: under pytest-xdist (``make test``) the first process that asks makes the
folder and the other one waits for it and reads the same folder (made_once.py).

Under pytest-xdist each test process also gets its share of the cores for its numeric pools (one thread each on 2
cores), as ``panogs worker`` gives each job process its share: see :func:`_share_the_cores`.
"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
from made_once import made_once
from shared_runs import BUILDING_NO_FIT, BUILDING_SPACE, BUILDING_TILED_ARGV

from panogs_core.threads import apply_thread_environment, available_cores, loaded_too_early, threads_per_process

REPO = Path(__file__).resolve().parents[1]


def _share_the_cores() -> None:
    """In a pytest-xdist worker: size this process's torch, OpenMP, OpenBLAS and OpenCV pools to its share of the
    cores, with idle threads sleeping (panogs_core/threads.py). Otherwise each of the test processes sizes its pools
    to all the cores, and their threads and the spinning of idle ones fight over the same cores.

    The pools read their variables when their library loads, so they are set here, in the root conftest (loaded
    before any test module imports numpy), while the libraries load, and restored afterwards: the processes that
    the tests start (``panogs run``, a worker, the API) see this machine's environment, as they do without xdist,
    and the tests of how those size their own pools (tests/worker/test_worker_threads.py) still see them do it."""
    workers = os.environ.get("PYTEST_XDIST_WORKER_COUNT")
    if not workers or loaded_too_early():
        return
    threads = threads_per_process(available_cores(), int(workers))
    saved = dict(os.environ)
    apply_thread_environment(os.environ, threads)
    try:
        import cv2
        import numpy  # noqa: F401  (OpenBLAS sizes its pool when numpy loads)
        import torch

        torch.set_num_threads(threads)  # torch reads its default count lazily, after the variables are restored
        cv2.setNumThreads(threads)
    finally:
        os.environ.clear()
        os.environ.update(saved)


_share_the_cores()


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

    def synth(out: Path) -> None:
        argv = [sys.executable, "-m", "panogs_core.cli", "synth", str(out / "scene"), "--preset", "tiny"]
        subprocess.run(argv, cwd=REPO, check=True, capture_output=True, timeout=300)

    folder = made_once(tmp_path_factory, "synth-tiny", synth) / "scene"
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

    def tilted_run(root: Path) -> None:
        no_fit = PipelineConfig(appearance=AppearanceConfig(enabled=False))
        with _one_torch_thread():
            run_pipeline(import_tilted_tum(synth_tiny, root, TILTED_55), root / "run", no_fit)

    return made_once(tmp_path_factory, "tilted-tum", tilted_run)


@pytest.fixture(scope="session")
def tiny_building(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two tiny rooms side by side, joined by a doorway (about 17k points, 28 frames). Only read."""
    from panogs_core.synthetic import make_building

    def building(folder: Path) -> None:
        make_building(folder / "b", rooms=(2, 1), room="tiny", feature_space=BUILDING_SPACE)

    return made_once(tmp_path_factory, "building", building) / "b"


@pytest.fixture(scope="session")
def tiny_building_tiled_run(tiny_building: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``panogs run BUILDING --tiles 2x1 --set appearance.enabled=false``, tiles one after another (the default),
    in this process: the run folder. Only read; a test that runs it again copies it first."""
    from panogs_core.cli import main as cli_main

    def tiled_run(folder: Path) -> None:
        with _one_torch_thread():
            assert cli_main(["run", str(tiny_building), "--out", str(folder / "run"), *BUILDING_TILED_ARGV]) == 0

    return made_once(tmp_path_factory, "building-tiled", tiled_run) / "run"


@pytest.fixture(scope="session")
def tiny_building_plain_run(tiny_building: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The building run whole by the library (``run_pipeline``, appearance fit off): the run folder. Only read."""
    from panogs_core.pipeline.config import PipelineConfig
    from panogs_core.pipeline.run import run_pipeline

    def plain_run(folder: Path) -> None:
        with _one_torch_thread():
            run_pipeline(tiny_building, folder / "run", PipelineConfig().with_overrides(BUILDING_NO_FIT))

    return made_once(tmp_path_factory, "building-plain", plain_run) / "run"


# The test files that took longest in a run of the whole suite (per-file totals of ``pytest -n 2 --dist loadfile
# --junitxml``; docs/contributing.md, "The test suite"), most first, then the readers of a session folder that an
# earlier one made: pytest-xdist hands whole files to the two processes in collection order (:func:`pytest_configure`
# turns off its own order, by each file's count of tests), so the long ones start first and the short ones fill in
# at the end, and both processes finish at about the same time instead of one waiting for the other's last long
# file. Files not named keep their order after these.
LONG_FIRST = (
    "tests/web/test_browser.py",
    "tests/core/test_tiling.py",  # makes the building and its two runs (tests/conftest.py)
    "tests/tools/test_readme_session.py",
    "tests/core/test_maps2d_pipeline.py",
    "tests/service/test_map_models.py",
    "tests/service/test_tiled_job.py",
    "tests/service/test_two_hosts.py",
    "tests/service/test_no_torch.py",  # makes the fresh install (fresh_install.py)
    "tests/service/test_e2e.py",
    "tests/core/test_pipeline.py",
    "tests/service/test_faults.py",
    "tests/core/test_importers_capture.py",
    "tests/worker/test_tiled_jobs.py",  # reads the building's runs
    "tests/migrations/test_migrations.py",  # reads the fresh install
    "tests/core/test_scannet_round_trip.py",
    "tests/service/test_job_vocabulary.py",
    "tests/service/test_results.py",
    "tests/core/test_up_direction.py",  # makes the tilted capture's run
    "tests/web/test_view_photo.py",
    "tests/core/test_synthetic.py",
    "tests/service/test_renders.py",
    "tests/web/test_viewer_up.py",  # reads the tilted capture's run
)


def pytest_configure(config: pytest.Config) -> None:
    """Under ``--dist loadfile`` pytest-xdist hands out the files in collection order, not by their count of tests
    (``--no-loadscope-reorder``, set here rather than in pyproject's ``addopts``: a pytest started without plugins,
    as tests/service/test_honest_ci.py starts one, would refuse the option)."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Put the files of ``LONG_FIRST`` first, in its order (a stable sort: the tests of a file keep theirs)."""
    stale = [name for name in LONG_FIRST if not (REPO / name).is_file()]
    if stale:
        raise pytest.UsageError(f"tests/conftest.py LONG_FIRST names files that do not exist: {stale}")
    rank = {name: i for i, name in enumerate(LONG_FIRST)}
    items.sort(key=lambda item: rank.get(item.nodeid.split("::")[0], len(rank)))
