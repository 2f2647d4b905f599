"""``/healthz`` (the process answers) and ``/readyz`` (the database and the broker answer). No API key."""

from __future__ import annotations

from fastapi import APIRouter, Response
from sqlalchemy import text

from service.api.deps import FactoryDep, SettingsDep
from service.broker import broker_ping
from service.schemas import Health

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> Health:
    """The process is up."""
    return Health(status="ok")


@router.get("/readyz", response_model=Health, responses={503: {"model": Health}})
def readyz(factory: FactoryDep, settings: SettingsDep, response: Response) -> Health:
    """The database and the broker are reachable (503 otherwise, naming which is not)."""
    checks = {"database": "ok", "broker": "ok"}
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
