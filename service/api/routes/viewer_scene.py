"""``/v1/jobs/{id}/viewer-scene``: a job's primitives in the viewer's binary layout, once its results are ready
(before its appearance fit ends: the colours are then the initialisation's, and the answer is not cached)."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool

from service import job_results
from service.api.deps import SettingsDep, StorageDep, TenantDep
from service.db.session import get_read_engine
from service.errors import FitNotReady
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
    try:
        await run_in_threadpool(job_results.fitted_scene, engine, job_id, tenant.id)
        final = True
    except FitNotReady:
        final = False  # the colours are the initialisation's until the fit replaces gaussians.ply: not cached
    scene = await run_in_threadpool(build_scene, storage.run_folder(job_id), extra={"title": f"job {job_id}"})
    cache = "private, max-age=3600" if final else "private, no-cache"
    return Response(scene.data, media_type="application/octet-stream", headers={"Cache-Control": cache})
