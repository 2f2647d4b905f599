"""Deleting scenes and jobs with their files, per-tenant quotas, retention and orphan sweeping, on
PostgreSQL and on the embedded SQLite."""

from __future__ import annotations

import uuid
from datetime import timedelta
from pathlib import Path

import numpy as np
from fastapi.testclient import TestClient
from svc_helpers import BOTH_BACKENDS, RecordingSender, make_scene, new_key, pack, upload_bytes, write_tiny_bundle
from test_results import _unit, finish_job

from service.api_app import create_app
from service.db.base import utcnow
from service.db.models import Artifact, Job, JobState, Scene
from service.db.session import get_session_factory, session_scope
from service.lifecycle import sweep_orphans, sweep_retention
from service.settings import Settings
from service.storage import Storage


def _job(client: TestClient, auth: dict[str, str], scene_id: str) -> dict[str, str]:
    response = client.post("/v1/jobs", json={"scene_id": scene_id}, headers=auth)
    assert response.status_code == 202, response.text
    return dict(response.json())


def _finished_job(client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes) -> tuple[str, str]:
    scene = make_scene(client, auth, tiny_zip)
    job = _job(client, auth, scene["id"])
    finish_job(settings, job["id"], _unit(np.eye(3, 8) + 0.1), "test-space")
    return scene["id"], job["id"]


def _rows(settings: Settings, model: type, ident: str) -> int:
    with session_scope(get_session_factory(settings.database)) as session:
        return 0 if session.get(model, uuid.UUID(ident)) is None else 1


@BOTH_BACKENDS
class TestDelete:
    def test_delete_job_removes_rows_and_files_and_is_safe_to_retry(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
    ) -> None:
        _, job_id = _finished_job(client, auth, settings, tiny_zip)
        folder = Storage(settings.storage).job_dir(uuid.UUID(job_id))
        assert (folder / "instances.json").is_file()
        assert client.get(f"/v1/jobs/{job_id}/instances", headers=auth).status_code == 200  # cached result
        assert client.delete(f"/v1/jobs/{job_id}", headers=auth).status_code == 204
        assert not folder.exists()
        assert _rows(settings, Job, job_id) == 0
        with session_scope(get_session_factory(settings.database)) as session:
            assert session.query(Artifact).filter(Artifact.job_id == uuid.UUID(job_id)).count() == 0
        assert client.get(f"/v1/jobs/{job_id}", headers=auth).status_code == 404
        assert client.get(f"/v1/jobs/{job_id}/instances", headers=auth).status_code == 404
        assert client.delete(f"/v1/jobs/{job_id}", headers=auth).status_code == 204  # a retry

    def test_delete_running_job_cancels_it_first(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
    ) -> None:
        scene = make_scene(client, auth, tiny_zip)
        job_id = _job(client, auth, scene["id"])["id"]
        with session_scope(get_session_factory(settings.database)) as session:
            job = session.get(Job, uuid.UUID(job_id))
            assert job is not None
            job.state, job.lease = JobState.RUNNING, "lease-1"
            session.commit()
        assert client.delete(f"/v1/jobs/{job_id}", headers=auth).status_code == 204
        assert _rows(settings, Job, job_id) == 0
        # The worker's next guarded write finds no row: it has lost the job and stops.
        from service.db import crud

        with session_scope(get_session_factory(settings.database)) as session:
            assert not crud.update_running(session, uuid.UUID(job_id), "lease-1", progress=0.5)

    def test_delete_scene_removes_its_jobs_and_bundle(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
    ) -> None:
        scene_id, job_id = _finished_job(client, auth, settings, tiny_zip)
        storage = Storage(settings.storage)
        assert storage.scene_dir(uuid.UUID(scene_id)).is_dir()
        assert client.delete(f"/v1/scenes/{scene_id}", headers=auth).status_code == 204
        assert not storage.scene_dir(uuid.UUID(scene_id)).exists()
        assert not storage.job_dir(uuid.UUID(job_id)).exists()
        assert _rows(settings, Scene, scene_id) == 0
        assert _rows(settings, Job, job_id) == 0
        assert client.delete(f"/v1/scenes/{scene_id}", headers=auth).status_code == 204

    def test_another_tenants_delete_touches_nothing(
        self,
        client: TestClient,
        auth: dict[str, str],
        other_auth: dict[str, str],
        settings: Settings,
        tiny_zip: bytes,
    ) -> None:
        scene_id, job_id = _finished_job(client, auth, settings, tiny_zip)
        assert client.delete(f"/v1/jobs/{job_id}", headers=other_auth).status_code == 204
        assert client.delete(f"/v1/scenes/{scene_id}", headers=other_auth).status_code == 204
        assert _rows(settings, Job, job_id) == 1
        assert _rows(settings, Scene, scene_id) == 1
        assert Storage(settings.storage).job_dir(uuid.UUID(job_id)).is_dir()


def _add_compressible_note(root: Path) -> None:
    (root / "notes.txt").write_bytes(bytes(100_000))


@BOTH_BACKENDS
class TestQuotas:
    def test_concurrent_jobs_refused_with_429_naming_the_limit(self, settings: Settings, tiny_zip: bytes) -> None:
        limited = settings.model_copy(update={"quota_concurrent_jobs": 2})
        auth = new_key(limited, "alice")
        with TestClient(create_app(limited, sender=RecordingSender(), run_reaper=False)) as client:
            scene = make_scene(client, auth, tiny_zip)
            _job(client, auth, scene["id"])
            second = _job(client, auth, scene["id"])
            third = client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth)
            assert third.status_code == 429
            assert third.json()["type"] == "quota_exceeded"
            assert "limit is 2" in third.json()["message"]
            assert "PANOGS_QUOTA_CONCURRENT_JOBS" in third.json()["message"]
            client.post(f"/v1/jobs/{second['id']}/cancel", headers=auth)  # a finished job frees its place
            assert client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).status_code == 202

    def test_storage_quota_refuses_an_upload_that_would_pass_it(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
    ) -> None:
        used = make_scene(client, auth, tiny_zip)["size_bytes"]  # the extracted scene counts
        limited = settings.model_copy(update={"quota_bytes": used + 100})
        with TestClient(create_app(limited, sender=RecordingSender(), run_reaper=False)) as limited_client:
            headers = {**auth, "Tus-Resumable": "1.0.0"}
            refused = limited_client.post("/v1/uploads", headers={**headers, "Upload-Length": "101"})
            assert refused.status_code == 413
            body = refused.json()
            assert body["type"] == "quota_exceeded"
            assert f"{used + 100:,} bytes (PANOGS_QUOTA_BYTES)" in body["message"]
            accepted = limited_client.post("/v1/uploads", headers={**headers, "Upload-Length": "100"})
            assert accepted.status_code == 201

    def test_extraction_is_bounded_by_the_quota(self, settings: Settings, tmp_path: Path) -> None:
        # Room for the archive itself, but not for what it expands to: a bundle with 100 kB of zeros in a note
        # (the archive being extracted counts once, so the quota must be below the extracted size).
        padded = pack(write_tiny_bundle(tmp_path / "padded", mutate=_add_compressible_note))
        limited = settings.model_copy(update={"quota_bytes": len(padded) + 10})
        auth = new_key(limited, "alice")
        with TestClient(create_app(limited, sender=RecordingSender(), run_reaper=False)) as client:
            upload = upload_bytes(client, auth, padded, filename="padded.zip")
            response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
            assert response.status_code == 422
            problems = response.json()["problems"]
            assert any("storage quota" in p and "PANOGS_QUOTA_BYTES" in p for p in problems), problems
            assert not any((Path(limited.storage) / "scenes").glob("*"))  # nothing kept


@BOTH_BACKENDS
def test_retention_deletes_old_finished_jobs_only(
    client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
) -> None:
    _, old_id = _finished_job(client, auth, settings, tiny_zip)
    _, new_id = _finished_job(client, auth, settings, tiny_zip)
    factory = get_session_factory(settings.database)
    with session_scope(factory) as session:
        for ident, age in ((old_id, 10), (new_id, 1)):
            job = session.get(Job, uuid.UUID(ident))
            assert job is not None
            job.finished_at = utcnow() - timedelta(days=age)
        session.commit()
    storage = Storage(settings.storage)
    with session_scope(factory) as session:
        assert sweep_retention(session, settings, storage) == 0  # no retention set: keep everything
        kept = settings.model_copy(update={"retention_days": 7})
        assert sweep_retention(session, kept, storage) == 1
    assert _rows(settings, Job, old_id) == 0
    assert not storage.job_dir(uuid.UUID(old_id)).exists()
    assert _rows(settings, Job, new_id) == 1
    assert storage.job_dir(uuid.UUID(new_id)).is_dir()


def test_orphan_folders_are_swept(settings: Settings) -> None:
    import os

    storage = Storage(settings.storage)
    orphan = storage.job_dir(uuid.uuid4())
    orphan.mkdir(parents=True)
    (orphan / "late.ply").write_bytes(b"written after the delete")
    fresh = storage.job_dir(uuid.uuid4())
    fresh.mkdir(parents=True)
    (fresh / "young.ply").write_bytes(b"being written")
    old = (utcnow() - timedelta(hours=1)).timestamp()
    os.utime(orphan / "late.ply", (old, old))  # nothing written in it for an hour
    with session_scope(get_session_factory(settings.database)) as session:
        assert sweep_orphans(session, storage) == 1
    assert not orphan.exists()
    assert fresh.is_dir()  # young: its row may not be committed yet
