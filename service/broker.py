"""The broker side of the job queue: task and queue names, the Celery app's configuration, and a ping.

Both the API (which publishes jobs by task name) and the worker (which registers the task under that name) build
their Celery app with :func:`create_celery_app`; the worker adds its task code on top (``worker.celery_app``). Only the
worker imports this module's names from the service, never the other way round, so the API never imports task
code, and importing this module builds nothing and writes nothing.

Reliability settings, and why:

- ``task_acks_late`` + ``task_reject_on_worker_lost``: a job's message is acknowledged only when the task
  ends, so a worker killed mid-job does not lose it (the job itself is also watched by heartbeats in the
  database).
- ``worker_prefetch_multiplier=1``: a worker holds one job at a time; the others stay available to idle
  workers.
- ``visibility_timeout`` longer than any job (Redis): an unacknowledged message of a job that is still
  running is not handed to a second worker.
- No result backend: a job's state lives in the database.
- ``task_create_missing_queues=False``: only the declared ``cpu`` and ``gpu`` queues exist.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

from celery import Celery
from kombu.entity import Queue

from service.settings import Settings


class TaskName(StrEnum):
    """Registered task names: the API publishes by name, so it never imports task code."""

    RUN_JOB = "panogs.run_job"
    RUN_TILE = "panogs.run_tile"  # one tile of a tiled job (docs/service.md, "Tiled jobs")
    MERGE_TILES = "panogs.merge_tiles"  # a tiled job's merge, published by the tile that completes last


class QueueName(StrEnum):
    """The queues workers consume; jobs go to ``Settings.job_queue``."""

    CPU = "cpu"
    GPU = "gpu"


def create_celery_app(settings: Settings) -> Celery:
    """A Celery app for ``settings``: broker, queues, reliability options; no tasks, no folders.

    The embedded broker's folders are made by ``Settings.ensure_dirs``, which the commands that serve or work
    call when they start; building an app only configures it.
    """
    app = Celery("panogs", broker=settings.broker)
    app.conf.update(
        broker_transport_options=settings.broker_transport_options(),
        broker_connection_retry_on_startup=True,
        broker_connection_timeout=2.0,
        broker_heartbeat=0,
        result_backend=None,
        task_ignore_result=True,
        task_serializer="json",
        accept_content=["json"],
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        worker_concurrency=settings.worker_concurrency,
        worker_pool=settings.worker_pool,
        worker_hijack_root_logger=False,
        worker_send_task_events=False,
        task_queues=[Queue(q.value) for q in QueueName],  # type: ignore[no-untyped-call]
        task_default_queue=QueueName.CPU.value,
        task_create_missing_queues=False,
        task_routes={name.value: {"queue": settings.job_queue} for name in TaskName},
        # The API publishes while a request waits: give up quickly when the broker is away (the reaper
        # publishes again).
        task_publish_retry=True,
        task_publish_retry_policy={
            "max_retries": 2,
            "interval_start": 0,
            "interval_step": 0.2,
            "interval_max": 0.5,
        },
        broker_pool_limit=4,
        worker_disable_rate_limits=True,
    )
    return app


def broker_ping(settings: Settings, timeout_s: float = 1.0) -> None:
    """Raise when the broker cannot be reached within ``timeout_s`` (the filesystem broker: its folders)."""
    if settings.is_embedded_broker:
        for key in ("data_folder_in", "control_folder"):
            folder = Path(settings.broker_transport_options()[key])
            if not folder.is_dir():
                raise ConnectionError(f"broker folder {folder} is missing")
        return
    from kombu.connection import Connection

    options = settings.broker_transport_options()
    with Connection(settings.broker, transport_options=options, connect_timeout=timeout_s) as conn:  # type: ignore[no-untyped-call]
        conn.ensure_connection(max_retries=1, timeout=timeout_s)
        conn.default_channel  # noqa: B018  (opening a channel round-trips to the server)
