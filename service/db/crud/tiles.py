"""The tile and merge rows of a tiled job.

The job's first task plans; a tiled plan becomes one row per tile and one for the merge (``pending``) in one
transaction with the job's move to stage ``tiles``. Each tile row is claimed, heart-beaten and finished under its
own lease, like a job (``service.db.leases``); the tile that completes last promotes the merge to ``queued`` in the
transaction that records it done, and the merge ends the job. Job-level outcomes (failed, canceled) end every
unfinished row too.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, Row, func, select, update
from sqlalchemy.orm import Session

from service.db.base import utcnow
from service.db.crud.jobs import fit_ended, replace_artifacts
from service.db.leases import JOBS, TILED, TILES, one_row, undispatched
from service.db.models import Artifact, FitState, Job, JobState, JobTile, TileKind, TileState

_LIVE_TILE = [TileState.PENDING, TileState.QUEUED, TileState.RUNNING]


def fan_out(session: Session, job_id: uuid.UUID, lease: str, rows: Sequence[JobTile], **values: Any) -> bool:
    """Record a running job we hold as tiled: its tile and merge rows, the job at stage ``tiles``; False once the
    lease is lost (nothing is written)."""
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(*JOBS.held(job_id, lease), ~TILED)
        .values(stage="tiles", progress=0.0, heartbeat_at=now, updated_at=now, **values)
    )
    if not one_row(result):
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


def undispatched_tiles(session: Session, older_than: datetime) -> list[tuple[uuid.UUID, TileKind, str]]:
    """Queued tiles and merges whose message never reached the broker (or was lost with their worker): id, kind and
    the job's queue."""
    stmt = (
        select(JobTile.id, JobTile.kind, Job.queue)
        .join(Job, Job.id == JobTile.job_id)
        .where(*undispatched(TILES, older_than))
    )
    return [(row[0], row[1], row[2]) for row in session.execute(stmt.limit(100))]


def job_queue(session: Session, job_id: uuid.UUID) -> str:
    """The queue a job's tasks go to."""
    return str(session.scalar(select(Job.queue).where(Job.id == job_id)))


def claim_tile(session: Session, tile_id: uuid.UUID, lease: str, worker: str, stale_before: datetime) -> JobTile | None:
    """Take a tile (or merge) for this task, on a job's rules (``claim_job``), while its job runs and is not asked to
    stop; the tile now ``running`` under ``lease``, or None."""
    return TILES.claim(session, tile_id, lease, worker, stale_before)


def _job_progress(job_id: uuid.UUID) -> Any:
    """The job's progress from its rows: the tiles' and the merge's, weighted by their ``weight``."""
    weighted = select(func.sum(JobTile.weight * JobTile.progress) / func.sum(JobTile.weight))
    return weighted.where(JobTile.job_id == job_id).scalar_subquery()


def update_tile_running(session: Session, tile_id: uuid.UUID, job_id: uuid.UUID, lease: str, **values: Any) -> bool:
    """Write progress fields (and the heartbeat) of a running tile we hold, and the job's progress with them; False
    once the lease is lost or the tile left running."""
    if not TILES.beat(session, tile_id, lease, **values):
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
    return TILES.release(session, tile_id, lease)


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
    done = TILES.beat(session, tile_id, lease, now, state=TileState.SUCCEEDED, progress=1.0, finished_at=now, **values)
    if not (one_row(locked) and done):
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
        merge_id = merge_id if one_row(promoted) else None
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
            fit_state=fit_ended(FitState.CANCELED if state == JobState.CANCELED else FitState.FAILED),
            finished_at=now,
            heartbeat_at=now,
            updated_at=now,
        )
    )
    if not one_row(result):
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
    moved = TILES.beat(
        session, merge_id, lease, now, state=TileState.SUCCEEDED, progress=1.0, finished_at=now, **merge_values
    )
    ended = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.state == JobState.RUNNING)
        .values(state=JobState.SUCCEEDED, finished_at=now, heartbeat_at=now, updated_at=now, **job_values)
    )
    if not (moved and one_row(ended)):
        session.rollback()
        return False
    replace_artifacts(session, job_id, artifacts)
    session.commit()
    return True
