"""The service with its objects in S3 (SeaweedFS): tus uploads as multipart parts, scenes, a job run by a worker
with a data folder of its own, results, ranged downloads and deletes; and nothing of it on the API's disk.

The API runs in the test process (TestClient); the job runs through ``worker.runner.execute_job`` with the
scripted pipeline and a second ``Settings`` whose data folder is another one, as a worker on another host has.
"""

from __future__ import annotations

import base64
import hashlib
import os
import secrets
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
import scripted_pipeline as scripted
from fastapi.testclient import TestClient
from seaweedfs import SeaweedFS
from svc_helpers import VOCABULARY_8D, RecordingSender, new_key

from service.api_app import create_app
from service.db.models import JobState, Upload
from service.db.session import get_session_factory, session_scope
from service.settings import Settings
from service.storage import parts
from service.storage.backends import open_storage
from service.storage.objects import Part
from worker import leased, runner

MIB = 1024 * 1024
TUS = {"Tus-Resumable": "1.0.0", "Content-Type": "application/offset+octet-stream"}


@pytest.fixture
def s3_settings(make_settings: Callable[..., Settings], seaweedfs_server: SeaweedFS) -> Settings:
    prefix = f"svc-{secrets.token_hex(4)}"
    return make_settings(
        "postgres",
        storage_url=seaweedfs_server.url(prefix),
        s3_endpoint_url=seaweedfs_server.endpoint,
        s3_access_key_id=seaweedfs_server.access_key,
        s3_secret_access_key=seaweedfs_server.secret_key,
    )


@pytest.fixture
def s3_client(s3_settings: Settings) -> Iterator[TestClient]:
    app = create_app(s3_settings, sender=RecordingSender(), run_reaper=False)
    with TestClient(app) as c:
        yield c


@pytest.fixture
def s3_auth(s3_settings: Settings) -> dict[str, str]:
    return new_key(s3_settings, "alice")


def _keys(settings: Settings, prefix: str) -> list[str]:
    return [o.key for o in open_storage(settings).objects.list_objects(prefix)]


def _files(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file())


def _tus_upload(client: TestClient, auth: dict[str, str], data: bytes, chunk: int) -> str:
    sha = hashlib.sha256(data).hexdigest()
    meta = f"filename {base64.b64encode(b'blob.bin').decode()},sha256 {base64.b64encode(sha.encode()).decode()}"
    created = client.post(
        "/v1/uploads", headers={**auth, **TUS, "Upload-Length": str(len(data)), "Upload-Metadata": meta}
    )
    assert created.status_code == 201, created.text
    upload_id = created.json()["id"]
    for offset in range(0, len(data), chunk):
        body = data[offset : offset + chunk]
        answer = client.patch(
            f"/v1/uploads/{upload_id}", content=body, headers={**auth, **TUS, "Upload-Offset": str(offset)}
        )
        assert answer.status_code == 204, answer.text
        assert int(answer.headers["Upload-Offset"]) == offset + len(body)
    return str(upload_id)


def test_tus_upload_in_4_mib_patches_goes_up_as_parts(
    s3_client: TestClient, s3_auth: dict[str, str], s3_settings: Settings
) -> None:
    data = os.urandom(23 * MIB + 12345)  # two full parts and a tail
    upload_id = _tus_upload(s3_client, s3_auth, data, 4 * MIB)
    status = s3_client.get(f"/v1/uploads/{upload_id}", headers=s3_auth).json()
    assert status["state"] == "complete"
    assert status["sha256"] == hashlib.sha256(data).hexdigest()
    storage = open_storage(s3_settings)
    assert storage.objects.get_bytes(f"uploads/{upload_id}/data") == data
    assert _keys(s3_settings, f"uploads/{upload_id}/") == [f"uploads/{upload_id}/data"]  # no state or tail left
    assert storage.objects.list_multipart("uploads/") == []
    assert _files(s3_settings.data_dir / "storage") == []  # the API wrote nothing of it to its own disk


def _multipart_row(settings: Settings, upload_id: str) -> dict[str, Any]:
    with session_scope(get_session_factory(settings.database)) as session:
        upload = session.get(Upload, uuid.UUID(upload_id))
        assert upload is not None
        assert upload.multipart is not None
        return dict(upload.multipart)


def test_the_part_state_moves_with_the_offset_and_resumes_in_another_process(
    s3_client: TestClient, s3_auth: dict[str, str], s3_settings: Settings
) -> None:
    data = os.urandom(14 * MIB + 3)
    created = s3_client.post("/v1/uploads", headers={**s3_auth, **TUS, "Upload-Length": str(len(data))})
    upload_id = created.json()["id"]
    for offset, size in ((0, 4 * MIB), (4 * MIB, 4 * MIB), (8 * MIB, 2 * MIB)):
        answer = s3_client.patch(f"/v1/uploads/{upload_id}", content=data[offset : offset + size],
                                 headers={**s3_auth, **TUS, "Upload-Offset": str(offset)})  # fmt: skip
        assert answer.status_code == 204, answer.text
    # In the row, at the row's offset: the first 4 MiB waited as a tail and went up with the next 4 as one part of
    # 8 MiB (no tail left then); the last 2 MiB are the tail now, an object named by the offset.
    state = _multipart_row(s3_settings, upload_id)
    assert (state["offset"], [p[:2] for p in state["parts"]], state["tail"]) == (10 * MIB, [[1, 8 * MIB]], 2 * MIB)
    assert not [k for k in _keys(s3_settings, f"uploads/{upload_id}/") if "state-" in k]  # no state object
    assert f"uploads/{upload_id}/tail-{10 * MIB}" in _keys(s3_settings, f"uploads/{upload_id}/")
    parts.TAILS.take(f"uploads/{upload_id}/data", 10 * MIB)  # as in another API process: the tail is read back
    rest = s3_client.patch(f"/v1/uploads/{upload_id}", content=data[10 * MIB :],
                           headers={**s3_auth, **TUS, "Upload-Offset": str(10 * MIB)})  # fmt: skip
    assert rest.status_code == 204, rest.text
    status = s3_client.get(f"/v1/uploads/{upload_id}", headers=s3_auth).json()
    assert (status["state"], status["sha256"]) == ("complete", hashlib.sha256(data).hexdigest())
    assert open_storage(s3_settings).objects.get_bytes(f"uploads/{upload_id}/data") == data
    assert _keys(s3_settings, f"uploads/{upload_id}/") == [f"uploads/{upload_id}/data"]  # every tail gone


def test_a_refused_chunk_keeps_the_last_good_state(s3_client: TestClient, s3_auth: dict[str, str]) -> None:
    data = os.urandom(12 * MIB)
    created = s3_client.post("/v1/uploads", headers={**s3_auth, **TUS, "Upload-Length": str(len(data))})
    upload_id = created.json()["id"]
    first = data[: 6 * MIB]
    assert (
        s3_client.patch(
            f"/v1/uploads/{upload_id}", content=first, headers={**s3_auth, **TUS, "Upload-Offset": "0"}
        ).status_code
        == 204
    )
    wrong = base64.b64encode(hashlib.sha256(b"other bytes").digest()).decode()
    refused = s3_client.patch(
        f"/v1/uploads/{upload_id}",
        content=data[6 * MIB :],
        headers={**s3_auth, **TUS, "Upload-Offset": str(6 * MIB), "Upload-Checksum": f"sha256 {wrong}"},
    )
    assert refused.status_code == 460
    head = s3_client.head(f"/v1/uploads/{upload_id}", headers=s3_auth)
    assert head.headers["Upload-Offset"] == str(6 * MIB)
    rest = s3_client.patch(
        f"/v1/uploads/{upload_id}", content=data[6 * MIB :], headers={**s3_auth, **TUS, "Upload-Offset": str(6 * MIB)}
    )
    assert rest.status_code == 204
    status = s3_client.get(f"/v1/uploads/{upload_id}", headers=s3_auth).json()
    assert status["sha256"] == hashlib.sha256(data).hexdigest()


def test_an_aborted_upload_leaves_no_parts(
    s3_client: TestClient, s3_auth: dict[str, str], s3_settings: Settings
) -> None:
    data = os.urandom(11 * MIB)
    created = s3_client.post("/v1/uploads", headers={**s3_auth, **TUS, "Upload-Length": str(len(data) * 2)})
    upload_id = created.json()["id"]
    s3_client.patch(f"/v1/uploads/{upload_id}", content=data, headers={**s3_auth, **TUS, "Upload-Offset": "0"})
    storage = open_storage(s3_settings)
    assert len(storage.objects.list_multipart(f"uploads/{upload_id}/")) == 1  # a part is up
    assert s3_client.delete(f"/v1/uploads/{upload_id}", headers=s3_auth).status_code == 204
    assert storage.objects.list_multipart(f"uploads/{upload_id}/") == []
    assert _keys(s3_settings, f"uploads/{upload_id}/") == []


def test_scene_job_results_range_and_delete(
    s3_client: TestClient, s3_auth: dict[str, str], s3_settings: Settings, tiny_zip: bytes, tmp_path: Path
) -> None:
    upload_id = _tus_upload(s3_client, s3_auth, tiny_zip, 4 * MIB)
    scene = s3_client.post("/v1/scenes", json={"upload_id": upload_id}, headers=s3_auth)
    assert scene.status_code == 201, scene.text
    scene_id = scene.json()["id"]
    assert _keys(s3_settings, f"uploads/{upload_id}/") == []  # extracted and stored: the archive is gone
    assert any(k.endswith("scene.json") for k in _keys(s3_settings, f"scenes/{scene_id}/"))
    job = s3_client.post(
        "/v1/jobs", json={"scene_id": scene_id, "config": {}, "vocabulary": VOCABULARY_8D}, headers=s3_auth
    )
    assert job.status_code == 202, job.text
    job_id = uuid.UUID(job.json()["id"])

    # The worker: another data folder (another host), the same database and bucket.
    worker_settings = s3_settings.model_copy(update={"data_dir": tmp_path / "worker-data"})
    env = _worker_env(worker_settings)
    assert runner.execute_job(job_id, lease="lease-1", worker="w1", env=env) is JobState.SUCCEEDED
    # Its scratch folder is gone with the task; the scene's bundle stays in the worker's cache for the next job.
    kept = _files(tmp_path / "worker-data")
    assert kept
    assert all(f.startswith(f"work/bundles/{scene_id}") for f in kept), kept

    status = s3_client.get(f"/v1/jobs/{job_id}", headers=s3_auth).json()
    assert status["state"] == "succeeded", status
    instances = s3_client.get(f"/v1/jobs/{job_id}/instances", headers=s3_auth)
    assert instances.status_code == 200
    assert [i["class_name"] for i in instances.json()["data"]] == ["chair", "table"]
    stored = open_storage(s3_settings).objects.get_bytes(f"artifacts/{job_id}/panoptic.ply")
    whole = s3_client.get(f"/v1/jobs/{job_id}/artifacts/panoptic.ply", headers=s3_auth)
    assert whole.status_code == 200
    assert whole.content == stored
    part = s3_client.get(f"/v1/jobs/{job_id}/artifacts/panoptic.ply", headers={**s3_auth, "Range": "bytes=10-49"})
    assert part.status_code == 206
    assert part.content == stored[10:50]
    assert part.headers["Content-Range"] == f"bytes 10-49/{len(stored)}"
    tail = s3_client.get(f"/v1/jobs/{job_id}/artifacts/panoptic.ply", headers={**s3_auth, "Range": "bytes=-5"})
    assert tail.content == stored[-5:]
    past = s3_client.get(
        f"/v1/jobs/{job_id}/artifacts/panoptic.ply", headers={**s3_auth, "Range": f"bytes={len(stored)}-"}
    )
    assert past.status_code == 416
    assert past.headers["Content-Range"] == f"bytes */{len(stored)}"
    # ?redirect=true: served here while the S3 server is reachable only from the service's network ...
    inside = s3_client.get(f"/v1/jobs/{job_id}/artifacts/panoptic.ply?redirect=true", headers=s3_auth)
    assert (inside.status_code, inside.content) == (200, stored)
    # ... and a 307 to a signed link of the store once its address for clients is set (the link works alone).
    public = s3_settings.model_copy(update={"s3_public_endpoint_url": s3_settings.s3_endpoint_url})
    with TestClient(create_app(public, sender=RecordingSender(), run_reaper=False)) as c:
        moved = c.get(f"/v1/jobs/{job_id}/artifacts/panoptic.ply?redirect=true", headers=s3_auth,
                      follow_redirects=False)  # fmt: skip
        unasked = c.get(f"/v1/jobs/{job_id}/artifacts/panoptic.ply", headers=s3_auth)
    assert moved.status_code == 307
    assert moved.headers["location"].startswith(f"{s3_settings.s3_endpoint_url}/")
    assert httpx.get(moved.headers["location"]).content == stored
    ranged = httpx.get(moved.headers["location"], headers={"Range": "bytes=10-49"})
    assert (ranged.status_code, ranged.content) == (206, stored[10:50])
    assert (unasked.status_code, unasked.content) == (200, stored)  # no redirect unless asked
    # The checkpoints are kept once, under the scene by key, not again with the job's files.
    assert any(k.endswith(".ckpt") for k in _keys(s3_settings, f"scenes/{scene_id}/stages/"))
    assert not [k for k in _keys(s3_settings, f"artifacts/{job_id}/") if k.endswith(".done")]

    assert s3_client.delete(f"/v1/scenes/{scene_id}", headers=s3_auth).status_code == 204
    assert _keys(s3_settings, f"scenes/{scene_id}/") == []
    assert _keys(s3_settings, f"artifacts/{job_id}/") == []
    assert _files(s3_settings.data_dir / "storage") == []
    assert not (s3_settings.data_dir / "work" / "cache" / "artifacts" / str(job_id)).exists()


def _worker_env(settings: Settings) -> leased.JobEnv:
    return leased.JobEnv(
        settings=settings,
        session_factory=get_session_factory(settings.database),
        storage=open_storage(settings),
        pipeline=scripted.run_pipeline,
        make_config=scripted.make_config,
        stages=scripted.STAGES,
    )


def test_upload_tails_are_named_by_offset() -> None:
    assert parts.state_key("uploads/u/data", 7) == "uploads/u/state-7.json"
    assert parts.tail_key("uploads/u/data", 7) == "uploads/u/tail-7"
    state = parts.UploadState(upload_id="x", offset=3, parts=[Part(number=1, size=5, etag="e")], tail=3, previous=0)
    assert parts.UploadState.from_record(state.to_record()) == state
