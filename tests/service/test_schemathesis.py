"""Property-based API tests from the OpenAPI schema (schemathesis): no input makes the server answer 5xx, and the
schema is true: answers, their headers and content types as it says, a 405 whose ``Allow`` lists the path's
methods, a missing required header refused, and (where the schema can state a route's rules) every request the
schema calls valid accepted."""

from __future__ import annotations

import atexit
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import schemathesis
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, settings
from pipeline_stand_in import stand_in
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    allow_header_conformance,
    content_type_conformance,
    missing_required_header,
    positive_data_acceptance,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
    unsupported_method,
)
from service_harness import SCRIPTED_PIPELINE
from sqlalchemy import text
from svc_helpers import RecordingSender, make_scene, new_key, pack, write_tiny_bundle

from service.api_app import create_app
from service.db.session import get_engine
from service.settings import Settings

CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
    response_headers_conformance,
    allow_header_conformance,
    unsupported_method,
    missing_required_header,
]
# Routes whose rules JSON Schema cannot state, so a schema-valid request may be refused: a job's config is checked
# against the pipeline's settings, its tiling by the planner and its maps against the operator's entries; a render's
# pose must be rigid and its focal lengths within a range of its size; a tus request's checksum must match the bytes
# it carries and its offset the upload's. Every other route is held to positive_data_acceptance.
RULES_BEYOND_THE_SCHEMA = {
    ("POST", "/v1/jobs"),
    ("POST", "/v1/jobs/{job_id}/render"),
    ("POST", "/v1/uploads"),
    ("PATCH", "/v1/uploads/{upload_id}"),
}


@pytest.fixture(scope="module")
def app_and_auth(pg_url: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[FastAPI, dict[str, str]]]:
    tmp = tmp_path_factory.mktemp("schemathesis")
    with get_engine(pg_url).begin() as conn:
        conn.execute(text("TRUNCATE artifact, job, scene, upload, api_key CASCADE"))
    settings_ = Settings(  # type: ignore[call-arg]
        _env_file=None,
        data_dir=tmp / "data",
        database_url=pg_url,
        api_key_cache_s=0,
        status_cache_s=0,
        max_upload_bytes=1_000_000,
    )
    app = create_app(settings_, sender=RecordingSender(), run_reaper=False)
    auth = new_key(settings_)
    # A scene and a job exist, so that some generated requests find rows; jobs' configs are the scripted pipeline's.
    with stand_in(SCRIPTED_PIPELINE), TestClient(app) as client:
        scene = make_scene(client, auth, pack(write_tiny_bundle(Path(tmp / "bundle"))))
        client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth)
        previous, DEFERRED.app = DEFERRED.app, app
        yield app, auth
        DEFERRED.app = previous


class DeferredApp:
    """An ASGI app that forwards to whichever app the fixture installs (the schema must load at import)."""

    def __init__(self) -> None:
        scratch = Path(tempfile.mkdtemp(prefix="panogs-schema-"))
        atexit.register(shutil.rmtree, scratch, True)
        scratch_settings = Settings(_env_file=None, data_dir=scratch)  # type: ignore[call-arg]
        self.app: Any = create_app(scratch_settings, sender=RecordingSender(), run_reaper=False)

    async def __call__(self, scope: Any, receive: Any, send: Any) -> None:
        await self.app(scope, receive, send)


# tus bodies are raw bytes under their own media type.
schemathesis.serializer.alias("application/offset+octet-stream", "application/octet-stream")
DEFERRED = DeferredApp()
schema = schemathesis.openapi.from_asgi("/openapi.json", DEFERRED)


@schema.parametrize()
# Derandomised: the same cases on every run (a few hundred over the schema's operations), so a failure repeats.
@settings(max_examples=12, deadline=None, derandomize=True, suppress_health_check=list(HealthCheck))
def test_no_server_errors(case: Any, app_and_auth: tuple[FastAPI, dict[str, str]]) -> None:
    _, auth = app_and_auth
    response = case.call(headers={**(case.headers or {}), **auth})
    beyond = (case.operation.method.upper(), case.operation.path) in RULES_BEYOND_THE_SCHEMA
    case.validate_response(response, checks=CHECKS if beyond else [*CHECKS, positive_data_acceptance])
    assert response.status_code < 500, response.text
