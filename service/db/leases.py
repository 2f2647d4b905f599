"""The lease queries, written once for the two kinds of leased rows: jobs and the tiles (and merges) of tiled jobs.

A row is run by the task holding its ``lease`` (the claiming Celery task's id). A task claims a queued row, its
own re-delivered one, or a running row whose heartbeat went silent; every write it makes afterwards is guarded by
the lease and the running state, so a worker presumed dead can no longer change the row. The reaper finds rows
whose heartbeat stopped and puts them back in the queue; a worker's shutdown hands its row back without counting
the claim as an attempt.

:data:`JOBS` and :data:`TILES` say what differs: the model, its states, and what else a claim requires (a job not
asked to stop and not fanned out into tiles; a tile whose job runs and is not asked to stop).
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, Generic, TypeVar, cast

from sqlalchemy import ColumnElement, Result, exists, func, or_, select, update
from sqlalchemy.orm import Session

from service.db.base import Base, utcnow
from service.db.models import Job, JobState, JobTile, TileState

M = TypeVar("M", bound=Base)

# A job that fanned out into tiles: its tiles and merge have the leases and heartbeats; the job's own go quiet.
TILED = exists().where(JobTile.job_id == Job.id)


def one_row(result: Result[Any]) -> bool:
    """True when an UPDATE or DELETE matched exactly one row (its guard held)."""
    return getattr(result, "rowcount", 0) == 1


def stale_cutoff(seconds: float) -> datetime:
    """``now - seconds``."""
    return utcnow() - timedelta(seconds=seconds)


@dataclass(frozen=True)
class LeasedTable(Generic[M]):
    """One kind of leased row: its model, its queued and running states, and the extra guards of its queries."""

    model: type[M]
    queued: Any  # the model's queued state
    running: Any  # the model's running state
    claimable: tuple[ColumnElement[bool], ...] = ()  # what a claim requires besides the row's own state
    watched: tuple[ColumnElement[bool], ...] = ()  # which running rows have a heartbeat the reaper watches

    @property
    def _c(self) -> Any:
        return cast(Any, self.model)

    def held(self, ident: uuid.UUID, lease: str) -> list[ColumnElement[bool]]:
        """The guard of every write a task makes: the row, under ``lease``, still running."""
        c = self._c
        return [c.id == ident, c.lease == lease, c.state == self.running]

    def claim(self, session: Session, ident: uuid.UUID, lease: str, worker: str, stale_before: datetime) -> M | None:
        """Take the row for this task: queued, a re-delivery of our own task, or running with a heartbeat older than
        ``stale_before``. Returns it (now running under ``lease``, one more attempt), or None when it is not ours."""
        c, now = self._c, utcnow()
        claimable = or_(
            c.state == self.queued,
            (c.state == self.running) & or_(c.lease == lease, c.heartbeat_at < stale_before),
        )
        result = session.execute(
            update(self.model)
            .where(c.id == ident, claimable, *self.claimable)
            .values(
                state=self.running,
                lease=lease,
                worker=worker,
                attempts=c.attempts + 1,
                heartbeat_at=now,
                started_at=func.coalesce(c.started_at, now),
                updated_at=now,
            )
        )
        session.commit()
        if not one_row(result):
            return None
        return session.get(self.model, ident, populate_existing=True)

    def beat(self, session: Session, ident: uuid.UUID, lease: str, now: datetime | None = None, **values: Any) -> bool:
        """Write ``values`` and the heartbeat (at ``now``) of a running row we hold, not committed (the caller writes
        what goes with it in the same transaction); False once the lease is lost or the row left running."""
        now = now or utcnow()
        result = session.execute(
            update(self.model).where(*self.held(ident, lease)).values(heartbeat_at=now, updated_at=now, **values)
        )
        return one_row(result)

    def release(self, session: Session, ident: uuid.UUID, lease: str, **values: Any) -> bool:
        """Hand a running row we hold back to the queue (worker shutdown); this claim does not count as an
        attempt."""
        c = self._c
        result = session.execute(
            update(self.model)
            .where(*self.held(ident, lease))
            .values(
                state=self.queued, lease=None, enqueued_at=None, attempts=c.attempts - 1, updated_at=utcnow(), **values
            )
        )
        session.commit()
        return one_row(result)

    def silent(self, session: Session, silent_since: datetime) -> list[M]:
        """Running rows whose worker has not sent a heartbeat since ``silent_since``."""
        c = self._c
        stmt = select(self.model).where(c.state == self.running, c.heartbeat_at < silent_since, *self.watched)
        return list(session.scalars(stmt.limit(100)))

    def requeue_silent(self, session: Session, ident: uuid.UUID, silent_since: datetime) -> bool:
        """Put a silent running row back in the queue (to be resumed); False if it moved meanwhile."""
        c = self._c
        result = session.execute(
            update(self.model)
            .where(c.id == ident, c.state == self.running, c.heartbeat_at < silent_since)
            .values(state=self.queued, lease=None, enqueued_at=None, updated_at=utcnow())
        )
        session.commit()
        return one_row(result)

    def requeue_worker(self, session: Session, worker_prefix: str) -> int:
        """Re-queue the running rows of a worker known to be dead (``worker`` starting with the prefix)."""
        c = self._c
        result = session.execute(
            update(self.model)
            .where(c.state == self.running, c.worker.startswith(worker_prefix, autoescape=True), *self.watched)
            .values(state=self.queued, lease=None, enqueued_at=None, updated_at=utcnow())
        )
        session.commit()
        return int(getattr(result, "rowcount", 0) or 0)

    def mark_enqueued(self, session: Session, ident: uuid.UUID) -> bool:
        """Record that the row's message reached the broker; False if another process already did."""
        c = self._c
        result = session.execute(
            update(self.model)
            .where(c.id == ident, c.state == self.queued, c.enqueued_at.is_(None))
            .values(enqueued_at=utcnow())
        )
        session.commit()
        return one_row(result)


def _job_runs() -> ColumnElement[bool]:
    return exists().where(Job.id == JobTile.job_id, Job.state == JobState.RUNNING, Job.cancel_requested.is_(False))


JOBS: LeasedTable[Job] = LeasedTable(
    Job, JobState.QUEUED, JobState.RUNNING, claimable=(Job.cancel_requested.is_(False), ~TILED), watched=(~TILED,)
)
TILES: LeasedTable[JobTile] = LeasedTable(JobTile, TileState.QUEUED, TileState.RUNNING, claimable=(_job_runs(),))


def undispatched(table: LeasedTable[M], older_than: datetime, *columns: Any) -> Sequence[Any]:
    """The where-clause of queued rows whose message never reached the broker, created before ``older_than``."""
    c = cast(Any, table.model)
    return [c.state == table.queued, c.enqueued_at.is_(None), c.created_at < older_than, *columns]
