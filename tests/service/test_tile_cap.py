"""Tiled jobs bounded: a job's ``NxM`` tiles are capped (one per frame of the scene, at least 8, at most
``PANOGS_MAX_TILES_PER_JOB``) with a 422 that says the cap, and a tiled job holds one concurrent-job slot per tile
(the whole limit at most), planned ``auto`` tiles included, on PostgreSQL and SQLite."""

from __future__ import annotations

import uuid
from typing import Any

import pytest
from fastapi.testclient import TestClient
from svc_helpers import RecordingSender, make_scene, new_key
from test_tiled_api import _fan_out

from service.api_app import create_app
from service.settings import Settings

BACKENDS = pytest.mark.parametrize("backend", ["postgres", "sqlite"])


def _job(client: TestClient, auth: dict[str, str], scene: dict[str, Any], tiles: str | None) -> Any:
    body: dict[str, Any] = {"scene_id": scene["id"]}
    if tiles is not None:
        body["tiling"] = {"tiles": tiles}
    return client.post("/v1/jobs", json=body, headers=auth)


@BACKENDS
def test_tiles_past_the_cap_are_refused_naming_it(make_settings: Any, backend: str, tiny_zip: bytes) -> None:
    settings = make_settings(backend, max_tiles_per_job=6)
    auth = new_key(settings)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        scene = make_scene(client, auth, tiny_zip)  # 2 frames: the scene's own cap is the floor of 8
        for tiles in ("99x99", "7x1", "3x3"):
            refused = _job(client, auth, scene, tiles)
            assert refused.status_code == 422, (tiles, refused.text)
            message = refused.json()["message"]
            assert "at most 6" in message
            assert "PANOGS_MAX_TILES_PER_JOB" in message
        assert _job(client, auth, scene, "3x2").status_code == 202
    wide = make_settings(backend)  # the default setting: the 2-frame scene's floor of 8 is the cap
    auth = new_key(wide)
    with TestClient(create_app(wide, sender=RecordingSender(), run_reaper=False)) as client:
        scene = make_scene(client, auth, tiny_zip)
        refused = _job(client, auth, scene, "3x3")
        assert refused.status_code == 422
        assert "9 tiles" in refused.json()["message"]
        assert "at most 8" in refused.json()["message"]
        assert _job(client, auth, scene, "4x2").status_code == 202


@BACKENDS
def test_a_tiled_job_holds_a_slot_per_tile(make_settings: Any, backend: str, tiny_zip: bytes) -> None:
    settings: Settings = make_settings(backend, quota_concurrent_jobs=4)
    auth = new_key(settings)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        scene = make_scene(client, auth, tiny_zip)
        first = _job(client, auth, scene, "3x1")
        assert first.status_code == 202
        assert _job(client, auth, scene, None).status_code == 202  # 3 + 1 slots: the limit
        refused = _job(client, auth, scene, None)
        assert refused.status_code == 429
        assert "hold 4 slot(s)" in refused.json()["message"]
        assert client.post(f"/v1/jobs/{first.json()['id']}/cancel", headers=auth).status_code == 202
        second = _job(client, auth, scene, "2x1")  # the 3 slots came back
        assert second.status_code == 202
        asks = _job(client, auth, scene, "2x1")
        assert asks.status_code == 429
        assert "this job asks 2" in asks.json()["message"]


@BACKENDS
def test_a_job_of_more_tiles_than_the_limit_runs_alone(make_settings: Any, backend: str, tiny_zip: bytes) -> None:
    settings: Settings = make_settings(backend, quota_concurrent_jobs=4)
    auth = new_key(settings)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        scene = make_scene(client, auth, tiny_zip)
        assert _job(client, auth, scene, "4x2").status_code == 202
        assert _job(client, auth, scene, None).status_code == 429


@BACKENDS
def test_planned_auto_tiles_count_as_slots(make_settings: Any, backend: str, tiny_zip: bytes) -> None:
    settings: Settings = make_settings(backend, quota_concurrent_jobs=8, max_tiles_per_job=64)
    auth = new_key(settings)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        scene = make_scene(client, auth, tiny_zip)
        auto = _job(client, auth, scene, "auto")
        assert auto.status_code == 202
        for _ in range(7):  # before its plan, an auto job holds one slot
            assert _job(client, auth, scene, None).status_code == 202
        assert _job(client, auth, scene, None).status_code == 429
    settings = make_settings(backend, quota_concurrent_jobs=9)
    auth = new_key(settings)
    with TestClient(create_app(settings, sender=RecordingSender(), run_reaper=False)) as client:
        scene = make_scene(client, auth, tiny_zip)
        job_id = uuid.UUID(_job(client, auth, scene, "auto").json()["id"])
        _fan_out(settings, job_id)  # planned into 8 tiles: it holds 8 of the 9 slots
        assert _job(client, auth, scene, None).status_code == 202
        assert _job(client, auth, scene, None).status_code == 429
