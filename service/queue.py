"""Handing jobs to the broker, by task name, after the database commit.

A job row is committed first with ``enqueued_at`` empty; then its message is published and ``enqueued_at``
set. If the broker is away at that moment, the job stays queued and the reaper publishes it later (an
outbox), so a broker outage delays jobs but loses none.
"""

from __future__ import annotations

import logging
import uuid
from typing import Any, Protocol, cast

from sqlalchemy.orm import Session, sessionmaker

from service.broker import TaskName, create_celery_app
from service.db.leases import JOBS, TILES, LeasedTable
from service.db.models import TileKind
from service.db.session import session_scope
from service.settings import Settings

logger = logging.getLogger(__name__)


class Sender(Protocol):
    """What the dispatcher needs of a Celery app (tests pass a recorder)."""

    def send_task(self, name: str, args: list[str] | None = ..., queue: str | None = ...) -> object: ...


def celery_sender(settings: Settings) -> Sender:
    """A Celery app for ``settings`` (configuration only; no task code is imported)."""
    return cast(Sender, create_celery_app(settings))


def dispatch(factory: sessionmaker[Session], sender: Sender, job_id: uuid.UUID, queue: str) -> bool:
    """Publish a committed job's message, then record it; False when the broker refused it.

    A job whose message could not be published stays ``queued`` with ``enqueued_at`` empty and the reaper
    publishes it again. A message published twice is harmless: only one task can claim the job.
    """
    return _publish(factory, sender, TaskName.RUN_JOB, JOBS, job_id, queue, f"job {job_id}")


TILE_TASKS = {TileKind.TILE: TaskName.RUN_TILE, TileKind.MERGE: TaskName.MERGE_TILES}


def dispatch_tile(
    factory: sessionmaker[Session], sender: Sender, tile_id: uuid.UUID, kind: TileKind, queue: str
) -> bool:
    """Publish a committed tile's (or merge's) message, then record it, as :func:`dispatch` does for a job."""
    return _publish(factory, sender, TILE_TASKS[kind], TILES, tile_id, queue, f"{kind} {tile_id}")


def _publish(
    factory: sessionmaker[Session],
    sender: Sender,
    task: TaskName,
    table: LeasedTable[Any],
    ident: uuid.UUID,
    queue: str,
    label: str,
) -> bool:
    try:
        sender.send_task(task.value, args=[str(ident)], queue=queue)
    except Exception as exc:  # any broker failure: the row stays queued and undispatched; the reaper retries
        logger.warning("%s: broker refused the message (%s); the reaper will retry", label, exc)
        return False
    with session_scope(factory) as session:
        table.mark_enqueued(session, ident)
    return True
