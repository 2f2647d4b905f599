"""A tiled job through the service, with real processes on PostgreSQL and Redis and the real pipeline: a small
synthetic building asked for 2 x 1 tiles, a worker killed (``kill -9``) while it runs a tile. The tile is re-queued
by the reaper and finished by the other worker, the merge runs once, the job's instances answer and its status lists
its tiles (docs/service.md, "Tiled jobs")."""

from __future__ import annotations

import io
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest
from procs import Procs, wait_for
from service_harness import (
    HEARTBEAT_TIMEOUT_S,
    PG_ADMIN_URL,
    REDIS_URL,
    drop_redis_prefix,
    new_redis_prefix,
    require_postgres,
    require_redis,
    temp_postgres,
)

pytestmark = pytest.mark.slow


def _zip(folder: Path) -> bytes:
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_STORED) as archive:
        for path in sorted(folder.rglob("*")):
            if path.is_file():
                archive.write(path, path.relative_to(folder).as_posix())
    return buffer.getvalue()


def _tiles(database_url: str, job_id: str) -> list[dict[str, Any]]:
    """The job's tile rows as the database holds them: index, kind, state, worker, attempts."""
    from sqlalchemy import create_engine, text

    engine = create_engine(database_url)
    with engine.connect() as conn:
        rows = conn.execute(
            text("SELECT tile_index, kind, state, worker, attempts FROM job_tile WHERE job_id = :id "
                 "ORDER BY tile_index"), {"id": job_id},
        )  # fmt: skip
        out = [dict(r) for r in rows.mappings()]
    engine.dispose()
    return out


@pytest.fixture(scope="module")
def services(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Procs, str, dict[str, str], str]]:
    require_postgres(PG_ADMIN_URL)
    require_redis(REDIS_URL)
    import subprocess
    import sys

    tmp = tmp_path_factory.mktemp("tiled")
    prefix = new_redis_prefix()
    with temp_postgres(PG_ADMIN_URL) as db_url:
        env = {
            "PANOGS_DATABASE_URL": db_url,
            "PANOGS_BROKER_URL": REDIS_URL,
            "PANOGS_BROKER_KEY_PREFIX": prefix,
            "PANOGS_DATA_DIR": str(tmp / "data"),
            "PANOGS_WORKER_THREADS": "1",
            "PANOGS_HEARTBEAT_INTERVAL_S": "0.5",
            "PANOGS_HEARTBEAT_TIMEOUT_S": str(HEARTBEAT_TIMEOUT_S),
            "PANOGS_REAPER_INTERVAL_S": "0.5",
            "PANOGS_PROGRESS_INTERVAL_S": "0.1",
        }
        procs = Procs(env, tmp)
        try:
            key = subprocess.run(
                [sys.executable, "-m", "service.cli", "keys", "create", "--name", "tiled"],
                env=procs.env, cwd=tmp, capture_output=True, text=True, check=True, timeout=120,
            ).stdout.strip()  # fmt: skip
            url = procs.api()
            for name in ("worker1", "worker2"):
                procs.worker(name)
            yield procs, url, {"Authorization": f"Bearer {key}"}, db_url
        finally:
            procs.kill_all()
            drop_redis_prefix(REDIS_URL, prefix)


def test_tiled_job_survives_a_killed_worker_and_merges_once(
    services: tuple[Procs, str, dict[str, str], str], tiny_building: Path
) -> None:
    procs, url, headers, db_url = services
    bundle = tiny_building  # two tiny rooms, the label-set space (the session's, tests/conftest.py: only zipped here)
    logs = lambda: "\n".join(f"--- {n}\n{procs.tail(n, 30)()}" for n in list(procs.procs))  # noqa: E731
    with httpx.Client(base_url=url, headers=headers, timeout=60) as c:
        data = _zip(bundle)
        tus = {"Upload-Length": str(len(data)), "Content-Type": "application/offset+octet-stream"}
        upload = c.post("/v1/uploads", content=data, headers=tus)
        assert upload.status_code == 201, upload.text
        scene = c.post("/v1/scenes", json={"upload_id": upload.json()["id"]})
        assert scene.status_code == 201, scene.text
        body = {
            "scene_id": scene.json()["id"],
            "config": {"appearance": {"enabled": False}},
            "tiling": {"tiles": "2x1"},
        }
        created = c.post("/v1/jobs", json=body)
        assert created.status_code == 202, created.text
        job_id = created.json()["id"]
        seen: dict[str, Any] = {}

        def a_tile_runs() -> bool:
            seen.update(c.get(f"/v1/jobs/{job_id}").json())
            assert seen["state"] not in ("failed", "canceled"), seen
            return any(t["kind"] == "tile" and t["state"] == "running" and t["stage"] for t in seen["tiles"])

        wait_for(a_tile_runs, 300, "a tile to run", lambda: f"{seen}\n{logs()}", 0.1)
        running = next(t for t in _tiles(db_url, job_id) if t["kind"] == "tile" and t["state"] == "running")
        pid = int(running["worker"].rsplit("/", 1)[1])
        victim = next(name for name, p in procs.procs.items() if p.pid == pid)
        procs.kill(victim)  # kill -9 the worker mid-tile

        def done() -> bool:
            seen.update(c.get(f"/v1/jobs/{job_id}").json())
            return seen["state"] in ("succeeded", "failed", "canceled")

        wait_for(done, 600, "the tiled job to end", lambda: f"{seen}\n{logs()}", 0.5)
        assert seen["state"] == "succeeded", f"{seen}\n{logs()}"
        assert seen["progress"] == 1.0
        assert [(t["index"], t["kind"], t["state"]) for t in seen["tiles"]] == [
            (0, "tile", "succeeded"), (1, "tile", "succeeded"), (2, "merge", "succeeded"),
        ]  # fmt: skip
        rows = _tiles(db_url, job_id)
        assert rows[running["tile_index"]]["attempts"] == 2  # re-queued and finished by the other worker
        assert rows[-1]["attempts"] == 1  # the merge ran once
        survivor = next(name for name in procs.procs if name.startswith("worker"))
        log = (procs.log_dir / f"{survivor}.log").read_text(errors="replace")
        assert log.count(f"job {job_id}: merged") == 1, log[-3000:]
        instances = c.get(f"/v1/jobs/{job_id}/instances")
        assert instances.status_code == 200, instances.text
        assert instances.json()["count"] > 0
        names = {a["name"] for a in c.get(f"/v1/jobs/{job_id}/artifacts").json()["data"]}
        assert {"instances.json", "labels.npz", "report.json"} <= names
