"""Every response carries the security headers: API answers, app pages, assets, errors, 404s,
the body limit's 413 and an unexpected 500; the app and the OpenAPI pages get the CSP they work with."""

from __future__ import annotations

import httpx
import pytest
from fastapi.testclient import TestClient

from service.security_headers import API_CSP, APP_CSP, DOCS_CSP
from service.viewer.assets import STATIC_DIR

STRICT = {"x-frame-options": "DENY", "x-content-type-options": "nosniff", "referrer-policy": "no-referrer"}


def assert_secured(response: httpx.Response, csp: str = API_CSP) -> None:
    for name, value in STRICT.items():
        assert response.headers.get(name) == value, (response.request.url, name, dict(response.headers))
    assert response.headers.get("content-security-policy") == csp
    assert "frame-ancestors 'none'" in response.headers["content-security-policy"]


def test_api_answers_and_errors_carry_the_headers(client: TestClient, auth: dict[str, str]) -> None:
    assert_secured(client.get("/healthz"))
    assert_secured(client.get("/openapi.json"))
    assert_secured(client.get("/v1/scenes", headers=auth))
    assert_secured(client.get("/v1/scenes"))  # 401
    assert_secured(client.get("/v1/scenes/not-a-uuid", headers=auth))  # 422
    assert_secured(client.get("/no/such/route"))  # 404
    assert_secured(client.post("/v1/jobs", content=b"x" * (2 * 1024 * 1024), headers=auth))  # the body limit's 413
    assert_secured(client.options("/v1/uploads"))


def test_an_unexpected_500_carries_the_headers(client: TestClient) -> None:
    def broken() -> None:
        raise RuntimeError("a bug")

    client.app.add_api_route("/broken", broken)  # type: ignore[attr-defined]
    with TestClient(client.app, raise_server_exceptions=False) as plain:
        r = plain.get("/broken")
    assert r.status_code == 500
    assert_secured(r)


@pytest.mark.skipif(not (STATIC_DIR / "index.html").is_file(), reason="the web app is not built (make web)")
def test_the_app_and_its_assets_carry_the_headers(client: TestClient) -> None:
    page = client.get("/app")
    assert page.status_code == 200
    assert_secured(page, APP_CSP)
    assert_secured(client.get("/app/static/app.js"))
    assert_secured(client.get("/app/static/missing.js"))  # 404
    assert_secured(client.get("/", follow_redirects=False))  # the redirect to /app


def test_the_openapi_pages_get_the_policy_of_their_cdn(client: TestClient) -> None:
    for path in ("/docs", "/redoc"):
        r = client.get(path)
        assert r.status_code == 200
        assert_secured(r, DOCS_CSP)
        for source in ("https://cdn.jsdelivr.net",):  # where FastAPI's pages load Swagger UI and ReDoc from
            assert source in r.text
