"""A stopped object store, as the API's clients and its load balancer see it: ``/readyz`` answers 503 naming the
storage (within its probe's timeout, the answer cached a few seconds), and a request the store cannot serve
(an upload, a download) answers 503 ``storage_unavailable`` with ``Retry-After`` and no host or bucket in it,
on a real SeaweedFS stopped mid-test and started again."""

from __future__ import annotations

import hashlib
import secrets
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from seaweedfs import SeaweedFS, seaweedfs
from svc_helpers import RecordingSender, make_scene, new_key

from service.api_app import create_app
from service.db.base import utcnow
from service.db.models import Artifact, FitState, Job, JobState
from service.db.session import get_session_factory, session_scope
from service.settings import Settings
from service.storage.backends import open_storage

TUS = {"Tus-Resumable": "1.0.0"}
PLY = b"ply\nformat ascii 1.0\nelement vertex 0\nend_header\n"


@pytest.fixture(scope="module")
def s3(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedFS]:
    """A SeaweedFS of this module: its tests stop it."""
    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as server:
        yield server


@pytest.fixture
def s3_settings(make_settings: Callable[..., Settings], s3: SeaweedFS) -> Iterator[Settings]:
    if s3.proc is None:
        s3.start()
    yield make_settings(
        "sqlite",
        storage_url=s3.url(f"ready-{secrets.token_hex(4)}"),
        s3_endpoint_url=s3.endpoint,
        s3_access_key_id=s3.access_key,
        s3_secret_access_key=s3.secret_key,
        storage_probe_timeout_s=2.0,
        storage_probe_cache_s=1.0,
    )
    if s3.proc is None:
        s3.start()


def _succeeded_with_artifact(settings: Settings, job_id: uuid.UUID) -> None:
    """The job as the worker leaves it: succeeded, one artifact in the store and its row."""
    storage = open_storage(settings)
    key = storage.job_prefix(job_id) + "panoptic.ply"
    storage.objects.put_bytes(key, PLY)
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        job.state = JobState.SUCCEEDED
        job.results_at = job.finished_at = utcnow()
        job.fit_state, job.fit_progress = FitState.SUCCEEDED, 1.0
        digest = hashlib.sha256(PLY).hexdigest()
        session.add(Artifact(job_id=job_id, name="panoptic.ply", path=key, size_bytes=len(PLY), sha256=digest,
                             media_type="application/octet-stream"))  # fmt: skip
        session.commit()


def _ready_within(client: TestClient, status: int, seconds: float) -> dict[str, object]:
    deadline = time.monotonic() + seconds
    while True:
        started = time.monotonic()
        answer = client.get("/readyz")
        assert time.monotonic() - started < 5, "/readyz must answer within its probe's timeout"
        if answer.status_code == status or time.monotonic() > deadline:
            assert answer.status_code == status, answer.text
            return dict(answer.json())
        time.sleep(0.2)


def _is_storage_outage(answer: object, endpoint: str) -> None:
    assert answer.status_code == 503, answer.text  # type: ignore[attr-defined]
    assert answer.headers["Retry-After"].isdigit()  # type: ignore[attr-defined]
    body = answer.json()  # type: ignore[attr-defined]
    assert body["type"] == "storage_unavailable"
    assert endpoint.split("//")[-1] not in answer.text  # type: ignore[attr-defined]
    assert "Traceback" not in answer.text  # type: ignore[attr-defined]


def test_a_stopped_store_is_not_ready_and_its_requests_are_503(
    s3: SeaweedFS, s3_settings: Settings, tiny_zip: bytes, tmp_path: Path
) -> None:
    auth = new_key(s3_settings)
    with TestClient(create_app(s3_settings, sender=RecordingSender(), run_reaper=False)) as client:
        ready = _ready_within(client, 200, 10)
        assert ready["checks"] == {"database": "ok", "broker": "ok", "storage": "ok"}
        scene = make_scene(client, auth, tiny_zip)
        job = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()
        _succeeded_with_artifact(s3_settings, uuid.UUID(job["id"]))
        started = client.post("/v1/uploads", headers={**auth, **TUS, "Upload-Length": "100"})
        assert started.status_code == 201
        download = f"/v1/jobs/{job['id']}/artifacts/panoptic.ply"
        assert client.get(download, headers=auth).content == PLY

        s3.stop()
        not_ready = _ready_within(client, 503, 10)
        assert str(not_ready["checks"]["storage"]).startswith("unavailable")  # type: ignore[index]
        assert not_ready["checks"]["database"] == "ok"  # type: ignore[index]
        _is_storage_outage(client.get(download, headers=auth), s3.endpoint)
        _is_storage_outage(client.post("/v1/uploads", headers={**auth, **TUS, "Upload-Length": "100"}), s3.endpoint)
        patch = client.patch(
            f"/v1/uploads/{started.json()['id']}", content=b"x" * 100,
            headers={**auth, **TUS, "Upload-Offset": "0", "Content-Type": "application/offset+octet-stream"},
        )  # fmt: skip
        _is_storage_outage(patch, s3.endpoint)
        assert client.get("/healthz").status_code == 200  # the process itself is fine

        s3.start()
        assert _ready_within(client, 200, 20)["checks"] == {"database": "ok", "broker": "ok", "storage": "ok"}
        assert client.get(download, headers=auth).content == PLY
        # The refused chunk left the upload where it was: it resumes at 0 once the store is back.
        head = client.head(f"/v1/uploads/{started.json()['id']}", headers={**auth, **TUS})
        assert head.headers["Upload-Offset"] == "0"


def test_the_probe_reads_its_own_object_back(tmp_path: Path) -> None:
    """The probe reads stored bytes (a stat alone was answered before a restarted SeaweedFS could serve a
    download): the first probe writes its object, later ones read it, and other bytes are a failure."""
    from service.storage.local import LocalStorage
    from service.storage.objects import StorageError
    from service.storage.probe import PROBE_BODY, PROBE_KEY, read_probe_object

    objects = LocalStorage(tmp_path)
    read_probe_object(objects)
    assert objects.get_bytes(PROBE_KEY) == PROBE_BODY
    read_probe_object(objects)  # read, not written again
    objects.put_bytes(PROBE_KEY, b"not the probe's")
    with pytest.raises(StorageError, match="readyz/probe"):
        read_probe_object(objects)
