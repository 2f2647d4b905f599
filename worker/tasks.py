"""Celery tasks: thin, they take ids. The pipeline (and torch) is imported on the first task, never at import.

Importing torch in a prefork parent before it forks deadlocks the children, so nothing here or in the
modules it imports at the top touches torch; ``runner.load_pipeline`` imports it inside the task.
"""

from __future__ import annotations

import functools
import os
import threading
import uuid
from typing import Any

from celery import Task
from celery.signals import worker_shutting_down

from service.db.session import get_session_factory
from service.settings import get_settings
from service.storage import Storage
from worker import runner
from worker.celery_app import app
from worker.names import TaskName

SHUTDOWN = threading.Event()  # set on warm shutdown; a running job is handed back at its next progress step


@worker_shutting_down.connect  # type: ignore[untyped-decorator]
def _on_shutdown(**_kwargs: Any) -> None:
    SHUTDOWN.set()


@functools.cache
def job_env() -> runner.JobEnv:
    """The worker process's job environment (settings, database, storage, pipeline), built on first use."""
    settings = get_settings()
    pipeline, stages, make_config = runner.load_pipeline(settings.pipeline_function)
    return runner.JobEnv(
        settings=settings,
        session_factory=get_session_factory(settings.database),
        storage=Storage(settings.storage),
        pipeline=pipeline,
        make_config=make_config,
        stages=stages,
        shutdown=SHUTDOWN,
    )


@app.task(  # type: ignore[untyped-decorator]
    name=TaskName.RUN_JOB.value,
    bind=True,
    acks_late=True,
    autoretry_for=(runner.TransientError,),
    retry_backoff=5,
    retry_backoff_max=120,
    max_retries=10,
)
def run_job(self: Task[Any, Any], job_id: str) -> str | None:
    """Run job ``job_id``; the job's row records everything, the return value is for the worker log only."""
    env = job_env()
    ident = uuid.UUID(job_id)
    lease = str(self.request.id)
    try:
        state = runner.execute_job(ident, lease=lease, worker=f"{self.request.hostname}/{os.getpid()}", env=env)
    except runner.TransientError:
        raise
    except Exception as exc:  # the task boundary: record the failure on the job, then let Celery log it
        runner.record_crash(ident, lease, exc, env)
        raise
    return None if state is None else state.value
