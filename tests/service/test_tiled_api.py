"""Tiled jobs as the API and the database see them (docs/service.md, "Tiled jobs"): the request's ``tiling``, the
status listing the tiles with the job's progress weighted by their cost, and the fan-in's count when tiles finish at
the same moment, on PostgreSQL and SQLite."""

from __future__ import annotations

import threading
import uuid
from typing import Any

from fastapi.testclient import TestClient
from sqlalchemy import select
from svc_helpers import BOTH_BACKENDS, make_scene

from service.db import crud
from service.db.models import Job, JobState, JobTile, TileKind, TileState
from service.db.session import get_session_factory, session_scope
from service.settings import Settings

WEIGHTS = [3.0, 1.0, 2.0, 2.0, 1.0, 3.0, 2.0, 2.0]  # bytes the plan estimated per tile; the merge: 1.0


def _new_job(client: TestClient, auth: dict[str, str], tiny_zip: bytes, **body: Any) -> dict[str, Any]:
    scene = make_scene(client, auth, tiny_zip)
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], **body}, headers=auth)
    assert response.status_code == 202, response.text
    return dict(response.json())


def _fan_out(settings: Settings, job_id: uuid.UUID) -> list[uuid.UUID]:
    """The job as its first task leaves it when the plan tiles it: running, a row per tile and a pending merge;
    every tile then claimed by a task of its own (lease ``lease-<index>``). Returns the tiles' ids."""
    factory = get_session_factory(settings.database)
    with session_scope(factory) as session:
        assert crud.claim_job(session, job_id, "job", "w/1", crud.stale_cutoff(60)) is not None
        rows = [
            JobTile(
                id=uuid.uuid4(),
                job_id=job_id,
                tile_index=i,
                kind=TileKind.TILE,
                name=f"tile-{i:03d}",
                state=TileState.QUEUED,
                weight=w,
                progress=0.0,
                attempts=0,
            )
            for i, w in enumerate(WEIGHTS)
        ]
        rows.append(JobTile(id=uuid.uuid4(), job_id=job_id, tile_index=len(WEIGHTS), kind=TileKind.MERGE,
                            name="merge", state=TileState.PENDING, weight=1.0, progress=0.0, attempts=0))  # fmt: skip
        ids = [r.id for r in rows[:-1]]
        assert crud.fan_out(session, job_id, "job", rows)
        for i, ident in enumerate(ids):
            assert crud.claim_tile(session, ident, f"lease-{i}", "w/2", crud.stale_cutoff(60)) is not None
    return ids


@BOTH_BACKENDS
def test_a_job_asks_for_tiles_and_bad_settings_are_refused(
    client: TestClient, auth: dict[str, str], tiny_zip: bytes
) -> None:
    job = _new_job(client, auth, tiny_zip, tiling={"tiles": "2x1", "halo_m": 0.5})
    assert job["tiling"] == {"tiles": "2x1", "halo_m": 0.5, "memory_target_bytes": None, "whole_limit_bytes": None}
    assert job["tiles"] == []  # not planned yet
    assert _new_job(client, auth, tiny_zip)["tiling"] is None
    scene = make_scene(client, auth, tiny_zip)
    for bad in ({"tiles": "2x"}, {"tiles": "0x2"}, {"tiles": "2x2", "halo_m": 0.3}, {"tiles": "auto", "extra": 1}):
        response = client.post("/v1/jobs", json={"scene_id": scene["id"], "tiling": bad}, headers=auth)
        assert response.status_code == 422, (bad, response.text)
    # halo_m must be whole cells of the planner's grid: the planner's own message comes back
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], "tiling": {"halo_m": 0.3}}, headers=auth)
    assert "tiling.halo_m" in response.text


@BOTH_BACKENDS
def test_status_lists_the_tiles_and_weights_their_progress(
    client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings
) -> None:
    job_id = uuid.UUID(_new_job(client, auth, tiny_zip, tiling={"tiles": "4x2"})["id"])
    ids = _fan_out(settings, job_id)
    with session_scope(get_session_factory(settings.database)) as session:
        assert crud.update_tile_running(session, ids[0], job_id, "lease-0", stage="fusion", progress=0.5)
        assert crud.update_tile_running(session, ids[5], job_id, "lease-5", stage="labeling", progress=1.0)
        assert not crud.update_tile_running(session, ids[1], job_id, "another", progress=0.9)  # not its lease
    status = client.get(f"/v1/jobs/{job_id}", headers=auth).json()
    assert status["stage"] == "tiles"
    assert [(t["index"], t["kind"], t["state"]) for t in status["tiles"]] == [
        *[(i, "tile", "running") for i in range(8)], (8, "merge", "pending"),
    ]  # fmt: skip
    assert status["tiles"][0]["stage"] == "fusion"
    assert status["tiles"][0]["progress"] == 0.5
    total = sum(WEIGHTS) + 1.0
    assert abs(status["progress"] - (3.0 * 0.5 + 3.0 * 1.0) / total) < 1e-9
    listed = client.get("/v1/jobs", headers=auth).json()["data"]
    assert next(j for j in listed if j["id"] == str(job_id))["tiles"] == status["tiles"]


@BOTH_BACKENDS
def test_tiles_finishing_at_once_publish_the_merge_once(
    client: TestClient, auth: dict[str, str], tiny_zip: bytes, settings: Settings
) -> None:
    job_id = uuid.UUID(_new_job(client, auth, tiny_zip, tiling={"tiles": "4x2"})["id"])
    ids = _fan_out(settings, job_id)
    factory = get_session_factory(settings.database)
    start = threading.Barrier(len(ids))
    merges: list[uuid.UUID | None] = []
    done: list[bool] = []
    errors: list[BaseException] = []

    def finish(i: int) -> None:
        try:
            start.wait(timeout=30)
            with session_scope(factory) as session:
                ok, merge_id = crud.finish_tile(session, ids[i], job_id, f"lease-{i}")
            done.append(ok)
            merges.append(merge_id)
        except BaseException as exc:  # the assertion below names it
            errors.append(exc)

    threads = [threading.Thread(target=finish, args=(i,)) for i in range(len(ids))]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert not errors, errors
    assert done == [True] * len(ids)
    assert len([m for m in merges if m is not None]) == 1  # exactly one tile saw none left
    with session_scope(factory) as session:
        merge = session.scalars(select(JobTile).where(JobTile.kind == TileKind.MERGE)).one()
        assert merge.state == TileState.QUEUED
        assert merge.id in merges
        job = session.get(Job, job_id)
        assert job is not None
        assert job.state == JobState.RUNNING
        assert abs(job.progress - sum(WEIGHTS) / (sum(WEIGHTS) + 1.0)) < 1e-9
        # A tile recorded twice (a late duplicate under its old lease) changes nothing.
        assert crud.finish_tile(session, ids[0], job_id, "lease-0") == (False, None)
