"""``POST /v1/jobs/{id}/render``: a PNG of a job's Gaussian scene seen from the pose in the body, once its appearance
fit is done (409 ``fit_not_ready`` with the fit's progress until then)."""

from __future__ import annotations

import uuid

from fastapi import APIRouter, Request, Response
from fastapi.concurrency import run_in_threadpool

from service import job_results, render_child
from service.api.deps import SettingsDep, StorageDep, TenantDep
from service.db.session import get_read_engine
from service.schemas import error_responses

router = APIRouter(prefix="/jobs/{job_id}", tags=["results"])
RENDER_SLOTS = render_child.RenderSlots()  # renders in flight, per tenant, in this API process


@router.post(
    "/render",
    response_class=Response,
    responses={**error_responses(404, 409, 422, 429, 503), 200: {"content": {"image/png": {}}}},
)
async def render(
    job_id: uuid.UUID,
    body: render_child.RenderCreate,
    request: Request,
    tenant: TenantDep,
    settings: SettingsDep,
    storage: StorageDep,
) -> Response:
    """One layer (colour, depth in mm as 16-bit PNG, semantic, instance, panoptic overlay, or a query's relevance)
    of the job's scene from ``T_world_cam``, at most ``MAX_RENDER_PIXELS`` pixels."""
    engine = get_read_engine(settings.database)
    # the tenant's job, its Gaussian scene fitted (404 / 409 otherwise; 409 fit_not_ready says how far the fit is)
    await run_in_threadpool(job_results.fitted_scene, engine, job_id, tenant.id)
    with RENDER_SLOTS.hold(tenant.id):
        png = await run_in_threadpool(render_child.render_layer, body, storage.run_folder(job_id))
    return Response(png, media_type="image/png")
