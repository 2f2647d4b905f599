"""``/v1/scenes``: scenes made from complete uploads, validated by the core validator."""

from __future__ import annotations

import uuid
from typing import Annotated

from fastapi import APIRouter, Query, Request, Response, status

from service import lifecycle, scenes
from service.api.deps import SceneDep, SessionDep, SettingsDep, StorageDep, TenantDep, forget_job
from service.db import crud
from service.db.models import Scene, Upload
from service.errors import InvalidBundle, NotFound
from service.schemas import MAX_OFFSET, Page, SceneCreate, ScenePublic, ScenesPublic, error_responses

router = APIRouter(prefix="/scenes", tags=["scenes"])
_ERRORS = error_responses(404, 409)


@router.post("", status_code=status.HTTP_201_CREATED, response_model=ScenePublic, responses=_ERRORS)
def create_scene(
    body: SceneCreate,
    session: SessionDep,
    tenant: TenantDep,
    storage: StorageDep,
    settings: SettingsDep,
    request: Request,
    response: Response,
) -> Scene:
    """Validate a complete upload and make it a scene; a bad bundle is refused with every problem listed."""
    upload = crud.get_owned(session, Upload, body.upload_id, tenant.id)
    if upload is None:
        raise NotFound("upload", body.upload_id)
    # An archive may expand only as far as the tenant's quota and the free disk allow, not to the bundle limit.
    # The upload stops counting once its scene exists: its bytes are room for the scene (counted once).
    limit, reason = lifecycle.extraction_limit(session, settings, storage, tenant.id, releasing=upload.length)
    try:
        opener = request.app.state.bundle_opener
        scene = scenes.create_scene(session, storage, upload, body.name, opener, max_bytes=limit, settings=settings)
    except InvalidBundle as exc:
        if any("exceeds the limit" in p for p in exc.problems or []):
            exc.problems = [*(exc.problems or []), f"the extraction limit of {limit:,} bytes is set by {reason}"]
        raise
    response.headers["Location"] = f"/v1/scenes/{scene.id}"
    return scene


@router.get("", response_model=ScenesPublic, responses=_ERRORS)
def list_scenes(
    session: SessionDep,
    tenant: TenantDep,
    limit: Annotated[int, Query(ge=1, le=200)] = 50,
    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
) -> ScenesPublic:
    """The caller's scenes, newest first."""
    rows, count = crud.list_owned(session, Scene, tenant.id, limit=limit, offset=offset)
    return ScenesPublic(
        data=[ScenePublic.model_validate(r) for r in rows], count=count, page=Page(limit=limit, offset=offset)
    )


@router.get("/{scene_id}", response_model=ScenePublic, responses=_ERRORS)
def get_scene(scene: SceneDep) -> Scene:
    """One scene."""
    return scene


@router.delete("/{scene_id}", status_code=status.HTTP_204_NO_CONTENT, responses=error_responses())
def delete_scene(
    scene_id: uuid.UUID, session: SessionDep, tenant: TenantDep, storage: StorageDep, request: Request
) -> Response:
    """Delete a scene, every job on it (running ones are cancelled first) and their files.

    Safe to retry: a scene that is not there (already deleted, or never this tenant's) answers 204 as well, and
    nothing is touched.
    """
    scene = crud.get_owned(session, Scene, scene_id, tenant.id)
    if scene is not None:
        for job_id in lifecycle.delete_scene(session, storage, scene):
            forget_job(request, tenant.id, job_id)
    return Response(status_code=204)
