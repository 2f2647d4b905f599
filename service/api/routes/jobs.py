"""``/v1/jobs``: create (202, idempotent), list, get, cancel."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request, Response, status
from fastapi.concurrency import run_in_threadpool

from service import jobs, lifecycle
from service.api.deps import FactoryDep, JobDep, SessionDep, SettingsDep, StorageDep, TenantDep, forget_job
from service.cache import TTLCache
from service.db import crud
from service.db.models import Job, JobState
from service.db.session import get_read_engine
from service.errors import Conflict
from service.queue import dispatch
from service.schemas import MAX_OFFSET, JobCreate, JobPublic, JobsPublic, Page, error_responses

router = APIRouter(prefix="/jobs", tags=["jobs"])
_ERRORS = error_responses(404, 409)


@router.post("", status_code=status.HTTP_202_ACCEPTED, response_model=JobPublic, responses=_ERRORS)
def create_job(
    body: JobCreate,
    request: Request,
    response: Response,
    session: SessionDep,
    factory: FactoryDep,
    tenant: TenantDep,
    settings: SettingsDep,
    idempotency_key: Annotated[
        str | None,
        Header(alias="Idempotency-Key", min_length=1, max_length=255, description="a retry returns the same job"),
    ] = None,
) -> JobPublic:
    """Queue a pipeline run on a scene. Poll ``GET /v1/jobs/{id}`` for its progress."""
    job, created = jobs.create_job(session, settings, tenant.id, body, idempotency_key)
    if created:  # enqueue only after the commit, by task name
        dispatch(factory, request.app.state.sender, job.id, job.queue)
        session.refresh(job)
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return jobs.to_public(job)


@router.get("", response_model=JobsPublic, responses=_ERRORS)
def list_jobs(
    session: SessionDep,
    tenant: TenantDep,
    state: JobState | None = None,
    scene_id: uuid.UUID | None = None,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
) -> JobsPublic:
    """The caller's jobs, newest first, optionally only those in ``state`` or on ``scene_id``."""
    filters = []
    if state is not None:
        filters.append(Job.state == state)
    if scene_id is not None:
        filters.append(Job.scene_id == scene_id)
    rows, count = crud.list_owned(session, Job, tenant.id, filters=filters, limit=limit, offset=offset)
    tiles = crud.tile_rows(session, [r.id for r in rows])
    data = [jobs.to_public(r, tiles.get(r.id, [])) for r in rows]
    return JobsPublic(data=data, count=count, page=Page(limit=limit, offset=offset))


@router.get("/{job_id}", response_model=JobPublic, responses=_ERRORS)
async def get_job(job_id: uuid.UUID, request: Request, tenant: TenantDep, settings: SettingsDep) -> Response:
    """A job's state, stage, progress, per-stage timings and error.

    The status-poll path: the answer is kept ``status_cache_s`` (0.2 s) per process, less than the worker's
    progress interval; otherwise one threadpool hop for one autocommit SELECT, serialised once.
    """
    cache: TTLCache[tuple[uuid.UUID, uuid.UUID], bytes] = request.app.state.status_cache
    hit, body = cache.get((tenant.id, job_id))
    if not hit:
        engine = get_read_engine(settings.database)
        body = (await run_in_threadpool(jobs.read_public, engine, job_id, tenant.id)).model_dump_json().encode()
        cache.put((tenant.id, job_id), body)
    return Response(body, media_type="application/json")


@router.post("/{job_id}/cancel", status_code=status.HTTP_202_ACCEPTED, response_model=JobPublic, responses=_ERRORS)
def cancel_job(job: JobDep, session: SessionDep, request: Request) -> JobPublic:
    """Cancel a job: a queued one at once, a running one at its next progress step (``cancel_requested``)."""
    if job.state in (JobState.SUCCEEDED, JobState.FAILED):
        raise Conflict(f"job {job.id} already {job.state.value}")
    forget_job(request, job.api_key_id, job.id)
    canceled = crud.request_cancel(session, job)
    return jobs.to_public(canceled, crud.tile_rows(session, [job.id]).get(job.id, []))


@router.delete("/{job_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses())
def delete_job(
    job_id: uuid.UUID, session: SessionDep, tenant: TenantDep, storage: StorageDep, request: Request
) -> Response:
    """Delete a job, its results and its files; a queued or running job is cancelled first.

    Safe to retry: a job that is not there (already deleted, or never this tenant's) answers 204 as well, and
    nothing is touched.
    """
    job = crud.get_owned(session, Job, job_id, tenant.id)
    if job is not None:
        lifecycle.delete_job(session, storage, job)
        forget_job(request, tenant.id, job_id)
    return Response(status_code=204)
