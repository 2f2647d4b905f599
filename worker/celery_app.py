"""The Celery app, configured from ``Settings``. Importing this module imports no task code and no torch.

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

from celery import Celery
from kombu.entity import Queue

from service.settings import Settings, get_settings
from worker.names import QueueName, TaskName


def create_celery_app(settings: Settings) -> Celery:
    """A Celery app for ``settings`` (broker, queues, reliability options)."""
    if settings.is_embedded_broker:
        settings.ensure_dirs()
    app = Celery("panogs", broker=settings.broker, include=["worker.tasks"])
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
        task_routes={TaskName.RUN_JOB.value: {"queue": settings.job_queue}},
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


app = create_celery_app(get_settings())
