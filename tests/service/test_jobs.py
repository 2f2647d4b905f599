"""Jobs over REST: create (202, enqueued by name after commit, idempotent), list, get, cancel; tenant
isolation."""

from __future__ import annotations

import uuid
from collections.abc import Callable
from typing import Any

import pytest
from fastapi.testclient import TestClient
from svc_helpers import BOTH_BACKENDS, RecordingSender, make_scene, new_key

from service.api_app import create_app
from service.broker import TaskName
from service.db.models import Job, JobState
from service.db.session import get_session_factory, session_scope
from service.settings import Settings


@pytest.fixture
def scene(client: TestClient, auth: dict[str, str], tiny_zip: bytes) -> dict[str, Any]:
    return make_scene(client, auth, tiny_zip)


def _create(client: TestClient, auth: dict[str, str], scene_id: str, **body: Any) -> Any:
    headers = {**auth, **body.pop("headers", {})}
    return client.post("/v1/jobs", json={"scene_id": scene_id, **body}, headers=headers)


def _set_state(settings: Settings, job_id: str, **values: Any) -> None:
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, uuid.UUID(job_id))
        assert job is not None
        for k, v in values.items():
            setattr(job, k, v)
        session.commit()


class TestCreate:
    @BOTH_BACKENDS
    def test_queued_and_sent_after_commit(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], sender: RecordingSender
    ) -> None:
        response = _create(client, auth, scene["id"], config={"stage_s": 0.5}, vocabulary="scannet20")
        assert response.status_code == 202, response.text
        job = response.json()
        assert response.headers["location"] == f"/v1/jobs/{job['id']}"
        assert job["state"] == "queued"
        assert job["progress"] == 0.0
        assert job["config"] == {"stage_s": 0.5}
        assert job["vocabulary"] == "scannet20"
        assert job["error"] is None
        assert sender.calls == [(TaskName.RUN_JOB.value, [job["id"]], "cpu")]

    def test_idempotency_key(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], sender: RecordingSender
    ) -> None:
        key = {"Idempotency-Key": "retry-me"}
        first = _create(client, auth, scene["id"], headers=key)
        again = _create(client, auth, scene["id"], headers=key)
        assert first.status_code == again.status_code == 202
        assert first.json()["id"] == again.json()["id"]
        assert len(sender.calls) == 1
        other = _create(client, auth, scene["id"], headers=key, vocabulary="matterport21")
        assert other.status_code == 422
        assert "Idempotency-Key" in other.json()["message"]
        assert _create(client, auth, scene["id"]).json()["id"] != first.json()["id"]

    def test_same_key_other_tenant_is_independent(
        self, client: TestClient, auth: dict[str, str], settings: Settings, tiny_zip: bytes
    ) -> None:
        other = new_key(settings, "bob")
        scene_a = make_scene(client, auth, tiny_zip)
        scene_b = make_scene(client, other, tiny_zip)
        a = _create(client, auth, scene_a["id"], headers={"Idempotency-Key": "k"}).json()
        b = _create(client, other, scene_b["id"], headers={"Idempotency-Key": "k"}).json()
        assert a["id"] != b["id"]

    def test_unknown_config_key(self, client: TestClient, auth: dict[str, str], scene: dict[str, Any]) -> None:
        response = _create(client, auth, scene["id"], config={"stage_seconds": 1})
        assert response.status_code == 422
        assert "stage_seconds" in response.json()["problems"][0]

    def test_real_pipeline_config_is_checked(self, make_settings: Callable[..., Settings], tiny_zip: bytes) -> None:
        pytest.importorskip("panogs_core.pipeline.config", reason="the core's PipelineConfig is not importable yet")
        settings = make_settings("postgres", stand_in=None)
        with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
            auth = new_key(settings)
            scene = make_scene(client, auth, tiny_zip)
            response = _create(client, auth, scene["id"], config={"clustering": {"no_such_threshold": 1}})
            assert response.status_code == 422
            assert "no_such_threshold" in response.json()["problems"][0]

    def test_unknown_scene(self, client: TestClient, auth: dict[str, str]) -> None:
        response = _create(client, auth, str(uuid.uuid4()))
        assert response.status_code == 404
        assert response.json()["type"] == "not_found"

    def test_broker_away_then_reaper_publishes(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], sender: RecordingSender,
        settings: Settings,
    ) -> None:  # fmt: skip
        from service.reaper import DISPATCH_GRACE_S, sweep
        from service.storage import Storage

        sender.fail = True
        response = _create(client, auth, scene["id"])
        assert response.status_code == 202  # accepted: the job waits in the database
        job_id = response.json()["id"]
        sender.fail = False
        factory = get_session_factory(settings.database)
        _set_state(settings, job_id, created_at=_ago(DISPATCH_GRACE_S + 1))
        counts = sweep(settings, factory, sender, Storage(settings.storage))
        assert counts["published"] == 1
        assert sender.calls == [(TaskName.RUN_JOB.value, [job_id], "cpu")]
        assert sweep(settings, factory, sender, Storage(settings.storage))["published"] == 0


class TestReadAndCancel:
    def test_get_list_filters(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        ids = [_create(client, auth, scene["id"]).json()["id"] for _ in range(3)]
        _set_state(settings, ids[0], state=JobState.RUNNING, stage="fusion", progress=0.4)
        got = client.get(f"/v1/jobs/{ids[0]}", headers=auth).json()
        assert (got["state"], got["stage"], got["progress"]) == ("running", "fusion", 0.4)
        everything = client.get("/v1/jobs", headers=auth).json()
        assert everything["count"] == 3
        assert [j["id"] for j in everything["data"]] == ids[::-1]  # newest first
        running = client.get("/v1/jobs", params={"state": "running"}, headers=auth).json()
        assert [j["id"] for j in running["data"]] == [ids[0]]
        page = client.get("/v1/jobs", params={"limit": 2, "offset": 2}, headers=auth).json()
        assert page["count"] == 3
        assert len(page["data"]) == 1
        assert page["page"] == {"limit": 2, "offset": 2}
        by_scene = client.get("/v1/jobs", params={"scene_id": str(uuid.uuid4())}, headers=auth).json()
        assert by_scene["count"] == 0
        assert client.get("/v1/jobs", params={"state": "bogus"}, headers=auth).status_code == 422

    def test_cancel_queued_and_running(
        self, client: TestClient, auth: dict[str, str], scene: dict[str, Any], settings: Settings
    ) -> None:
        queued = _create(client, auth, scene["id"]).json()["id"]
        canceled = client.post(f"/v1/jobs/{queued}/cancel", headers=auth)
        assert canceled.status_code == 202
        assert canceled.json()["state"] == "canceled"
        running = _create(client, auth, scene["id"]).json()["id"]
        _set_state(settings, running, state=JobState.RUNNING)
        asked = client.post(f"/v1/jobs/{running}/cancel", headers=auth).json()
        assert asked["state"] == "running"
        assert asked["cancel_requested"] is True
        _set_state(settings, running, state=JobState.SUCCEEDED)
        assert client.post(f"/v1/jobs/{running}/cancel", headers=auth).status_code == 409

    def test_other_tenant_sees_404(
        self, client: TestClient, auth: dict[str, str], other_auth: dict[str, str], scene: dict[str, Any]
    ) -> None:
        job_id = _create(client, auth, scene["id"]).json()["id"]
        assert _create(client, other_auth, scene["id"]).status_code == 404
        for path in ("", "/instances", "/artifacts", "/artifacts/panoptic.ply"):
            assert client.get(f"/v1/jobs/{job_id}{path}", headers=other_auth).status_code == 404
        assert client.post(f"/v1/jobs/{job_id}/cancel", headers=other_auth).status_code == 404
        assert client.post(f"/v1/jobs/{job_id}/query", json={"text": "chair"}, headers=other_auth).status_code == 404
        assert client.get("/v1/jobs", headers=other_auth).json()["count"] == 0

    def test_results_before_success(self, client: TestClient, auth: dict[str, str], scene: dict[str, Any]) -> None:
        job_id = _create(client, auth, scene["id"]).json()["id"]
        response = client.get(f"/v1/jobs/{job_id}/instances", headers=auth)
        assert response.status_code == 409
        assert "queued" in response.json()["message"]


def _ago(seconds: float) -> Any:
    from datetime import timedelta

    from service.db.base import utcnow

    return utcnow() - timedelta(seconds=seconds)
