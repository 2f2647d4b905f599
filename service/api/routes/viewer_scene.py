"""``/v1/jobs/{id}/viewer-scene``: a finished job's primitives in the viewer's binary layout."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool

from service import job_results
from service.api.deps import SettingsDep, StorageDep, TenantDep
from service.db.session import get_read_engine
from service.schemas import error_responses

router = APIRouter(prefix="/jobs/{job_id}", tags=["results"])
_ERRORS = error_responses(404, 409)


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
    await run_in_threadpool(job_results.finished, engine, request.app.state.results, storage, job_id, tenant.id)
    scene = await run_in_threadpool(build_scene, storage.job_dir(job_id), extra={"title": f"job {job_id}"})
    return Response(
        scene.data, media_type="application/octet-stream", headers={"Cache-Control": "private, max-age=3600"}
    )
