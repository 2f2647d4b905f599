"""Job rows: what the API asks of them (idempotency, cancel, the outbox and the reaper's finds) and the guarded moves
of the task that runs one (claim, progress, results, finish; ``service.db.leases`` for the lease's own queries)."""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from datetime import datetime
from typing import Any

from sqlalchemy import Connection, Row, case, func, literal, select, update
from sqlalchemy.orm import Session

from service.db.base import utcnow
from service.db.leases import JOBS, one_row, undispatched
from service.db.models import Artifact, FitState, Job, JobState

# API side ---------------------------------------------------------------------------------------------------------


def read_job_row(conn: Connection, job_id: uuid.UUID, tenant_id: uuid.UUID) -> Row[Any] | None:
    """A tenant's job as a plain row (attribute access like the model), in one statement."""
    table = Job.__table__
    shown = [column for column in table.c if column.name != "vocabulary_embeddings"]  # the poll never needs them
    stmt = select(*shown).where(table.c.id == job_id, table.c.api_key_id == tenant_id)
    return conn.execute(stmt).first()


def find_idempotent_job(session: Session, tenant_id: uuid.UUID, key: str) -> Job | None:
    """The tenant's job created with Idempotency-Key ``key``."""
    return session.scalar(select(Job).where(Job.api_key_id == tenant_id, Job.idempotency_key == key))


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
                fit_state=fit_ended(FitState.CANCELED),
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
    return list(session.scalars(select(Job).where(*undispatched(JOBS, older_than)).limit(100)))


def fail_lost(session: Session, job: Job, silent_since: datetime, error_type: str, message: str) -> bool:
    """Fail a lost running job for good; False if it moved meanwhile."""
    return _fail_where(
        session, [Job.id == job.id, Job.state == JobState.RUNNING, Job.heartbeat_at < silent_since], error_type, message
    )


def fail_unclaimed(session: Session, job_id: uuid.UUID, error_type: str, message: str) -> bool:
    """Fail a queued job that cannot be run at all (e.g. claimed too many times)."""
    live = [Job.id == job_id, Job.state.in_([JobState.QUEUED, JobState.RUNNING])]
    return _fail_where(session, live, error_type, message)


def _fail_where(session: Session, where: list[Any], error_type: str, message: str) -> bool:
    now = utcnow()
    result = session.execute(
        update(Job)
        .where(*where)
        .values(
            state=JobState.FAILED,
            error_type=error_type,
            error_message=message,
            fit_state=fit_ended(FitState.FAILED),
            finished_at=now,
            updated_at=now,
        )
    )
    session.commit()
    return one_row(result)


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
        .values(state=JobState.CANCELED, fit_state=fit_ended(FitState.CANCELED), finished_at=now, updated_at=now)
    )
    session.commit()


def cancel_requested(session: Session, job_id: uuid.UUID) -> bool:
    """True when the job's owner asked it to stop."""
    return bool(session.scalar(select(Job.cancel_requested).where(Job.id == job_id)))


# The task that runs a job -----------------------------------------------------------------------------------------


def claim_job(session: Session, job_id: uuid.UUID, lease: str, worker: str, stale_before: datetime) -> Job | None:
    """Take a job for this task: a queued job, a re-delivery of our own task, or a running job gone silent.

    Returns the job (now ``running`` under ``lease``), or None when it is not ours to run: finished, canceled,
    running under a live worker, or fanned out into tiles (its tiles' tasks run it).
    """
    return JOBS.claim(session, job_id, lease, worker, stale_before)


def update_running(session: Session, job_id: uuid.UUID, lease: str, **values: Any) -> bool:
    """Write progress fields of a running job we hold; False once the lease is lost or the job left running."""
    held = JOBS.beat(session, job_id, lease, **values)
    session.commit()
    return held


def release_job(session: Session, job_id: uuid.UUID, lease: str, **values: Any) -> bool:
    """Hand a running job we hold back to the queue (worker shutdown); this claim does not count as an attempt."""
    return JOBS.release(session, job_id, lease, **values)


def record_results(
    session: Session, job_id: uuid.UUID, lease: str, artifacts: Sequence[Artifact], **values: Any
) -> bool:
    """The results of a running job we hold are ready: ``results_at``, the fit running, and the results' artifact
    rows (replacing any from an earlier attempt), in one transaction; False once the lease is lost."""
    now = utcnow()
    results_at = func.coalesce(Job.results_at, now)
    fit = {"fit_state": FitState.RUNNING, "fit_progress": 0.0, "fit_error": None}
    if not JOBS.beat(session, job_id, lease, now, results_at=results_at, **fit, **values):
        session.rollback()
        return False
    replace_artifacts(session, job_id, artifacts)
    session.commit()
    return True


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
    if state != JobState.SUCCEEDED and "fit_state" not in values:
        values["fit_state"] = fit_ended(FitState.CANCELED if state == JobState.CANCELED else FitState.FAILED)
    now = utcnow()
    if not JOBS.beat(session, job_id, lease, now, state=state, finished_at=now, **values):
        session.rollback()
        return False
    if artifacts or state == JobState.SUCCEEDED:  # a job that ends otherwise keeps the rows of its results
        replace_artifacts(session, job_id, artifacts)
    session.commit()
    return True


def replace_artifacts(session: Session, job_id: uuid.UUID, artifacts: Sequence[Artifact]) -> None:
    """The job's artifact rows become ``artifacts`` (a re-run overwrites); not committed."""
    for old in session.scalars(select(Artifact).where(Artifact.job_id == job_id)):
        session.delete(old)
    session.flush()
    session.add_all(artifacts)


def fit_ended(state: FitState) -> Any:
    """``fit_state`` as a job that ends now leaves it: a fit still running takes ``state``, any other stays."""
    return case(
        (Job.fit_state == FitState.RUNNING, literal(state, Job.__table__.c.fit_state.type)), else_=Job.fit_state
    )
