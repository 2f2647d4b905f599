"""The bytes of a refused upload do not stay in storage: a whole-file checksum that does not match (after parts went
up), a creation whose first chunk fails its checksum, an archive refused as a scene; on the local backend and on a
real S3 server (SeaweedFS), objects and unfinished multipart uploads alike."""

from __future__ import annotations

import base64
import hashlib
import os
import secrets
from collections.abc import Callable

import pytest
from fastapi.testclient import TestClient
from seaweedfs import SeaweedFS
from svc_helpers import RecordingSender, new_key

from service.api_app import create_app
from service.settings import Settings
from service.storage.backends import open_storage

MIB = 1024 * 1024
TUS = {"Tus-Resumable": "1.0.0", "Content-Type": "application/offset+octet-stream"}


def _meta(**values: str) -> str:
    return ",".join(f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in values.items())


@pytest.mark.parametrize("backend", ["local", "s3"])
def test_refused_uploads_leave_no_bytes(
    make_settings: Callable[..., Settings], request: pytest.FixtureRequest, backend: str
) -> None:
    overrides = {}
    if backend == "s3":
        server: SeaweedFS = request.getfixturevalue("seaweedfs_server")
        overrides = {"storage_url": server.url(f"refused-{secrets.token_hex(4)}"), "s3_endpoint_url": server.endpoint,
                     "s3_access_key_id": server.access_key, "s3_secret_access_key": server.secret_key}  # fmt: skip
    settings = make_settings("sqlite", **overrides)
    auth = new_key(settings)
    storage = open_storage(settings)
    data = os.urandom(11 * MIB)  # over one S3 part: a part is up before the checksum is known
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        wrong = client.post("/v1/uploads", headers={**auth, **TUS, "Upload-Length": str(len(data)),
                                                     "Upload-Metadata": _meta(sha256="0" * 64)})  # fmt: skip
        assert wrong.status_code == 201
        upload_id = wrong.json()["id"]
        half = len(data) // 2
        for offset, chunk in ((0, data[:half]), (half, data[half:])):
            answer = client.patch(f"/v1/uploads/{upload_id}", content=chunk,
                                  headers={**auth, **TUS, "Upload-Offset": str(offset)})  # fmt: skip
        assert answer.status_code == 460, answer.text  # the whole file's SHA-256 did not match: discarded
        bad_chunk = base64.b64encode(hashlib.sha256(b"other").digest()).decode()
        refused = client.post("/v1/uploads", content=b"x" * 100, headers={
            **auth, **TUS, "Upload-Length": "100", "Upload-Checksum": f"sha256 {bad_chunk}"})  # fmt: skip
        assert refused.status_code == 460
        not_archive = client.post("/v1/uploads", content=b"not an archive" * 10,
                                  headers={**auth, **TUS, "Upload-Length": "140"})  # fmt: skip
        assert not_archive.status_code == 201
        scene = client.post("/v1/scenes", json={"upload_id": not_archive.json()["id"]}, headers=auth)
        assert scene.status_code == 422
    assert [o.key for o in storage.objects.list_objects("uploads/")] == []
    if backend == "s3":
        assert storage.objects.list_multipart("uploads/") == []
