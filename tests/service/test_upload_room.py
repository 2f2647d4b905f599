"""Room for what a tenant stores: an upload being made into a scene counts once, and an
upload is created, and each PATCH accepted, only when its remaining bytes fit in the quota (413) and on the disk
with ``min_free_disk_bytes`` left free (507), refused before a byte is written."""

from __future__ import annotations

import shutil
from pathlib import Path

from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, new_key, upload_bytes

from service.api_app import create_app
from service.settings import Settings

TUS = {"Tus-Resumable": "1.0.0"}
OCTET = {"Content-Type": "application/offset+octet-stream"}


def _client(settings: Settings) -> TestClient:
    return TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False))


def _uploads_on_disk(settings: Settings) -> list[Path]:
    return [p for p in (Path(settings.storage) / "uploads").glob("*/*") if p.is_file()]


def test_the_upload_being_extracted_counts_once(
    client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
) -> None:
    """The reported case scaled down: a quota of 6.5 MB, a 3.05 MB upload, a 3.5 MB scene. Here the quota holds the
    scene and the upload each, not both together."""
    upload = upload_bytes(client, auth, tiny_zip, filename="tiny.zip")
    scene_size = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth).json()["size_bytes"]
    quota = scene_size + len(tiny_zip) - 1
    assert max(scene_size, len(tiny_zip)) <= quota
    limited = settings.model_copy(update={"quota_bytes": quota})
    bob = new_key(limited, "bob")  # a tenant that stores nothing yet
    with _client(limited) as c:
        upload = upload_bytes(c, bob, tiny_zip, filename="tiny.zip")
        made = c.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=bob)
        assert made.status_code == 201, made.text
        assert made.json()["size_bytes"] == scene_size
        # What is stored now is the scene alone: the rest of the quota is free, and not a byte more.
        room = quota - scene_size
        assert c.post("/v1/uploads", headers={**bob, **TUS, "Upload-Length": str(room + 1)}).status_code == 413
        assert c.post("/v1/uploads", headers={**bob, **TUS, "Upload-Length": str(room)}).status_code == 201


def test_an_upload_the_disk_cannot_hold_is_refused_with_507(
    auth: dict[str, str], settings: Settings, tmp_path: Path
) -> None:
    free = shutil.disk_usage(tmp_path).free
    # PANOGS_MIN_FREE_DISK_BYTES above the free disk: no upload at all (the reported 3 MB one).
    above = settings.model_copy(update={"min_free_disk_bytes": free + 2**30})
    with _client(above) as c:
        r = c.post("/v1/uploads", content=b"x" * 3000, headers={**auth, **TUS, **OCTET, "Upload-Length": "3000"})
    assert r.status_code == 507, r.text
    assert r.json()["type"] == "insufficient_storage"
    assert "PANOGS_MIN_FREE_DISK_BYTES" in r.json()["message"]
    assert _uploads_on_disk(settings) == []
    # An Upload-Length larger than the room left (the reported 2 GiB upload against 230 MB): refused at creation.
    room_of_1_mib = settings.model_copy(update={"min_free_disk_bytes": max(0, free - 2**20)})
    with _client(room_of_1_mib) as c:
        r = c.post("/v1/uploads", headers={**auth, **TUS, "Upload-Length": str(2**31)})
    assert r.status_code == 507, r.text
    assert f"{2**31:,} more bytes" in r.json()["message"]


def test_each_patch_checks_the_disk_and_the_quota_before_writing(
    client: TestClient, auth: dict[str, str], settings: Settings, tmp_path: Path
) -> None:
    created = client.post("/v1/uploads", headers={**auth, **TUS, "Upload-Length": "2000"})
    assert created.status_code == 201
    location = created.headers["Location"]
    assert (
        client.patch(location, content=b"a" * 500, headers={**auth, **TUS, **OCTET, "Upload-Offset": "0"}).status_code
        == 204
    )

    full_disk = settings.model_copy(update={"min_free_disk_bytes": shutil.disk_usage(tmp_path).free + 2**30})
    with _client(full_disk) as c:
        r = c.patch(location, content=b"b" * 500, headers={**auth, **TUS, **OCTET, "Upload-Offset": "500"})
        assert r.status_code == 507, r.text
        assert "1,500 more bytes" in r.json()["message"]  # Upload-Length less what already arrived
    lowered_quota = settings.model_copy(update={"quota_bytes": 1000})
    with _client(lowered_quota) as c:
        r = c.patch(location, content=b"b" * 500, headers={**auth, **TUS, **OCTET, "Upload-Offset": "500"})
        assert r.status_code == 413, r.text
        assert "PANOGS_QUOTA_BYTES" in r.json()["message"]
    assert client.head(location, headers={**auth, **TUS}).headers["Upload-Offset"] == "500"  # nothing written
    r = client.patch(location, content=b"b" * 1500, headers={**auth, **TUS, **OCTET, "Upload-Offset": "500"})
    assert r.status_code == 204
    assert client.get(location, headers=auth).json()["state"] == "complete"
