"""``/v1/jobs/{id}/...``: a finished job's instances, downloads (with HTTP Range) and queries."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from panogs_core.io.run_folder import DOWNLOADABLE
from service import results
from service.api.deps import JobDep, SettingsDep, StorageDep, TenantDep
from service.db.models import Job, JobState
from service.db.session import get_read_engine
from service.errors import Conflict, NotFound
from service.schemas import (
    ArtifactPublic,
    ArtifactsPublic,
    InstancesPublic,
    QueryCreate,
    QueryResult,
    error_responses,
)

router = APIRouter(prefix="/jobs/{job_id}", tags=["results"])
_ERRORS = error_responses(404, 409)


def _finished(job: Job) -> Job:
    if job.state != JobState.SUCCEEDED:
        raise Conflict(f"job {job.id} is {job.state.value}; results exist once it has succeeded")
    return job


@router.get("/instances", response_model=InstancesPublic, responses=_ERRORS)
async def list_instances(
    job_id: uuid.UUID, request: Request, tenant: TenantDep, settings: SettingsDep, storage: StorageDep
) -> Response:
    """Every instance with its class, score and axis-aligned box."""
    engine = get_read_engine(settings.database)
    loaded = await run_in_threadpool(results.finished, engine, request.app.state.results, storage, job_id, tenant.id)
    return Response(loaded.instances_body, media_type="application/json")


@router.get("/artifacts", response_model=ArtifactsPublic, responses=_ERRORS)
def list_artifacts(job: JobDep) -> ArtifactsPublic:
    """The job's downloadable files."""
    data = [
        ArtifactPublic(
            name=a.name,
            size_bytes=a.size_bytes,
            sha256=a.sha256,
            media_type=DOWNLOADABLE[a.name].media_type,
            url=f"/v1/jobs/{job.id}/artifacts/{a.name}",
        )
        for a in _finished(job).artifacts
        if a.name in DOWNLOADABLE  # a row the declaration no longer serves is neither listed nor served
    ]
    return ArtifactsPublic(data=data, count=len(data))


@router.get(
    "/artifacts/{name}",
    response_class=FileResponse,
    responses={
        **_ERRORS,
        200: {"content": {"application/octet-stream": {}}},
        206: {"description": "a byte range"},
    },
)
def download_artifact(job: JobDep, name: str, storage: StorageDep) -> FileResponse:
    """Download one file of ``panogs_core.io.run_folder.DOWNLOADABLE`` (``panoptic.ply``, ``gaussians.ply`` ...).

    Supports ``Range: bytes=start-end`` (206) to resume an interrupted download.
    """
    artifact = next((a for a in _finished(job).artifacts if a.name == name), None)
    if artifact is None or name not in DOWNLOADABLE:
        raise NotFound("artifact", name)
    return FileResponse(
        storage.path(artifact.path),
        media_type=DOWNLOADABLE[name].media_type,
        filename=artifact.name,
        headers={"ETag": f'"{artifact.sha256}"', "Cache-Control": "private, max-age=3600"},
    )


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
    answer = await run_in_threadpool(results.answer_query, engine, cache, storage, job_id, tenant.id, body, encoder)
    return Response(answer.model_dump_json(), media_type="application/json")


@router.get(
    "/viewer-scene",
    response_class=Response,
    responses={**_ERRORS, 200: {"content": {"application/octet-stream": {}}}},
)
async def viewer_scene(
    job_id: uuid.UUID, request: Request, tenant: TenantDep, settings: SettingsDep, storage: StorageDep
) -> Response:
    """The finished job's primitives for the viewer: a JSON header and typed arrays (``service/viewer/scene.py``
    documents the layout): positions, camera colours, class and instance labels, scales."""
    from service.viewer.scene import build_scene

    engine = get_read_engine(settings.database)
    await run_in_threadpool(results.finished, engine, request.app.state.results, storage, job_id, tenant.id)
    scene = await run_in_threadpool(build_scene, storage.job_dir(job_id), extra={"title": f"job {job_id}"})
    return Response(
        scene.data, media_type="application/octet-stream", headers={"Cache-Control": "private, max-age=3600"}
    )
