"""A worker killed mid-task leaves its scratch folder; the next worker process on the data folder removes it at its
first task, and leaves a live sibling's (another worker process, the API extracting an upload) alone."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from service.db.models import JobState
from service.settings import Settings
from service.storage.scratch import is_stale, owner_tag, start_ticks
from worker import leased, runner

HOLD = """
import sys, time
from pathlib import Path
from service.storage import Storage
with Storage(Path(sys.argv[1])).scratch(sys.argv[2]) as folder:
    (folder / "partial.npz").write_bytes(b"x" * 1000)
    print(folder, flush=True)
    time.sleep(600)
"""


@pytest.fixture
def holders(settings: Settings) -> Iterator[Callable[[str], tuple[subprocess.Popen[str], Path]]]:
    """Processes that each hold a scratch folder of ``settings``'s storage until killed."""
    started: list[subprocess.Popen[str]] = []

    def hold(what: str) -> tuple[subprocess.Popen[str], Path]:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
        proc = subprocess.Popen([sys.executable, "-c", HOLD, str(settings.storage), what], stdout=subprocess.PIPE,
                                text=True, env=env)  # fmt: skip
        started.append(proc)
        assert proc.stdout is not None
        folder = Path(proc.stdout.readline().strip())
        assert folder.is_dir()
        return proc, folder

    yield hold
    for proc in started:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)


def test_a_killed_workers_scratch_is_removed_at_the_next_workers_first_task(
    make_env: Callable[..., leased.JobEnv],
    make_job: Callable[..., uuid.UUID],
    holders: Callable[[str], tuple[subprocess.Popen[str], Path]],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    killed, dead_folder = holders(f"job-{uuid.uuid4()}")
    _sibling, live_folder = holders("extract")
    killed.send_signal(signal.SIGKILL)  # kill -9 mid-task: its finally never runs
    killed.wait(timeout=30)
    assert dead_folder.is_dir()
    monkeypatch.setattr(leased, "_SWEPT", set())  # this test process plays a freshly started worker
    job_id = make_job(config={"stage_s": 0.0})
    assert runner.execute_job(job_id, lease="l1", worker="w", env=make_env()) is JobState.SUCCEEDED
    assert not dead_folder.exists()
    assert live_folder.is_dir()
    assert (live_folder / "partial.npz").stat().st_size == 1000


def test_a_reused_pid_does_not_pass_for_the_owner(tmp_path: Path) -> None:
    pid = os.getpid()
    start = start_ticks(pid)
    assert start  # Linux: the start time is read from /proc
    now = time.time()
    ours = tmp_path / f"job-{owner_tag()}-abc123"
    before = tmp_path / f"job-o{pid}.{start - 1}-abc123"  # the same pid, an earlier process (a restarted container)
    gone = tmp_path / f"job-o{2**22 + 7}.{start}-abc123"  # past the largest pid Linux hands out
    for folder in (ours, before, gone):
        folder.mkdir()
    assert not is_stale(ours, now)
    assert is_stale(before, now)
    assert is_stale(gone, now)
