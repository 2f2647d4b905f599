"""``/v1/scenes``: scenes made from complete uploads, validated by the core validator."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Query, Response, status

from service import scenes
from service.api.deps import SceneDep, SessionDep, SettingsDep, StorageDep, TenantDep
from service.db import crud
from service.db.models import Scene, Upload
from service.errors import NotFound
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
    response: Response,
) -> Scene:
    """Validate a complete upload and make it a scene; a bad bundle is refused with every problem listed."""
    upload = crud.get_owned(session, Upload, body.upload_id, tenant.id)
    if upload is None:
        raise NotFound("upload", body.upload_id)
    scene = scenes.create_scene(session, storage, upload, body.name, max_bytes=settings.bundle_max_bytes)
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
