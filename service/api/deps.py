"""Dependencies as ``Annotated`` aliases: settings, session, storage, the calling tenant, get-or-404
lookups."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from typing import Annotated, Any

from fastapi import Depends, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session, sessionmaker

from service.auth import KeyVerifier, Tenant
from service.db import crud
from service.db.models import Job, Scene, Upload
from service.db.session import session_scope
from service.errors import Forbidden, NotFound, Unauthorized
from service.settings import Settings
from service.storage import Storage
from service.web_app_sessions import APP_HEADER, COOKIE_NAME, SAFE_METHODS, session_tenant


# Plain attribute reads: async, so that FastAPI does not hop to its threadpool for them.
async def _settings(request: Request) -> Settings:
    return request.app.state.settings  # type: ignore[no-any-return]


async def _factory(request: Request) -> sessionmaker[Session]:
    return request.app.state.session_factory  # type: ignore[no-any-return]


async def _storage(request: Request) -> Storage:
    return request.app.state.storage  # type: ignore[no-any-return]


SettingsDep = Annotated[Settings, Depends(_settings)]
FactoryDep = Annotated[sessionmaker[Session], Depends(_factory)]
StorageDep = Annotated[Storage, Depends(_storage)]


def _session(factory: FactoryDep) -> Iterator[Session]:
    with session_scope(factory) as session:
        yield session


SessionDep = Annotated[Session, Depends(_session)]

_bearer = HTTPBearer(auto_error=False, description="An API key: `Authorization: Bearer pgs_...`")


async def _tenant(
    request: Request,
    factory: FactoryDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Tenant:
    # A key seen in the last api_key_cache_s seconds is answered from memory; otherwise one short session of
    # its own (streaming upload routes must not hold a connection for the whole body).
    if credentials is None:
        token = request.cookies.get(COOKIE_NAME)
        if token:
            return await _cookie_tenant(request, factory, token)
        raise Unauthorized("missing API key: send Authorization: Bearer <key>")
    verifier: KeyVerifier = request.app.state.key_verifier
    known, tenant = verifier.cached(credentials.credentials)
    if not known:
        tenant = await run_in_threadpool(_verify, factory, verifier, credentials.credentials)
    if tenant is None:
        raise Unauthorized("invalid or revoked API key")
    return tenant


async def _cookie_tenant(request: Request, factory: sessionmaker[Session], token: str) -> Tenant:
    """The app's signed-in tenant. A write must carry X-Panogs-App: a cross-site page cannot set that header, so
    a cookie alone never changes anything (defence in depth on top of SameSite=Strict)."""
    if request.method not in SAFE_METHODS and request.headers.get(APP_HEADER) != "1":
        raise Forbidden(f"a request signed in by cookie must send the header {APP_HEADER}: 1")
    found = await run_in_threadpool(_in_session, factory, session_tenant, token)
    if found is None:
        raise Unauthorized("the app session expired or was signed out; sign in again")
    return found[0]  # type: ignore[no-any-return]


def _in_session(factory: sessionmaker[Session], fn: Any, *args: Any) -> Any:
    with session_scope(factory) as session:
        return fn(session, *args)


def _verify(factory: sessionmaker[Session], verifier: KeyVerifier, key: str) -> Tenant | None:
    with session_scope(factory) as session:
        return verifier.verify(session, key)


TenantDep = Annotated[Tenant, Depends(_tenant)]


def _job(job_id: uuid.UUID, session: SessionDep, tenant: TenantDep) -> Job:
    job = crud.get_owned(session, Job, job_id, tenant.id)
    if job is None:
        raise NotFound("job", job_id)
    return job


def _scene(scene_id: uuid.UUID, session: SessionDep, tenant: TenantDep) -> Scene:
    scene = crud.get_owned(session, Scene, scene_id, tenant.id)
    if scene is None:
        raise NotFound("scene", scene_id)
    return scene


def _upload(upload_id: uuid.UUID, session: SessionDep, tenant: TenantDep) -> Upload:
    upload = crud.get_owned(session, Upload, upload_id, tenant.id)
    if upload is None:
        raise NotFound("upload", upload_id)
    return upload


JobDep = Annotated[Job, Depends(_job)]
SceneDep = Annotated[Scene, Depends(_scene)]
UploadDep = Annotated[Upload, Depends(_upload)]


def forget_job(request: Request, tenant_id: uuid.UUID, job_id: uuid.UUID) -> None:
    """Drop a job from the API's in-memory caches (its polled status, its loaded result) once it changed or went."""
    request.app.state.status_cache.drop((tenant_id, job_id))
    request.app.state.results.drop(job_id)
