"""The app's sign-in: an API key exchanged for an HttpOnly SameSite session cookie that the /v1 routes accept;
cookie writes need the app's header; sign-out and key revocation end the session. And the app's pages."""

from __future__ import annotations

from fastapi.testclient import TestClient
from svc_helpers import BOTH_BACKENDS, make_scene

from service.auth import revoke_api_key
from service.db.session import get_session_factory, session_scope
from service.settings import Settings
from service.web_app_sessions import APP_HEADER, COOKIE_NAME

APP = {APP_HEADER: "1"}


def _key(auth: dict[str, str]) -> str:
    return auth["Authorization"].removeprefix("Bearer ")


def _sign_in(client: TestClient, auth: dict[str, str]) -> None:
    response = client.post("/app/session", json={"key": _key(auth)})
    assert response.status_code == 204, response.text
    cookie = response.headers["set-cookie"]
    assert cookie.startswith(f"{COOKIE_NAME}=")
    assert "HttpOnly" in cookie
    assert "SameSite=strict" in cookie
    assert _key(auth) not in cookie  # the long-lived key never travels back


@BOTH_BACKENDS
def test_cookie_signs_in_and_sees_only_the_tenants_data(
    client: TestClient, auth: dict[str, str], other_auth: dict[str, str], tiny_zip: bytes
) -> None:
    mine = make_scene(client, auth, tiny_zip)
    theirs = make_scene(client, other_auth, tiny_zip)
    _sign_in(client, auth)
    assert client.get("/app/session").json()["tenant"] == "alice"
    assert client.get(f"/v1/scenes/{mine['id']}").status_code == 200
    assert client.get(f"/v1/scenes/{theirs['id']}").status_code == 404
    job = client.post("/v1/jobs", json={"scene_id": mine["id"]}, headers=APP)
    assert job.status_code == 202, job.text


def test_cookie_write_without_the_app_header_is_refused(
    client: TestClient, auth: dict[str, str], tiny_zip: bytes
) -> None:
    scene = make_scene(client, auth, tiny_zip)
    _sign_in(client, auth)
    response = client.post("/v1/jobs", json={"scene_id": scene["id"]})
    assert response.status_code == 403
    assert APP_HEADER in response.json()["message"]


def test_bad_key_gets_no_cookie(client: TestClient) -> None:
    response = client.post("/app/session", json={"key": "pgs_000000000000_" + "x" * 43})
    assert response.status_code == 401
    assert "set-cookie" not in response.headers
    assert client.get("/app/session").status_code == 401


def test_sign_out_and_revocation_end_the_session(client: TestClient, auth: dict[str, str], settings: Settings) -> None:
    _sign_in(client, auth)
    token = client.cookies[COOKIE_NAME]
    assert client.delete("/app/session").status_code == 204
    client.cookies.set(COOKIE_NAME, token)  # a copy of the old cookie is worthless now
    assert client.get("/v1/scenes").status_code == 401
    client.cookies.clear()
    _sign_in(client, auth)
    assert client.get("/v1/scenes").status_code == 200
    with session_scope(get_session_factory(settings.database)) as session:
        revoke_api_key(session, _key(auth).split("_")[1])
    assert client.get("/v1/scenes").status_code == 401


def test_app_pages_are_served(client: TestClient) -> None:
    assert client.get("/", follow_redirects=False).headers["location"] == "/app"
    page = client.get("/app")
    assert page.status_code == 200
    assert "/app/static/app.js" in page.text
    assert client.get("/app/static/app.js").status_code == 200
    assert client.get("/app/static/..%2Fsettings.py").status_code == 404
    assert "cdn" not in page.text.lower()
    assert "https://" not in page.text
