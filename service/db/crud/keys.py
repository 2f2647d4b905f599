"""A tenant's rows (an API key is a tenant), and what the tenant uses against its quotas.

Every read the API makes is scoped to a tenant: another tenant's rows are simply not found.

The quota reads (:func:`stored_bytes`, :func:`live_jobs`) are where a check compares use with a limit
(``service.lifecycle``). Today that is a read, then the insert: two requests at once can both pass. Making it atomic
belongs here, beside them: a reservation that locks the tenant's ``api_key`` row (``SELECT ... FOR UPDATE`` on
PostgreSQL; SQLite's write lock, taken by the transaction's first write) or moves a counter by a conditional
``UPDATE ... WHERE used + n <= limit``, in the transaction that adds the upload or the job.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from typing import TypeVar

from sqlalchemy import ColumnElement, func, select
from sqlalchemy.orm import Session

from service.db.base import Base
from service.db.models import Artifact, Job, JobState, Scene, Upload, UploadState

M = TypeVar("M", bound=Base)

LIVE_JOB_STATES = (JobState.QUEUED, JobState.RUNNING)  # the jobs that count against the concurrent-job quota


def get_owned(session: Session, model: type[M], ident: uuid.UUID, tenant_id: uuid.UUID) -> M | None:
    """A row of ``model`` by id, only if it belongs to ``tenant_id``."""
    row = session.get(model, ident)
    if row is None or getattr(row, "api_key_id", None) != tenant_id:
        return None
    return row


def list_owned(
    session: Session,
    model: type[M],
    tenant_id: uuid.UUID,
    *,
    filters: Sequence[ColumnElement[bool]] = (),
    limit: int,
    offset: int,
) -> tuple[list[M], int]:
    """A page of a tenant's rows, newest first, and the total count."""
    where = [model.api_key_id == tenant_id, *filters]  # type: ignore[attr-defined]
    count = session.scalar(select(func.count()).select_from(model).where(*where)) or 0
    stmt = select(model).where(*where).order_by(model.created_at.desc(), model.id)  # type: ignore[attr-defined]
    rows = list(session.scalars(stmt.limit(limit).offset(offset)))
    return rows, count


def stored_bytes(session: Session, tenant_id: uuid.UUID) -> int:
    """What the tenant holds in storage: uploads not yet made into scenes, scenes, and job results."""
    uploads = session.scalar(
        select(func.coalesce(func.sum(Upload.length), 0)).where(
            Upload.api_key_id == tenant_id, Upload.state != UploadState.CONSUMED
        )
    )
    scenes = session.scalar(select(func.coalesce(func.sum(Scene.size_bytes), 0)).where(Scene.api_key_id == tenant_id))
    results = session.scalar(
        select(func.coalesce(func.sum(Artifact.size_bytes), 0))
        .join(Job, Job.id == Artifact.job_id)
        .where(Job.api_key_id == tenant_id)
    )
    return int(uploads or 0) + int(scenes or 0) + int(results or 0)


def live_jobs(session: Session, tenant_id: uuid.UUID) -> int:
    """How many of the tenant's jobs are queued or running."""
    live = session.scalar(
        select(func.count()).select_from(Job).where(Job.api_key_id == tenant_id, Job.state.in_(LIVE_JOB_STATES))
    )
    return int(live or 0)
