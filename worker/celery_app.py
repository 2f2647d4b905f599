"""The worker's Celery app: the service's broker configuration plus the job task. Built on demand, never at
import, from the settings the caller passes."""

from __future__ import annotations

from celery import Celery

from service.broker import create_celery_app
from service.settings import Settings
from worker.tasks import register_tasks


def create_worker_app(settings: Settings) -> Celery:
    """A Celery app for ``settings`` with the job task registered (its jobs use the same ``settings``)."""
    app = create_celery_app(settings)
    register_tasks(app, settings)
    return app
