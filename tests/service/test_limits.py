"""Limits from the outside review: JSON bodies capped with a 413 naming the limit, short validation
errors, no upload left behind by a refused creation, and a dead embedded worker's job re-queued at once."""

from __future__ import annotations

import json
import uuid

import pytest
from fastapi.testclient import TestClient
from svc_helpers import make_scene

from service.db.models import Job, JobState, Upload
from service.db.session import get_session_factory, session_scope
from service.reaper import embedded_worker_name, requeue_dead_worker
from service.settings import Settings


def test_json_body_over_the_cap_is_refused_naming_the_limit(client: TestClient, auth: dict[str, str]) -> None:
    body = b'{"scene_id": "' + b"x" * (2 * 1024 * 1024) + b'"}'
    response = client.post("/v1/jobs", content=body, headers={**auth, "Content-Type": "application/json"})
    assert response.status_code == 413
    assert "1048576 bytes" in response.json()["message"]
    assert "PANOGS_MAX_JSON_BODY_BYTES" in response.json()["message"]


def test_chunked_json_body_over_the_cap_is_refused(client: TestClient, auth: dict[str, str]) -> None:
    def chunks():  # no Content-Length: the cap counts bytes as they arrive
        for _ in range(40):
            yield b" " * 65536

    response = client.post("/v1/jobs", content=chunks(), headers={**auth, "Content-Type": "application/json"})
    assert response.status_code == 413


def test_validation_errors_are_short(client: TestClient, auth: dict[str, str], tiny_zip: bytes) -> None:
    scene = make_scene(client, auth, tiny_zip)
    config = {f"unknown_{i}": {"x": i} for i in range(20_000)}
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], "config": config}, headers=auth)
    assert response.status_code == 422
    assert len(response.content) < 4_000
    many = client.post("/v1/jobs", json={f"k{i}": 1 for i in range(1000)}, headers=auth)
    assert many.status_code == 422
    problems = many.json()["problems"]
    assert len(problems) == 6
    assert problems[-1].startswith("... and ")


def test_refused_creation_with_a_body_leaves_no_upload(
    client: TestClient, auth: dict[str, str], settings: Settings
) -> None:
    headers = {**auth, "Tus-Resumable": "1.0.0", "Upload-Length": "10",
               "Content-Type": "application/offset+octet-stream"}  # fmt: skip
    response = client.post("/v1/uploads", content=b"y" * 20, headers=headers)
    assert response.status_code == 413
    with session_scope(get_session_factory(settings.database)) as session:
        assert session.query(Upload).count() == 0
    uploads = settings.storage / "uploads"
    assert not uploads.exists() or not any(uploads.iterdir())


def test_dead_workers_job_is_requeued_at_once(
    client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
) -> None:
    scene = make_scene(client, auth, tiny_zip)
    ids = [client.post("/v1/jobs", json={"scene_id": scene["id"]}, headers=auth).json()["id"] for _ in range(2)]
    factory = get_session_factory(settings.database)
    with session_scope(factory) as session:
        for ident, pid in zip(ids, (4242, 4243)):
            job = session.get(Job, uuid.UUID(ident))
            assert job is not None
            job.state, job.lease, job.worker = JobState.RUNNING, "l", embedded_worker_name(pid) + str(pid)
        session.commit()
    assert requeue_dead_worker(factory, 4242) == 1
    states = [json.loads(client.get(f"/v1/jobs/{i}", headers=auth).text)["state"] for i in ids]
    assert states == ["queued", "running"]  # only the dead worker's job


def test_supervisor_reports_a_dead_worker_before_restarting_it(monkeypatch: pytest.MonkeyPatch) -> None:
    import threading

    from service import cli

    # A "worker" that dies at once; the supervisor must report its pid (to re-queue its job) before the restart.
    monkeypatch.setattr(cli, "WORKER_COMMAND", ("-c", "raise SystemExit(3)"))
    monkeypatch.setattr(cli, "WORKER_RESTART_DELAY_S", 0.05)
    seen: list[int] = []
    reported = threading.Event()

    def on_exit(pid: int) -> None:
        seen.append(pid)
        reported.set()

    supervisor = cli.WorkerSupervisor(on_exit=on_exit)
    supervisor.start()
    try:
        first = supervisor._proc
        assert first is not None
        assert reported.wait(30)
        assert seen[0] == first.pid
    finally:
        supervisor.stop()
