"""A tenant's rows (an API key is a tenant), and what the tenant uses against its quotas.

Every read the API makes is scoped to a tenant: another tenant's rows are simply not found.

The quota reads (:func:`stored_bytes`, :func:`live_job_slots`, :func:`reserved_upload_bytes`) are where a check
compares use with a limit (``service.lifecycle``). A read, then an insert, lets two requests at once both pass; so a
reservation first takes :func:`lock_tenant` in the transaction that adds the upload or the job, and reads and
inserts under it: the tenant's ``api_key`` row locked (``SELECT ... FOR UPDATE`` on PostgreSQL; on SQLite the
database's write lock, taken by a write as the transaction's first statement, which waits out the busy timeout).
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from typing import TypeVar

from sqlalchemy import ColumnElement, func, select, text, update
from sqlalchemy.orm import Session

from service.db.base import Base
from service.db.models import ApiKey, Artifact, Job, JobState, JobTile, Scene, TileKind, Upload, UploadState

M = TypeVar("M", bound=Base)

LIVE_JOB_STATES = (JobState.QUEUED, JobState.RUNNING)  # the jobs that count against the concurrent-job quota
# PostgreSQL advisory lock held while an upload reserves room on the one storage volume all tenants share.
VOLUME_LOCK_KEY = 0x70616E6F  # "pano"


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


def lock_tenant(session: Session, tenant_id: uuid.UUID, *, volume: bool = False) -> None:
    """Hold the tenant's quota lock until the session's transaction ends (commit or rollback).

    ``volume``: also the lock of the shared storage volume (every tenant's uploads take room on it); taken after
    the tenant's, always in this order, so two reservations never wait on each other in a circle. On SQLite the
    write lock is already the whole database's.
    """
    if session.get_bind().dialect.name == "sqlite":
        # A write first: pysqlite opens the transaction here and SQLite takes its write lock for it, so every read
        # below sees the last committed reservation and no other one can commit until this transaction ends.
        same = update(ApiKey).where(ApiKey.id == tenant_id).values(name=ApiKey.name)
        session.execute(same.execution_options(synchronize_session=False))
        return
    session.execute(select(ApiKey.id).where(ApiKey.id == tenant_id).with_for_update())
    if volume:
        session.execute(text("SELECT pg_advisory_xact_lock(:key)"), {"key": VOLUME_LOCK_KEY})


def reserved_upload_bytes(session: Session, excluding: uuid.UUID | None = None) -> int:
    """Bytes every tenant's open uploads (but ``excluding``) have reserved on the volume and not yet written."""
    where = [Upload.state == UploadState.RECEIVING]
    if excluding is not None:
        where.append(Upload.id != excluding)
    total = session.scalar(select(func.coalesce(func.sum(Upload.length - Upload.offset), 0)).where(*where))
    return int(total or 0)


def live_job_slots(session: Session, tenant_id: uuid.UUID, limit: int) -> int:
    """The concurrent-job slots the tenant's queued and running jobs hold (:func:`job_slots` each)."""
    rows = session.execute(
        select(Job.id, Job.tiling).where(Job.api_key_id == tenant_id, Job.state.in_(LIVE_JOB_STATES))
    ).all()
    if not rows:
        return 0
    planned = dict(
        session.execute(
            select(JobTile.job_id, func.count())
            .where(JobTile.job_id.in_([r.id for r in rows]), JobTile.kind == TileKind.TILE)
            .group_by(JobTile.job_id)
        ).all()
    )
    return sum(job_slots(r.tiling, limit, int(planned.get(r.id, 0))) for r in rows)


def job_slots(tiling: dict[str, object] | None, limit: int, planned_tiles: int = 0) -> int:
    """The slots one live job holds: 1, or as many as its tiles (asked ``NxM``, or planned by ``auto``), never more
    than the whole ``limit`` (a job with more tiles than the limit runs alone)."""
    tiles = planned_tiles
    asked = str((tiling or {}).get("tiles", "off"))
    if "x" in asked:
        columns, _, rows = asked.partition("x")
        tiles = max(tiles, int(columns) * int(rows))
    return max(1, min(tiles, limit))
