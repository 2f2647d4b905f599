"""``/v1/jobs/{id}/instances`` and ``/v1/jobs/{id}/query``: a finished job's instances, listed and ranked against a
query."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool

from service import job_results
from service.api.deps import SettingsDep, StorageDep, TenantDep
from service.db.session import get_read_engine
from service.schemas import InstancesPublic, QueryCreate, QueryResult, error_responses

router = APIRouter(prefix="/jobs/{job_id}", tags=["results"])
_ERRORS = error_responses(404, 409)


@router.get("/instances", response_model=InstancesPublic, responses=_ERRORS)
async def list_instances(
    job_id: uuid.UUID, request: Request, tenant: TenantDep, settings: SettingsDep, storage: StorageDep
) -> Response:
    """Every instance with its class, score and axis-aligned box."""
    engine = get_read_engine(settings.database)
    loaded = await run_in_threadpool(
        job_results.finished, engine, request.app.state.results, storage, job_id, tenant.id
    )
    return Response(loaded.instances_body, media_type="application/json")


@router.post("/query", response_model=QueryResult, responses=_ERRORS)
async def query(
    job_id: uuid.UUID,
    body: QueryCreate,
    request: Request,
    tenant: TenantDep,
    settings: SettingsDep,
    storage: StorageDep,
) -> Response:
    """Rank the job's instances against a class name, free text or a ``(D,)`` vector; best first.

    A class name or a vector needs no text encoder; free text is encoded in the API's encoder process,
    started on the first such query and warm after it (``PANOGS_QUERY_ENCODER=off`` refuses free text).
    """
    encoder = request.app.state.encoder if settings.query_encoder == "process" else None
    engine = get_read_engine(settings.database)
    cache = request.app.state.results
    answer = await run_in_threadpool(job_results.answer_query, engine, cache, storage, job_id, tenant.id, body, encoder)
    return Response(answer.model_dump_json(), media_type="application/json")
