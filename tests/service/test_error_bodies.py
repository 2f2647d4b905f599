"""No response body carries a traceback or a host path: the error handlers cut every path under
the storage folder to its part below it, write ``<path>`` for any other absolute path, and replace a message that
holds a traceback by one naming a request id, whichever route and handler answered."""

from __future__ import annotations

import io
import logging
import zipfile
from pathlib import Path

import pytest
from fastapi import FastAPI, HTTPException
from fastapi.testclient import TestClient
from svc_helpers import upload_bytes, write_tiny_bundle

from service.errors import InvalidInput, install_error_handlers, sanitize_message
from service.settings import Settings

TRACEBACK = 'Traceback (most recent call last):\n  File "/srv/panogs/service/x.py", line 3, in f\nValueError: boom'


def test_paths_are_cut_below_the_roots_and_redacted_elsewhere() -> None:
    roots = [Path("/data/storage")]
    text = "bad /data/storage/scenes/1/bundle/a.png and '/etc/passwd' and /home/u/x; see /v1/jobs/3/query"
    assert sanitize_message(text, roots) == "bad scenes/1/bundle/a.png and '<path>' and <path>; see /v1/jobs/3/query"
    # Not paths: relative names, URLs, ratios.
    kept = "frames/0001.png of http://127.0.0.1:8000/v1/uploads at 3/4 of 640x480"
    assert sanitize_message(kept, roots) == kept


def _route_app(settings: Settings, raise_it: Exception) -> TestClient:
    app = FastAPI()
    app.state.settings = settings
    install_error_handlers(app)

    @app.get("/boom")
    def boom() -> None:
        raise raise_it

    return TestClient(app, raise_server_exceptions=False)


@pytest.mark.parametrize(
    "error",
    [
        InvalidInput(f"refused: {TRACEBACK}"),
        InvalidInput("bad file", problems=["ok", TRACEBACK]),
        HTTPException(400, detail=TRACEBACK),
    ],
)
def test_a_route_error_with_a_traceback_answers_a_request_id(
    error: Exception, caplog: pytest.LogCaptureFixture, tmp_path: Path
) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path / "data")  # type: ignore[call-arg]
    with caplog.at_level(logging.ERROR, logger="service.errors"):
        r = _route_app(settings, error).get("/boom")
    assert r.status_code in (400, 422)
    assert "Traceback" not in r.text
    assert "line 3" not in r.text
    assert "/srv" not in r.text
    assert "request " in r.json()["message"]
    request_id = r.json()["message"].split("request ")[1].split(")")[0]
    assert any(request_id in rec.getMessage() and "Traceback" in rec.getMessage() for rec in caplog.records)


def test_a_route_error_naming_host_paths_names_them_relative(tmp_path: Path) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path / "data")  # type: ignore[call-arg]
    stored = settings.data_dir.resolve() / "storage" / "scenes" / "x" / "a.png"
    r = _route_app(settings, InvalidInput(f"{stored}: unreadable", problems=["/usr/lib/secret.so: missing"])).get(
        "/boom"
    )
    assert r.status_code == 422
    assert r.json()["message"] == "scenes/x/a.png: unreadable"
    assert r.json()["problems"] == ["<path>: missing"]
    assert str(tmp_path) not in r.text


def test_a_bundle_refusal_names_no_host_path(client: TestClient, auth: dict[str, str], settings: Settings,
                                             tmp_path: Path) -> None:  # fmt: skip
    """A real route: an archive member with a name too long for the disk (its 422 once showed the storage path)."""
    folder = write_tiny_bundle(tmp_path / "bundle")
    data = io.BytesIO()
    with zipfile.ZipFile(data, "w") as zf:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                zf.write(path, path.relative_to(folder).as_posix())
        zf.writestr("frames/" + "n" * 300 + ".png", b"x")
    upload = upload_bytes(client, auth, data.getvalue(), filename="long.zip")
    r = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
    assert 400 <= r.status_code < 500, r.text
    assert str(settings.storage) not in r.text
    assert str(tmp_path) not in r.text
    assert "Traceback" not in r.text


@pytest.mark.parametrize(
    ("method", "path", "allow"),
    [
        ("PUT", "/v1/jobs", "GET, POST"),
        ("DELETE", "/v1/scenes", "GET, POST"),
        ("PATCH", "/v1/jobs/00000000-0000-0000-0000-000000000000", "DELETE, GET"),
        ("PUT", "/v1/uploads", "OPTIONS, POST"),
    ],
)
def test_a_405_allows_every_method_of_the_path(client: TestClient, method: str, path: str, allow: str) -> None:
    # Starlette names only the first matching route's methods (PUT /v1/jobs said "Allow: POST").
    response = client.request(method, path)
    assert response.status_code == 405
    assert response.headers["Allow"] == allow
    assert response.json()["type"] == "method_not_allowed"
