"""``/v1/map-models``: the operator's 2D models a job may name, by entry name and kind (never their folders)."""

from __future__ import annotations

from fastapi import APIRouter

from service.api.deps import SettingsDep, TenantDep
from service.schemas import MapModelsPublic, error_responses

router = APIRouter(prefix="/map-models", tags=["jobs"])


@router.get("", response_model=MapModelsPublic, responses=error_responses())
async def list_map_models(tenant: TenantDep, settings: SettingsDep) -> MapModelsPublic:
    """The entries of ``PANOGS_MAP_MODELS`` per kind: what ``maps`` of ``POST /v1/jobs`` may name (the app's upload
    form offers them for a bundle without its own maps). Read from the settings; no folder is opened."""
    del tenant  # signed in: a key or the app's session
    return MapModelsPublic(masks=settings.map_model_names("masks"), features=settings.map_model_names("features"))
