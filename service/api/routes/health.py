"""``/healthz`` (the process answers) and ``/readyz`` (the database, the broker and the storage answer). No API
key."""

from __future__ import annotations

from fastapi import APIRouter, Request, Response
from sqlalchemy import text

from service.api.deps import FactoryDep, SettingsDep, StorageDep
from service.broker import broker_ping
from service.schemas import Health
from service.settings import Settings
from service.storage import Storage
from service.storage.probe import StorageProbe, read_probe_object

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
async def healthz() -> Health:
    """The process is up.

    Answered on the event loop itself, never waiting for one of the request threads: those may all be busy (bundles
    being validated, slow uploads), which is not the process being down."""
    return Health(status="ok")


@router.get("/readyz", response_model=Health, responses={503: {"model": Health}})
def readyz(
    request: Request, factory: FactoryDep, settings: SettingsDep, storage: StorageDep, response: Response
) -> Health:
    """The database, the broker and the storage are reachable (503 otherwise, naming which is not); the storage's
    answer may be ``PANOGS_STORAGE_PROBE_CACHE_S`` old."""
    checks = {"database": "ok", "broker": "ok", "storage": storage_probe(request, settings, storage).status()}
    try:
        with factory() as session:
            session.execute(text("SELECT 1"))
    except Exception as exc:  # any failure means not ready; the reason goes into the answer
        checks["database"] = f"unavailable: {type(exc).__name__}"
    try:
        broker_ping(settings)
    except Exception as exc:  # as above
        checks["broker"] = f"unavailable: {type(exc).__name__}"
    ready = all(v == "ok" for v in checks.values())
    response.status_code = 200 if ready else 503
    return Health(status="ok" if ready else "unavailable", checks=checks)


def storage_probe(request: Request, settings: Settings, storage: Storage) -> StorageProbe:
    """The app's one storage probe, made on the first readiness check."""
    probe: StorageProbe | None = getattr(request.app.state, "storage_probe", None)
    if probe is None:
        probe = StorageProbe(
            lambda: read_probe_object(storage.objects),
            timeout_s=settings.storage_probe_timeout_s,
            cache_s=settings.storage_probe_cache_s,
        )
        request.app.state.storage_probe = probe
    return probe
