"""The browser app: its pages and assets under ``/app``, and sign-in (``/app/session``).

``POST /app/session`` takes ``{"key": "pgs_..."}`` in the body (never in a URL), checks it like a bearer key and
answers with an HttpOnly, SameSite=Strict session cookie (Secure over HTTPS) that the ``/v1`` routes accept in
place of the key (:mod:`service.web_app_sessions`). The key itself is not kept by the browser.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Cookie, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, RedirectResponse
from pydantic import BaseModel, ConfigDict, Field

from service import web_app_sessions
from service.api.deps import FactoryDep, SettingsDep
from service.db.session import session_scope
from service.errors import NotFound, ServiceUnavailable, Unauthorized
from service.schemas import error_responses

router = APIRouter(tags=["app"])


class SessionCreate(BaseModel):
    """Sign in with an API key."""

    model_config = ConfigDict(extra="forbid")
    key: str = Field(min_length=1, max_length=200)


class SessionPublic(BaseModel):
    """Who is signed in, until when."""

    tenant: str
    expires_at: str


def _static() -> Path:
    from panogs_core.errors import InputError
    from service.viewer.assets import static_dir

    try:
        return static_dir()
    except InputError as exc:
        raise ServiceUnavailable(str(exc)) from exc


@router.get("/", include_in_schema=False)
def root() -> RedirectResponse:
    """The app is the service's front page."""
    return RedirectResponse("/app", status_code=307)


@router.get("/app", include_in_schema=False)
def app_page() -> FileResponse:
    """The app's one page (routes live in the URL fragment)."""
    folder = _static()
    return FileResponse(folder / "index.html", headers={"Cache-Control": "no-cache"})


@router.get("/app/static/{name}", include_in_schema=False)
def app_asset(name: str) -> FileResponse:
    """A built asset (app.js, viewer.js, app.css)."""
    folder = _static()
    path = folder / name
    if "/" in name or name.startswith(".") or not path.is_file():
        raise NotFound("asset", name)
    return FileResponse(path, headers={"Cache-Control": "no-cache"})


@router.post("/app/session", status_code=204, responses=error_responses(401))
async def sign_in(body: SessionCreate, request: Request, factory: FactoryDep, settings: SettingsDep) -> Response:
    """Exchange an API key for a session cookie of ``session_ttl_s`` seconds."""
    verifier = request.app.state.key_verifier

    def open_session() -> str | None:
        with session_scope(factory) as session:
            tenant = verifier.verify(session, body.key)
            if tenant is None:
                return None
            token, _ = web_app_sessions.open_session(session, tenant.id, settings.session_ttl_s)
            return token

    token = await run_in_threadpool(open_session)
    if token is None:
        raise Unauthorized("invalid or revoked API key")
    response = Response(status_code=204)
    response.set_cookie(
        web_app_sessions.COOKIE_NAME,
        token,
        max_age=settings.session_ttl_s,
        httponly=True,
        samesite="strict",
        secure=request.url.scheme == "https",
        path="/",
    )
    return response


Token = Annotated[str | None, Cookie(alias=web_app_sessions.COOKIE_NAME, include_in_schema=False)]


@router.get("/app/session", response_model=SessionPublic, responses=error_responses(401))
async def whoami(factory: FactoryDep, token: Token = None) -> SessionPublic:
    """The signed-in tenant (401 when not signed in)."""
    if not token:
        raise Unauthorized("not signed in")

    def look_up() -> SessionPublic | None:
        with session_scope(factory) as session:
            found = web_app_sessions.session_tenant(session, token)
            if found is None:
                return None
            tenant, row = found
            return SessionPublic(tenant=tenant.name, expires_at=row.expires_at.isoformat())

    answer = await run_in_threadpool(look_up)
    if answer is None:
        raise Unauthorized("the app session expired or was signed out; sign in again")
    return answer


@router.delete("/app/session", status_code=204)
async def sign_out(factory: FactoryDep, token: Token = None) -> Response:
    """Sign out: the session is deleted and the cookie cleared."""
    if token:

        def close() -> None:
            with session_scope(factory) as session:
                web_app_sessions.close_session(session, token)

        await run_in_threadpool(close)
    response = Response(status_code=204)
    response.delete_cookie(web_app_sessions.COOKIE_NAME, path="/", httponly=True, samesite="strict")
    return response
