"""Queries and guarded state transitions, shared by the API, the reaper and the worker.

Every read the API makes is scoped to a tenant (another tenant's rows are simply not found). Every write a
worker makes to a running job is guarded by the job's ``lease`` (the claiming task's id), so a worker that
lost its job (presumed dead and replaced) can no longer change it.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import datetime, timedelta
from typing import Any, TypeVar

from sqlalchemy import ColumnElement, Connection, Result, Row, case, delete, exists, func, literal, or_, select, update
from sqlalchemy.orm import Session

from service.db.base import Base, utcnow
from service.db.models import (
    Artifact,
    FitState,
    Job,
    JobState,
    JobTile,
    Scene,
    TileKind,
    TileState,
    Upload,
    UploadState,
)

M = TypeVar("M", bound=Base)

# A job that fanned out into tiles: its tiles and merge have the leases and heartbeats; the job's own go quiet.
_TILED = exists().where(JobTile.job_id == Job.id)


def _one_row(result: Result[Any]) -> bool:
    """True when an UPDATE or DELETE matched exactly one row (its guard held)."""
    return getattr(result, "rowcount", 0) == 1


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


def read_job_row(conn: Connection, job_id: uuid.UUID, tenant_id: uuid.UUID) -> Row[Any] | None:
    """A tenant's job as a plain row (attribute access like the model), in one statement."""
    table = Job.__table__
    shown = [column for column in table.c if column.name != "vocabulary_embeddings"]  # the poll never needs them
    stmt = select(*shown).where(table.c.id == job_id, table.c.api_key_id == tenant_id)
    return conn.execute(stmt).first()


# Uploads ---------------------------------------------------------------------------------------------------


def advance_upload(session: Session, upload_id: uuid.UUID, old_offset: int, new_offset: int, **values: Any) -> bool:
    """Move an upload's offset forward (with ``values``: its multipart state), only if nobody else moved it
    meanwhile."""
    result = session.execute(
        update(Upload)
        .where(Upload.id == upload_id, Upload.offset == old_offset)
        .values(offset=new_offset, updated_at=utcnow(), **values)
    )
    session.commit()
    return _one_row(result)


def stale_uploads(session: Session, older_than: datetime) -> list[Upload]:
    """Uploads not made into a scene and untouched since ``older_than``."""
    live = [UploadState.RECEIVING, UploadState.COMPLETE]
    stmt = select(Upload).where(Upload.state.in_(live), Upload.updated_at < older_than)
    return list(session.scalars(stmt.limit(100)))


def set_upload_state(session: Session, upload_id: uuid.UUID, old: UploadState, new: UploadState) -> bool:
    """Move an upload from ``old`` to ``new``; False when it was not in ``old`` (someone else moved it)."""
    result = session.execute(
        update(Upload).where(Upload.id == upload_id, Upload.state == old).values(state=new, updated_at=utcnow())
    )
    session.commit()
    return _one_row(result)


def delete_upload(session: Session, upload_id: uuid.UUID) -> None:
    """Delete an upload's row (its bytes are the caller's to remove)."""
    session.execute(delete(Upload).where(Upload.id == upload_id))
    session.commit()


# Jobs: API side --------------------------------------------------------------------------------------------


def find_idempotent_job(session: Session, tenant_id: uuid.UUID, key: str) -> Job | None:
    """The tenant's job created with Idempotency-Key ``key``."""
    return session.scalar(select(Job).where(Job.api_key_id == tenant_id, Job.idempotency_key == key))


def mark_enqueued(session: Session, job_id: uuid.UUID) -> bool:
    """Record that the job's message reached the broker; False if another process already did."""
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.QUEUED, Job.enqueued_at.is_(None))
        .values(enqueued_at=utcnow())
    )
    session.commit()
    return _one_row(result)


def request_cancel(session: Session, job: Job) -> Job:
    """Cancel a queued job at once; ask a running one to stop (the worker checks between progress steps)."""
    now = utcnow()
    if job.state == JobState.QUEUED:
        session.execute(
            update(Job)
            .where(Job.id == job.id, Job.state == JobState.QUEUED)
            .values(
                state=JobState.CANCELED,
                cancel_requested=True,
                fit_state=_fit_ended(FitState.CANCELED),
                finished_at=now,
                updated_at=now,
            )
        )
    elif job.state == JobState.RUNNING:
        session.execute(update(Job).where(Job.id == job.id).values(cancel_requested=True, updated_at=now))
    session.commit()
    session.refresh(job)
    return job


def undispatched_jobs(session: Session, older_than: datetime) -> list[Job]:
    """Queued jobs whose message never reached the broker (it was away when they were created)."""
    stmt = select(Job).where(Job.state == JobState.QUEUED, Job.enqueued_at.is_(None), Job.created_at < older_than)
    return list(session.scalars(stmt.limit(100)))


def lost_jobs(session: Session, silent_since: datetime) -> list[Job]:
    """Running jobs whose worker has not sent a heartbeat since ``silent_since``."""
    stmt = select(Job).where(Job.state == JobState.RUNNING, Job.heartbeat_at < silent_since, ~_TILED)
    return list(session.scalars(stmt.limit(100)))


def requeue_lost(session: Session, job: Job, silent_since: datetime) -> bool:
    """Put a lost running job back in the queue (to be resumed); False if it moved meanwhile."""
    result = session.execute(
        update(Job)
        .where(Job.id == job.id, Job.state == JobState.RUNNING, Job.heartbeat_at < silent_since)
        .values(state=JobState.QUEUED, lease=None, enqueued_at=None, updated_at=utcnow())
    )
    session.commit()
    return _one_row(result)


def requeue_worker_jobs(session: Session, worker_prefix: str) -> int:
    """Re-queue the running jobs of a worker known to be dead (``worker`` column starting with the prefix)."""
    result = session.execute(
        update(Job)
        .where(Job.state == JobState.RUNNING, Job.worker.startswith(worker_prefix, autoescape=True), ~_TILED)
        .values(state=JobState.QUEUED, lease=None, enqueued_at=None, updated_at=utcnow())
    )
    session.commit()
    return int(getattr(result, "rowcount", 0) or 0)


def fail_lost(session: Session, job: Job, silent_since: datetime, error_type: str, message: str) -> bool:
    """Fail a lost running job for good; False if it moved meanwhile."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(Job.id == job.id, Job.state == JobState.RUNNING, Job.heartbeat_at < silent_since)
        .values(
            state=JobState.FAILED,
            error_type=error_type,
            error_message=message,
            fit_state=_fit_ended(FitState.FAILED),
            finished_at=now,
            updated_at=now,
        )
    )
    session.commit()
    return _one_row(result)


# Jobs: worker side -----------------------------------------------------------------------------------------


def claim_job(session: Session, job_id: uuid.UUID, lease: str, worker: str, stale_before: datetime) -> Job | None:
    """Take a job for this task: a queued job, a re-delivery of our own task, or a running job gone silent.

    Returns the job (now ``running`` under ``lease``), or None when it is not ours to run: finished, canceled,
    running under a live worker, or fanned out into tiles (its tiles' tasks run it).
    """
    now = utcnow()
    claimable = or_(
        Job.state == JobState.QUEUED,
        (Job.state == JobState.RUNNING) & or_(Job.lease == lease, Job.heartbeat_at < stale_before),
    )
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, claimable, Job.cancel_requested.is_(False), ~_TILED)
        .values(
            state=JobState.RUNNING,
            lease=lease,
            worker=worker,
            attempts=Job.attempts + 1,
            heartbeat_at=now,
            started_at=func.coalesce(Job.started_at, now),
            updated_at=now,
        )
    )
    session.commit()
    if not _one_row(result):
        return None
    return session.get(Job, job_id, populate_existing=True)


def update_running(session: Session, job_id: uuid.UUID, lease: str, **values: Any) -> bool:
    """Write progress fields of a running job we hold; False once the lease is lost or the job left
    running."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease == lease, Job.state == JobState.RUNNING)
        .values(heartbeat_at=now, updated_at=now, **values)
    )
    session.commit()
    return _one_row(result)


def release_job(session: Session, job_id: uuid.UUID, lease: str, **values: Any) -> bool:
    """Hand a running job we hold back to the queue (worker shutdown); this claim does not count as an
    attempt."""
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease == lease, Job.state == JobState.RUNNING)
        .values(
            state=JobState.QUEUED,
            lease=None,
            enqueued_at=None,
            attempts=Job.attempts - 1,
            updated_at=utcnow(),
            **values,
        )
    )
    session.commit()
    return _one_row(result)


def record_results(
    session: Session, job_id: uuid.UUID, lease: str, artifacts: Sequence[Artifact], **values: Any
) -> bool:
    """The results of a running job we hold are ready: ``results_at``, the fit running, and the results' artifact
    rows (replacing any from an earlier attempt), in one transaction; False once the lease is lost."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease == lease, Job.state == JobState.RUNNING)
        .values(
            results_at=func.coalesce(Job.results_at, now),
            fit_state=FitState.RUNNING,
            fit_progress=0.0,
            fit_error=None,
            heartbeat_at=now,
            updated_at=now,
            **values,
        )
    )
    if not _one_row(result):
        session.rollback()
        return False
    _replace_artifacts(session, job_id, artifacts)
    session.commit()
    return True


def _replace_artifacts(session: Session, job_id: uuid.UUID, artifacts: Sequence[Artifact]) -> None:
    for old in session.scalars(select(Artifact).where(Artifact.job_id == job_id)):
        session.delete(old)  # a re-run overwrites
    session.flush()
    session.add_all(artifacts)


def _fit_ended(state: FitState) -> Any:
    """``fit_state`` as a job that ends now leaves it: a fit still running takes ``state``, any other stays."""
    return case(
        (Job.fit_state == FitState.RUNNING, literal(state, Job.__table__.c.fit_state.type)), else_=Job.fit_state
    )


def cancel_requested(session: Session, job_id: uuid.UUID) -> bool:
    """True when the job's owner asked it to stop."""
    return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


def finish_job(
    session: Session,
    job_id: uuid.UUID,
    lease: str,
    state: JobState,
    *,
    artifacts: Sequence[Artifact] = (),
    **values: Any,
) -> bool:
    """Move a running job we hold to a terminal state (with its artifacts), in one transaction. A job that ends
    otherwise than succeeded during its fit keeps its results' artifacts, and its fit ends with it unless
    ``values`` says how."""
    now = utcnow()
    if state != JobState.SUCCEEDED and "fit_state" not in values:
        values["fit_state"] = _fit_ended(FitState.CANCELED if state == JobState.CANCELED else FitState.FAILED)
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease == lease, Job.state == JobState.RUNNING)
        .values(state=state, finished_at=now, heartbeat_at=now, updated_at=now, **values)
    )
    if not _one_row(result):
        session.rollback()
        return False
    if artifacts or state == JobState.SUCCEEDED:  # a job that ends otherwise keeps the rows of its results
        _replace_artifacts(session, job_id, artifacts)
    session.commit()
    return True


def fail_unclaimed(session: Session, job_id: uuid.UUID, error_type: str, message: str) -> bool:
    """Fail a queued job that cannot be run at all (e.g. claimed too many times)."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state.in_([JobState.QUEUED, JobState.RUNNING]))
        .values(
            state=JobState.FAILED,
            error_type=error_type,
            error_message=message,
            fit_state=_fit_ended(FitState.FAILED),
            finished_at=now,
            updated_at=now,
        )
    )
    session.commit()
    return _one_row(result)


def cancel_unclaimed(session: Session, job_id: uuid.UUID) -> None:
    """Mark a job whose owner asked to cancel it before a worker started it."""
    now = utcnow()
    session.execute(
        update(Job)
        .where(
            Job.id == job_id,
            Job.state.in_([JobState.QUEUED, JobState.RUNNING]),
            Job.cancel_requested.is_(True),
        )
        .values(state=JobState.CANCELED, fit_state=_fit_ended(FitState.CANCELED), finished_at=now, updated_at=now)
    )
    session.commit()


def get_scene(session: Session, scene_id: uuid.UUID) -> Scene | None:
    """A scene by id (worker side; no tenant scope)."""
    return session.get(Scene, scene_id)


def stale_cutoff(seconds: float) -> datetime:
    """``now - seconds``."""
    return utcnow() - timedelta(seconds=seconds)


# Tiles of a tiled job ----------------------------------------------------------------------------------------
#
# The job's first task plans; a tiled plan becomes one row per tile and one for the merge (``pending``) in one
# transaction with the job's move to stage ``tiles``. Each tile row is claimed, heart-beaten and finished under its
# own lease, like a job; the tile that completes last promotes the merge to ``queued`` in the transaction that
# records it done, and the merge ends the job. Job-level outcomes (failed, canceled) end every unfinished row too.

_LIVE_TILE = [TileState.PENDING, TileState.QUEUED, TileState.RUNNING]


def fan_out(session: Session, job_id: uuid.UUID, lease: str, rows: Sequence[JobTile], **values: Any) -> bool:
    """Record a running job we hold as tiled: its tile and merge rows, the job at stage ``tiles``; False once the
    lease is lost (nothing is written)."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease == lease, Job.state == JobState.RUNNING, ~_TILED)
        .values(stage="tiles", progress=0.0, heartbeat_at=now, updated_at=now, **values)
    )
    if not _one_row(result):
        session.rollback()
        return False
    session.add_all(rows)
    session.commit()
    return True


def tile_rows(conn: Connection | Session, job_ids: Sequence[uuid.UUID]) -> dict[uuid.UUID, list[Row[Any]]]:
    """The tile and merge rows of ``job_ids`` as plain rows, by index (the merge last), in one statement; a job that
    ran whole has none."""
    if not job_ids:
        return {}
    table = JobTile.__table__
    stmt = select(table).where(table.c.job_id.in_(list(job_ids))).order_by(table.c.job_id, table.c.tile_index)
    out: dict[uuid.UUID, list[Row[Any]]] = {}
    for row in conn.execute(stmt):
        out.setdefault(row.job_id, []).append(row)
    return out


def mark_tile_enqueued(session: Session, tile_id: uuid.UUID) -> bool:
    """Record that a tile's (or merge's) message reached the broker."""
    result = session.execute(
        update(JobTile)
        .where(JobTile.id == tile_id, JobTile.state == TileState.QUEUED, JobTile.enqueued_at.is_(None))
        .values(enqueued_at=utcnow())
    )
    session.commit()
    return _one_row(result)


def undispatched_tiles(session: Session, older_than: datetime) -> list[tuple[uuid.UUID, TileKind, str]]:
    """Queued tiles and merges whose message never reached the broker (or was lost with their worker): id, kind and
    the job's queue."""
    stmt = (
        select(JobTile.id, JobTile.kind, Job.queue)
        .join(Job, Job.id == JobTile.job_id)
        .where(JobTile.state == TileState.QUEUED, JobTile.enqueued_at.is_(None), JobTile.created_at < older_than)
    )
    return [(row[0], row[1], row[2]) for row in session.execute(stmt.limit(100))]


def job_queue(session: Session, job_id: uuid.UUID) -> str:
    """The queue a job's tasks go to."""
    return str(session.scalar(select(Job.queue).where(Job.id == job_id)))


def lost_tiles(session: Session, silent_since: datetime) -> list[JobTile]:
    """Running tiles and merges whose worker has not sent a heartbeat since ``silent_since``."""
    stmt = select(JobTile).where(JobTile.state == TileState.RUNNING, JobTile.heartbeat_at < silent_since)
    return list(session.scalars(stmt.limit(100)))


def requeue_lost_tile(session: Session, tile: JobTile, silent_since: datetime) -> bool:
    """Put a lost running tile back in the queue (its next task resumes from its checkpoints); False if it moved."""
    result = session.execute(
        update(JobTile)
        .where(JobTile.id == tile.id, JobTile.state == TileState.RUNNING, JobTile.heartbeat_at < silent_since)
        .values(state=TileState.QUEUED, lease=None, enqueued_at=None, updated_at=utcnow())
    )
    session.commit()
    return _one_row(result)


def requeue_worker_tiles(session: Session, worker_prefix: str) -> int:
    """Re-queue the running tiles of a worker known to be dead."""
    result = session.execute(
        update(JobTile)
        .where(JobTile.state == TileState.RUNNING, JobTile.worker.startswith(worker_prefix, autoescape=True))
        .values(state=TileState.QUEUED, lease=None, enqueued_at=None, updated_at=utcnow())
    )
    session.commit()
    return int(getattr(result, "rowcount", 0) or 0)


def claim_tile(session: Session, tile_id: uuid.UUID, lease: str, worker: str, stale_before: datetime) -> JobTile | None:
    """Take a tile (or merge) for this task, on a job's rules (:func:`claim_job`), while its job runs and is not
    asked to stop; the tile now ``running`` under ``lease``, or None."""
    now = utcnow()
    claimable = or_(
        JobTile.state == TileState.QUEUED,
        (JobTile.state == TileState.RUNNING) & or_(JobTile.lease == lease, JobTile.heartbeat_at < stale_before),
    )
    job_runs = exists().where(Job.id == JobTile.job_id, Job.state == JobState.RUNNING, Job.cancel_requested.is_(False))
    result = session.execute(
        update(JobTile)
        .where(JobTile.id == tile_id, claimable, job_runs)
        .values(
            state=TileState.RUNNING,
            lease=lease,
            worker=worker,
            attempts=JobTile.attempts + 1,
            heartbeat_at=now,
            started_at=func.coalesce(JobTile.started_at, now),
            updated_at=now,
        )
    )
    session.commit()
    if not _one_row(result):
        return None
    return session.get(JobTile, tile_id, populate_existing=True)


def _job_progress(job_id: uuid.UUID) -> Any:
    """The job's progress from its rows: the tiles' and the merge's, weighted by their ``weight``."""
    weighted = select(func.sum(JobTile.weight * JobTile.progress) / func.sum(JobTile.weight))
    return weighted.where(JobTile.job_id == job_id).scalar_subquery()


def update_tile_running(session: Session, tile_id: uuid.UUID, job_id: uuid.UUID, lease: str, **values: Any) -> bool:
    """Write progress fields (and the heartbeat) of a running tile we hold, and the job's progress with them; False
    once the lease is lost or the tile left running."""
    now = utcnow()
    result = session.execute(
        update(JobTile)
        .where(JobTile.id == tile_id, JobTile.lease == lease, JobTile.state == TileState.RUNNING)
        .values(heartbeat_at=now, updated_at=now, **values)
    )
    if not _one_row(result):
        session.rollback()
        return False
    if "progress" in values:
        session.execute(
            update(Job).where(Job.id == job_id, Job.state == JobState.RUNNING).values(progress=_job_progress(job_id))
        )
    session.commit()
    return True


def release_tile(session: Session, tile_id: uuid.UUID, lease: str) -> bool:
    """Hand a running tile we hold back to the queue (worker shutdown); this claim does not count as an attempt."""
    result = session.execute(
        update(JobTile)
        .where(JobTile.id == tile_id, JobTile.lease == lease, JobTile.state == TileState.RUNNING)
        .values(
            state=TileState.QUEUED, lease=None, enqueued_at=None, attempts=JobTile.attempts - 1, updated_at=utcnow()
        )
    )
    session.commit()
    return _one_row(result)


def finish_tile(
    session: Session, tile_id: uuid.UUID, job_id: uuid.UUID, lease: str, **values: Any
) -> tuple[bool, uuid.UUID | None]:
    """Record a running tile we hold as succeeded; (False, None) once the lease is lost or the job stopped running.

    The fan-in, in this one transaction: the job's row is written first, which locks it (PostgreSQL: a row lock;
    SQLite: the database's write lock), so tiles finishing at once count one after the other; the tile that sees
    none left moves the merge from ``pending`` to ``queued`` and gets its id back (to publish it).
    """
    now = utcnow()
    locked = session.execute(update(Job).where(Job.id == job_id, Job.state == JobState.RUNNING).values(updated_at=now))
    done = session.execute(
        update(JobTile)
        .where(JobTile.id == tile_id, JobTile.lease == lease, JobTile.state == TileState.RUNNING)
        .values(state=TileState.SUCCEEDED, progress=1.0, finished_at=now, heartbeat_at=now, updated_at=now, **values)
    )
    if not (_one_row(locked) and _one_row(done)):
        session.rollback()
        return False, None
    left = session.scalar(
        select(func.count())
        .select_from(JobTile)
        .where(JobTile.job_id == job_id, JobTile.kind == TileKind.TILE, JobTile.state != TileState.SUCCEEDED)
    )
    merge_id = None
    if not left:
        merge_id = session.scalar(select(JobTile.id).where(JobTile.job_id == job_id, JobTile.kind == TileKind.MERGE))
        promoted = session.execute(
            update(JobTile)
            .where(JobTile.id == merge_id, JobTile.state == TileState.PENDING)
            .values(state=TileState.QUEUED, enqueued_at=None, updated_at=now)
        )
        merge_id = merge_id if _one_row(promoted) else None
    session.execute(update(Job).where(Job.id == job_id).values(progress=_job_progress(job_id)))
    session.commit()
    return True, merge_id


def end_tiled_job(
    session: Session,
    job_id: uuid.UUID,
    state: JobState,
    *,
    tile_id: uuid.UUID | None = None,
    lease: str | None = None,
    error_type: str | None = None,
    message: str | None = None,
) -> bool:
    """End a tiled job otherwise than by its merge (a tile failed, was lost too often, or was canceled): the tile
    (when ``tile_id``, under ``lease`` if given) and every unfinished row take ``state``, the job too (while it
    runs), in one transaction. False when the job had already left running."""
    now = utcnow()
    tile_state = TileState.CANCELED if state == JobState.CANCELED else TileState.FAILED
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.RUNNING)
        .values(
            state=state,
            error_type=error_type,
            error_message=message,
            fit_state=_fit_ended(FitState.CANCELED if state == JobState.CANCELED else FitState.FAILED),
            finished_at=now,
            heartbeat_at=now,
            updated_at=now,
        )
    )
    if not _one_row(result):
        session.rollback()
        return False
    if tile_id is not None:
        guard = [JobTile.id == tile_id, *([JobTile.lease == lease] if lease is not None else [])]
        session.execute(
            update(JobTile)
            .where(*guard, JobTile.state.in_(_LIVE_TILE))
            .values(state=tile_state, error_type=error_type, error_message=message, finished_at=now, updated_at=now)
        )
    session.execute(
        update(JobTile)
        .where(JobTile.job_id == job_id, JobTile.state.in_(_LIVE_TILE))
        .values(state=TileState.CANCELED, lease=None, finished_at=now, updated_at=now)
    )
    session.commit()
    return True


def finish_merge(
    session: Session,
    merge_id: uuid.UUID,
    job_id: uuid.UUID,
    lease: str,
    artifacts: Sequence[Artifact],
    merge_values: dict[str, Any],
    **job_values: Any,
) -> bool:
    """The merge we hold is done: it moves running -> succeeded under its lease and the job to succeeded with its
    artifacts, in one transaction; only one merge can make that move, so the job is finished once."""
    now = utcnow()
    moved = session.execute(
        update(JobTile)
        .where(JobTile.id == merge_id, JobTile.lease == lease, JobTile.state == TileState.RUNNING)
        .values(
            state=TileState.SUCCEEDED, progress=1.0, finished_at=now, heartbeat_at=now, updated_at=now, **merge_values
        )
    )
    ended = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.RUNNING)
        .values(state=JobState.SUCCEEDED, finished_at=now, heartbeat_at=now, updated_at=now, **job_values)
    )
    if not (_one_row(moved) and _one_row(ended)):
        session.rollback()
        return False
    _replace_artifacts(session, job_id, artifacts)
    session.commit()
    return True
