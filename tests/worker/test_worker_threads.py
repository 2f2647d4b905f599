"""The worker's thread policy: ``PANOGS_WORKER_THREADS`` and its default (the cores a worker process is given,
divided by the jobs it runs at once), and a real worker whose job process runs torch, OpenMP and BLAS with that
many threads and a passive wait policy."""

from __future__ import annotations

import json
import sys
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
from pipeline_stand_in import ENV as STAND_IN
from pydantic import ValidationError
from service_harness import Procs, wait_for
from wk_helpers import read_job

from panogs_core.threads import available_cores, threads_per_process
from service import settings as settings_module
from service.broker import TaskName, create_celery_app
from service.db.models import JobState
from service.settings import Settings
from service.storage import Storage

MakeJob = Callable[..., uuid.UUID]


def _settings(tmp_path: Path, **values: object) -> Settings:
    return Settings(_env_file=None, data_dir=tmp_path, **values)  # type: ignore[call-arg, arg-type]


def test_default_is_the_cores_divided_by_the_jobs_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(settings_module, "available_cores", lambda: 8)
    assert _settings(tmp_path).worker_thread_count == 8
    assert _settings(tmp_path, worker_pool="prefork", worker_concurrency=3).worker_thread_count == 2
    assert _settings(tmp_path, worker_pool="threads", worker_concurrency=16).worker_thread_count == 1
    # The solo pool runs one job at a time whatever the concurrency says.
    assert _settings(tmp_path, worker_pool="solo", worker_concurrency=4).worker_thread_count == 8


def test_the_setting_wins_over_the_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("PANOGS_WORKER_THREADS", "3")
    assert Settings(_env_file=None, data_dir=tmp_path).worker_thread_count == 3  # type: ignore[call-arg]


@pytest.mark.parametrize("value", ["0", "-2", "two", "1.5"])
def test_the_setting_is_validated(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, value: str) -> None:
    monkeypatch.setenv("PANOGS_WORKER_THREADS", value)
    with pytest.raises(ValidationError, match="worker_threads"):
        Settings(_env_file=None, data_dir=tmp_path)  # type: ignore[call-arg]


def _run_in_worker(settings: Settings, job_id: uuid.UUID, log_dir: Path, **env: str) -> dict[str, object]:
    """Start ``panogs worker`` on ``settings``'s embedded data folder with the thread probe as its pipeline, send
    it the job, and return the thread state its job process recorded (plus the worker's own pid)."""
    settings.ensure_dirs()  # the broker folders, so that the message can be sent before the worker is up
    procs = Procs({STAND_IN: "thread_probe", **env}, log_dir)
    try:
        argv = [sys.executable, "-m", "panogs_core.cli", "worker", "--data-dir", str(settings.data_dir)]
        worker = procs.start("worker", argv)
        create_celery_app(settings).send_task(TaskName.RUN_JOB.value, args=[str(job_id)], queue="cpu")
        wait_for(lambda: read_job(settings, job_id).state is JobState.SUCCEEDED, 120, "the job", procs.tail("worker"))
        # What the job recorded is all this reads: kill the worker's process group (its forked child with it)
        # rather than wait 4-5 s for an idle Celery worker's warm shutdown (test_runner and test_faults test that).
        procs.kill("worker")
    finally:
        procs.stop_all()
    probe = next(Storage(settings.storage).job_dir(job_id).rglob("threads.json"))
    return {**json.loads(probe.read_text()), "worker_pid": worker.pid}


@pytest.mark.slow  # a real worker process: start, one job, warm shutdown
@pytest.mark.skipif(available_cores() < 2, reason="one core: a limit of 1 is also the default")
def test_a_solo_worker_runs_its_jobs_with_the_configured_threads(
    settings: Settings, make_job: MakeJob, tmp_path: Path
) -> None:
    state = _run_in_worker(settings, make_job(), tmp_path, PANOGS_WORKER_THREADS="1", PANOGS_WORKER_POOL="solo")
    assert state["pid"] == state["worker_pid"], "the solo pool runs the job in the worker process itself"
    assert state["torch_threads"] == state["opencv_threads"] == 1
    assert state["pools"] == {"openmp": 1, "openblas": 1}, "numpy's and torch's pools were sized before loading"
    environ = state["environ"]
    assert isinstance(environ, dict)
    assert environ["OMP_NUM_THREADS"] == environ["MKL_NUM_THREADS"] == environ["OPENBLAS_NUM_THREADS"] == "1"
    assert environ["OMP_WAIT_POLICY"] == "PASSIVE"
    assert environ["KMP_BLOCKTIME"] == "0"
    assert environ["OPENCV_THREAD_POOL_ACTIVE_WAIT_WORKER"] == "0"


@pytest.mark.slow  # a real worker process: start, one job, warm shutdown
def test_a_prefork_child_gets_its_share_of_the_cores(settings: Settings, make_job: MakeJob, tmp_path: Path) -> None:
    """No setting: two job processes share the worker's cores; the limits reach the forked child."""
    state = _run_in_worker(settings, make_job(), tmp_path, PANOGS_WORKER_POOL="prefork", PANOGS_WORKER_CONCURRENCY="2")
    assert state["ppid"] == state["worker_pid"], "the job ran in a child forked by the worker"
    expected = threads_per_process(available_cores(), 2)
    assert state["torch_threads"] == state["opencv_threads"] == expected
    assert state["pools"] == {"openmp": expected, "openblas": expected}
    environ = state["environ"]
    assert isinstance(environ, dict)
    assert environ["OMP_NUM_THREADS"] == str(expected)
    assert environ["OMP_WAIT_POLICY"] == "PASSIVE"
