"""The Celery tasks: thin, they take a job id (or a tiled job's tile id). Registered on an app by
:func:`register_tasks`, never at import.

Importing torch in a prefork parent before it forks deadlocks the children, so nothing here or in the modules it
imports at the top touches torch: the pipeline (and torch, and the CUDA check) are loaded by the first task, in
the process that runs it, which also sets torch's thread count there (the OpenMP and BLAS pools took theirs from
the environment ``panogs worker`` set before anything imported them: worker/cli.py).
"""

from __future__ import annotations

import logging
import os
import threading
import uuid
from typing import Any

from celery import Celery, Task
from celery.signals import worker_shutting_down

from panogs_core.threads import set_torch_threads
from service.broker import TaskName
from service.db.session import get_session_factory
from service.settings import Settings
from service.storage.backends import open_storage
from worker import runner, tiles
from worker.device import cuda_available, device_config_factory
from worker.leased import JobEnv, TransientError

logger = logging.getLogger(__name__)


# Every task: acknowledged after it ran (a worker lost mid-task leaves its message to another), and retried with
# backoff when the database or the object storage stayed away (TransientError).
TASK_OPTIONS: dict[str, Any] = {
    "bind": True,
    "acks_late": True,
    "autoretry_for": (TransientError,),
    "retry_backoff": 5,
    "retry_backoff_max": 120,
    "max_retries": 10,
}


class LazyJobEnv:
    """The worker process's job environment, built by the first task that asks (after any fork)."""

    def __init__(self, settings: Settings, shutdown: threading.Event) -> None:
        self._settings = settings
        self._shutdown = shutdown
        self._env: JobEnv | None = None
        self._lock = threading.Lock()

    def get(self) -> JobEnv:
        """The environment, built once."""
        with self._lock:
            if self._env is None:
                self._env = build_job_env(self._settings, self._shutdown)
            return self._env


def build_job_env(settings: Settings, shutdown: threading.Event) -> JobEnv:
    """Settings, database, storage and the pipeline, with configs placed on this process's device."""
    threads = settings.worker_thread_count
    set_torch_threads(threads)  # here, not in the worker's parent: a torch call there deadlocks forked children
    logger.info("jobs use %d thread(s) in this process (PANOGS_WORKER_THREADS)", threads)
    pipeline, stages, make_config = runner.load_pipeline()
    has_cuda = cuda_available()
    logger.info("jobs train on %s unless they name a device", "cuda" if has_cuda else "cpu")
    return JobEnv(
        settings=settings,
        session_factory=get_session_factory(settings.database),
        storage=open_storage(settings),
        pipeline=pipeline,
        make_config=device_config_factory(make_config, has_cuda),
        stages=stages,
        shutdown=shutdown,
    )


def run_job(env: JobEnv, job_id: str, *, lease: str, worker: str) -> str | None:
    """Run job ``job_id``; the job's row records everything, the return value is for the worker log only."""
    ident = uuid.UUID(job_id)
    try:
        state = runner.execute_job(ident, lease=lease, worker=worker, env=env)
    except TransientError:
        raise
    except Exception as exc:  # the task boundary: record the failure on the job, then let Celery log it
        runner.record_crash(ident, lease, exc, env)
        raise
    return None if state is None else state.value


def run_part(env: JobEnv, tile_id: str, *, lease: str, worker: str) -> str | None:
    """Run the tile or merge ``tile_id`` of a tiled job; its row records everything (worker/tiles.py)."""
    try:
        state = tiles.execute_part(uuid.UUID(tile_id), lease=lease, worker=worker, env=env)
    except TransientError:
        raise
    except Exception as exc:  # the task boundary: fail the job with the error, then let Celery log it
        tiles.record_crash(uuid.UUID(tile_id), lease, exc, env)
        raise
    return None if state is None else state.value


def register_tasks(app: Celery, settings: Settings) -> None:
    """Register the job, tile and merge tasks on ``app``; their jobs use ``settings``, not whatever the environment
    holds."""
    shutdown = threading.Event()  # set on warm shutdown; a running job is handed back at its next progress step
    envs = LazyJobEnv(settings, shutdown)

    def on_shutdown(**_kwargs: Any) -> None:
        shutdown.set()

    worker_shutting_down.connect(on_shutdown, weak=False)

    @app.task(name=TaskName.RUN_JOB.value, **TASK_OPTIONS)  # type: ignore[untyped-decorator]
    def run_job_task(self: Task[Any, Any], job_id: str) -> str | None:
        worker = f"{self.request.hostname}/{os.getpid()}"
        return run_job(envs.get(), job_id, lease=str(self.request.id), worker=worker)

    def run_part_task(self: Task[Any, Any], tile_id: str) -> str | None:
        worker = f"{self.request.hostname}/{os.getpid()}"
        return run_part(envs.get(), tile_id, lease=str(self.request.id), worker=worker)

    for name in (TaskName.RUN_TILE, TaskName.MERGE_TILES):  # one body: the row's kind says which it runs
        app.task(name=name.value, **TASK_OPTIONS)(run_part_task)  # type: ignore[untyped-decorator]
