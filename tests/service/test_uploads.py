"""tus uploads: streamed to disk, size-limited, checksummed, resumable after an interruption."""

from __future__ import annotations

import base64
import hashlib
from collections.abc import Callable
from typing import Any

import pytest
from fastapi.testclient import TestClient
from svc_helpers import BOTH_BACKENDS, RecordingSender, new_key, upload_bytes

from service.api_app import create_app
from service.settings import Settings

OCTET = {"Content-Type": "application/offset+octet-stream", "Tus-Resumable": "1.0.0"}


def _create(client: TestClient, auth: dict[str, str], length: int, **extra: str) -> dict[str, Any]:
    response = client.post("/v1/uploads", headers={**auth, "Upload-Length": str(length), **extra})
    assert response.status_code == 201, response.text
    assert response.headers["location"] == f"/v1/uploads/{response.json()['id']}"
    assert response.headers["tus-resumable"] == "1.0.0"
    return dict(response.json())


def _patch(client: TestClient, auth: dict[str, str], upload_id: str, offset: int, data: bytes, **extra: str) -> Any:
    headers = {**auth, **OCTET, "Upload-Offset": str(offset), **extra}
    return client.patch(f"/v1/uploads/{upload_id}", content=data, headers=headers)


def _b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


class TestUpload:
    @BOTH_BACKENDS
    def test_one_request(self, client: TestClient, auth: dict[str, str]) -> None:
        data = bytes(range(256)) * 1000
        upload = upload_bytes(client, auth, data, filename="scene.zip")
        assert upload["state"] == "complete"
        assert upload["offset"] == len(data)
        assert upload["sha256"] == hashlib.sha256(data).hexdigest()
        assert upload["filename"] == "scene.zip"

    def test_resume_in_chunks(self, client: TestClient, auth: dict[str, str], settings: Settings) -> None:
        data = b"0123456789" * 300_000  # 3 MB in three PATCHes, one of them interrupted halfway
        upload = _create(
            client,
            auth,
            len(data),
            **{"Upload-Metadata": f"sha256 {_b64(hashlib.sha256(data).hexdigest().encode())}"},
        )
        uid = upload["id"]
        assert _patch(client, auth, uid, 0, data[:1_000_000]).status_code == 204
        head = client.head(f"/v1/uploads/{uid}", headers=auth)
        assert head.headers["upload-offset"] == "1000000"
        assert head.headers["upload-length"] == str(len(data))
        # A wrong offset is refused and changes nothing.
        wrong = _patch(client, auth, uid, 5, data[5:10])
        assert wrong.status_code == 409
        assert wrong.json()["type"] == "conflict"
        # Bytes past the recorded offset (a server killed mid-PATCH) are cut off by the next PATCH.
        path = settings.storage / "uploads" / uid / "data"
        with path.open("ab") as f:
            f.write(b"garbage")
        assert _patch(client, auth, uid, 1_000_000, data[1_000_000:2_000_000]).headers["upload-offset"] == "2000000"
        last = _patch(client, auth, uid, 2_000_000, data[2_000_000:])
        assert last.status_code == 204
        assert last.headers["upload-offset"] == str(len(data))
        done = client.get(f"/v1/uploads/{uid}", headers=auth).json()
        assert done["state"] == "complete"
        assert done["sha256"] == hashlib.sha256(data).hexdigest()
        assert path.read_bytes() == data

    def test_hash_rebuilt_after_restart(self, settings: Settings, auth: dict[str, str]) -> None:
        data = b"abc" * 100_000
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as first:
            uid = _create(first, auth, len(data))["id"]
            assert _patch(first, auth, uid, 0, data[:1000]).status_code == 204
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as second:
            assert _patch(second, auth, uid, 1000, data[1000:]).status_code == 204
            assert second.get(f"/v1/uploads/{uid}", headers=auth).json()["sha256"] == hashlib.sha256(data).hexdigest()

    def test_chunk_checksum(self, client: TestClient, auth: dict[str, str], settings: Settings) -> None:
        uid = _create(client, auth, 8)["id"]
        good = {"Upload-Checksum": f"sha256 {_b64(hashlib.sha256(b'abcd').digest())}"}
        bad = {"Upload-Checksum": f"sha256 {_b64(hashlib.sha256(b'xxxx').digest())}"}
        assert _patch(client, auth, uid, 0, b"abcd", **good).status_code == 204
        refused = _patch(client, auth, uid, 4, b"efgh", **bad)
        assert refused.status_code == 460
        assert refused.json()["type"] == "checksum_mismatch"
        assert client.head(f"/v1/uploads/{uid}", headers=auth).headers["upload-offset"] == "4"
        assert (settings.storage / "uploads" / uid / "data").read_bytes() == b"abcd"
        unsupported = _patch(client, auth, uid, 4, b"efgh", **{"Upload-Checksum": "md5 AAAA"})
        assert unsupported.status_code == 422

    def test_whole_file_checksum_mismatch_discards(
        self, client: TestClient, auth: dict[str, str], settings: Settings
    ) -> None:
        wrong = hashlib.sha256(b"something else").hexdigest()
        headers = {**auth, **OCTET, "Upload-Length": "4", "Upload-Metadata": f"sha256 {_b64(wrong.encode())}"}
        response = client.post("/v1/uploads", content=b"abcd", headers=headers)
        assert response.status_code == 460
        assert "discarded" in response.json()["message"]
        assert not any((settings.storage / "uploads").iterdir())


class TestLimits:
    def test_declared_length_over_limit(self, make_settings: Callable[..., Settings], auth: dict[str, str]) -> None:
        settings = make_settings("postgres", max_upload_bytes=1000)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            auth = new_key(settings)
            response = client.post("/v1/uploads", headers={**auth, "Upload-Length": "1001"})
            assert response.status_code == 413
            assert response.json()["type"] == "payload_too_large"
            assert not (settings.storage / "uploads").exists() or not any((settings.storage / "uploads").iterdir())

    def test_body_longer_than_declared(self, client: TestClient, auth: dict[str, str]) -> None:
        uid = _create(client, auth, 10)["id"]
        response = _patch(client, auth, uid, 0, b"x" * 11)
        assert response.status_code == 413
        assert client.head(f"/v1/uploads/{uid}", headers=auth).headers["upload-offset"] == "0"

    def test_chunked_body_longer_than_declared(self, client: TestClient, auth: dict[str, str]) -> None:
        uid = _create(client, auth, 10)["id"]
        response = _patch(client, auth, uid, 0, iter([b"x" * 6, b"y" * 6]))  # no Content-Length: chunked
        assert response.status_code == 413
        assert client.head(f"/v1/uploads/{uid}", headers=auth).headers["upload-offset"] == "0"

    @pytest.mark.parametrize(
        ("headers", "status"),
        [
            ({"Upload-Length": "-1"}, 422),
            ({"Upload-Length": "ten"}, 422),
            ({}, 422),
            ({"Upload-Length": "5", "Tus-Resumable": "0.2.2"}, 412),
            ({"Upload-Length": "5", "Upload-Metadata": "filename !!!"}, 422),
            ({"Upload-Length": "5", "Upload-Metadata": f"sha256 {_b64(b'not-hex')}"}, 422),
        ],
    )
    def test_bad_headers(self, client: TestClient, auth: dict[str, str], headers: dict[str, str], status: int) -> None:
        response = client.post("/v1/uploads", headers={**auth, **headers})
        assert response.status_code == status, response.text
        assert response.json()["message"]

    def test_wrong_content_type(self, client: TestClient, auth: dict[str, str]) -> None:
        uid = _create(client, auth, 4)["id"]
        response = client.patch(
            f"/v1/uploads/{uid}",
            content=b"abcd",
            headers={**auth, "Upload-Offset": "0", "Content-Type": "application/json"},
        )
        assert response.status_code == 415


class TestOwnership:
    def test_other_tenant_sees_404(self, client: TestClient, auth: dict[str, str], other_auth: dict[str, str]) -> None:
        uid = _create(client, auth, 4)["id"]
        for method in ("get", "head", "delete"):
            assert getattr(client, method)(f"/v1/uploads/{uid}", headers=other_auth).status_code == 404
        assert _patch(client, other_auth, uid, 0, b"abcd").status_code == 404
        assert client.get(f"/v1/uploads/{uid}", headers=auth).status_code == 200

    def test_terminate(self, client: TestClient, auth: dict[str, str], settings: Settings) -> None:
        uid = _create(client, auth, 4)["id"]
        assert client.delete(f"/v1/uploads/{uid}", headers=auth).status_code == 204
        assert client.get(f"/v1/uploads/{uid}", headers=auth).status_code == 404
        assert not (settings.storage / "uploads" / uid).exists()

    def test_discovery(self, client: TestClient) -> None:
        response = client.options("/v1/uploads")
        assert response.status_code == 204
        assert "creation-with-upload" in response.headers["tus-extension"]
        assert response.headers["tus-checksum-algorithm"] == "sha256"
