"""panogs_core/threads.py: the cores a process is given, each worker's share, the pools' environment, and
``panogs run --threads`` in a fresh process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from panogs_core import threads
from panogs_core.cli import build_parser

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(
    ("text", "expected"),
    [("max 100000\n", None), ("200000 100000\n", 2), ("150000 100000", 2), ("50000 100000", 1), ("", None),
     ("abc 100000", None), ("100000 0", None)],
)  # fmt: skip
def test_cgroup_cpu_limit(tmp_path: Path, text: str, expected: int | None) -> None:
    cpu_max = tmp_path / "cpu.max"
    cpu_max.write_text(text)
    assert threads.cgroup_cpu_limit(cpu_max) == expected


def test_no_cgroup_file_is_no_limit(tmp_path: Path) -> None:
    assert threads.cgroup_cpu_limit(tmp_path / "missing") is None


def test_available_cores_is_the_affinity_capped_by_the_quota(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "sched_getaffinity", lambda _pid: {0, 1, 2, 3, 4, 5}, raising=False)
    cpu_max = tmp_path / "cpu.max"
    cpu_max.write_text("max 100000\n")
    assert threads.available_cores(cpu_max) == 6
    cpu_max.write_text("250000 100000\n")  # docker --cpus=2.5
    assert threads.available_cores(cpu_max) == 3
    cpu_max.write_text("900000 100000\n")  # a quota above the affinity does not add cores
    assert threads.available_cores(cpu_max) == 6


@pytest.mark.parametrize(("cores", "processes", "expected"), [(8, 1, 8), (8, 3, 2), (2, 4, 1), (1, 1, 1)])
def test_threads_per_process(cores: int, processes: int, expected: int) -> None:
    assert threads.threads_per_process(cores, processes) == expected


@pytest.mark.parametrize(("cores", "processes"), [(0, 1), (4, 0)])
def test_threads_per_process_refuses_nonsense(cores: int, processes: int) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        threads.threads_per_process(cores, processes)


def test_environment_sets_counts_and_keeps_an_operators_wait_policy() -> None:
    environ = {"OMP_NUM_THREADS": "16", "KMP_BLOCKTIME": "200", "OPENBLAS_CORETYPE": "Haswell"}
    threads.apply_thread_environment(environ, 3)
    assert environ["OMP_NUM_THREADS"] == environ["MKL_NUM_THREADS"] == environ["OPENBLAS_NUM_THREADS"] == "3"
    assert environ["OPENCV_FOR_THREADS_NUM"] == "3"
    assert environ["OMP_WAIT_POLICY"] == "PASSIVE"
    assert environ["OPENBLAS_THREAD_TIMEOUT"] == "4"
    assert environ["KMP_BLOCKTIME"] == "200", "an operator's own wait policy is kept"
    assert environ["OPENBLAS_CORETYPE"] == "Haswell", "not a thread variable: left alone"
    with pytest.raises(ValueError, match="at least 1"):
        threads.thread_environment(0)


def test_run_threads_option_is_validated(capsys: pytest.CaptureFixture[str]) -> None:
    assert build_parser().parse_args(["run", "b", "--out", "o", "--threads", "2"]).threads == 2
    assert build_parser().parse_args(["run", "b", "--out", "o"]).threads is None
    for bad in ("0", "-1", "two"):
        with pytest.raises(SystemExit):
            build_parser().parse_args(["run", "b", "--out", "o", "--threads", bad])
        assert f"--threads: expected a whole number of at least 1, got '{bad}'" in capsys.readouterr().err


def _fresh_process_state(code: str) -> dict[str, object]:
    probe = (
        "import json, os, sys, cv2, threadpoolctl, torch\n"
        "pools = {p['internal_api']: p['num_threads'] for p in threadpoolctl.threadpool_info()}\n"
        "print(json.dumps({'torch': torch.get_num_threads(), 'pools': pools, 'opencv': cv2.getNumThreads(),\n"
        "                  'wait': os.environ.get('OMP_WAIT_POLICY')}))\n"
    )
    env = {k: v for k, v in os.environ.items() if k not in (*threads.THREAD_COUNT_VARIABLES, *threads.WAIT_POLICY)}
    env["PYTHONPATH"] = str(REPO)
    done = subprocess.run([sys.executable, "-c", code + probe], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    return dict(json.loads(done.stdout.splitlines()[-1]))


@pytest.mark.slow  # a fresh interpreter imports torch, numpy and OpenCV (1-3 s here)
@pytest.mark.skipif(threads.available_cores() < 2, reason="one core: a limit of 1 is also the default")
def test_panogs_run_limits_every_pool_before_the_pipeline_loads() -> None:
    """What ``panogs run --threads 1`` does first, in a process of its own: torch, OpenMP and numpy's OpenBLAS
    all run one thread, and idle threads wait passively."""
    code = "from panogs_core.cli.arguments import limit_threads\nlimit_threads(1)\nimport numpy\n"
    state = _fresh_process_state(code)
    assert state["torch"] == state["opencv"] == 1
    assert state["pools"] == {"openmp": 1, "openblas": 1}
    assert state["wait"] == "PASSIVE"


def test_panogs_parser_loads_no_thread_pool() -> None:
    """``panogs worker`` and ``panogs run`` set the limits after parsing their arguments: the parser (every
    command's module, the service's and the viewer's included) must not have loaded numpy or torch by then, nor
    the parsing of ``run``'s arguments (argparse converts the string default of ``--tiles`` too: it once loaded the
    tiling planner, so ``panogs run`` kept the libraries' own pools and imported torch inside the fusion)."""
    code = (
        "import sys\nfrom panogs_core.cli import build_parser\nfrom panogs_core.threads import loaded_too_early\n"
        "build_parser().parse_args(['run', 'bundle', '--out', 'out'])\nprint(loaded_too_early())"
    )
    done = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.strip() == "[]"


@pytest.mark.parametrize("inside", [1, None])
def test_torch_threads_sets_the_count_in_the_block_and_restores_it(inside: int | None) -> None:
    torch = pytest.importorskip("torch")
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        seen: list[int] = []

        def failing_stage() -> None:
            with threads.torch_threads(inside):
                seen.append(torch.get_num_threads())
                raise RuntimeError("the stage failed")

        with pytest.raises(RuntimeError):
            failing_stage()
        assert seen == [2 if inside is None else inside]
        assert torch.get_num_threads() == 2  # restored after a failure too
    finally:
        torch.set_num_threads(before)


class TestPrefetched:
    """``prefetched``: results in order, reads ahead on threads, an error raised where its result is due."""

    @pytest.mark.parametrize("workers", [1, 2, 3])
    def test_order(self, workers: int) -> None:
        from panogs_core.threads import prefetched

        assert list(prefetched(lambda x: x * x, list(range(10)), workers)) == [x * x for x in range(10)]
        assert list(prefetched(str, [], workers)) == []

    def test_error_where_due(self) -> None:
        from panogs_core.threads import prefetched

        def read(x: int) -> int:
            if x == 3:
                raise ValueError("bad frame 3")
            return x

        got = prefetched(read, list(range(6)), 2)
        assert [next(got) for _ in range(3)] == [0, 1, 2]
        with pytest.raises(ValueError, match="bad frame 3"):
            next(got)


def test_decode_threads_follow_the_lower_of_opencv_and_torch() -> None:
    """A tile's process narrows torch's threads only: the stages' frame threads follow it."""
    import cv2
    import torch

    from panogs_core.threads import decode_threads

    before_cv, before_torch = cv2.getNumThreads(), torch.get_num_threads()
    try:
        cv2.setNumThreads(3)
        torch.set_num_threads(2)
        assert decode_threads() == 2
        torch.set_num_threads(4)
        assert decode_threads() == 3
    finally:
        cv2.setNumThreads(before_cv)
        torch.set_num_threads(before_torch)
