"""Faults, with real processes on PostgreSQL and Redis: killed workers, a restarted API, database and broker
outages.

The pipeline is the scripted stand-in (``scripted_pipeline``: known stage times, checkpoints, no torch), so that
"the middle of a job" is a moment the test controls. PostgreSQL and Redis are reached through TCP proxies that
the test can cut, which is how an outage looks to the service without stopping servers others use.
"""

from __future__ import annotations

import itertools
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import pytest
from pipeline_stand_in import ENV as STAND_IN
from procs import REPO, Procs, TcpProxy, wait_for, worker_of
from service_harness import (
    HEARTBEAT_TIMEOUT_S,
    PG_ADMIN_URL,
    REDIS_URL,
    SCRIPTED_PIPELINE,
    drop_redis_prefix,
    new_redis_prefix,
    require_postgres,
    require_redis,
    temp_postgres,
)
from svc_helpers import pack, write_tiny_bundle

pytestmark = pytest.mark.slow

STAGE_S = 0.4  # the scripted job takes 6 stages x 0.4 s


@dataclass
class Cluster:
    procs: Procs
    url: str
    headers: dict[str, str]
    scene_id: str
    pg: TcpProxy
    redis: TcpProxy
    workers: list[str]
    serial: Iterator[int] = field(default_factory=lambda: itertools.count(1))

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=self.headers, timeout=30)

    def new_job(self, **body: Any) -> str:
        # Settings of its own: every job computes its stages (the scene's jobs share checkpoints by key), so that
        # "mid-stage" is a moment each test can catch.
        body.setdefault("config", {"settings": {"validate": next(self.serial)}})
        with self.client() as c:
            response = c.post("/v1/jobs", json={"scene_id": self.scene_id, **body})
        assert response.status_code == 202, response.text
        return str(response.json()["id"])

    def job(self, job_id: str) -> dict[str, Any]:
        with self.client() as c:
            response = c.get(f"/v1/jobs/{job_id}")
        assert response.status_code == 200, response.text
        return dict(response.json())

    # Deadlines, not timings: a job starts within seconds on a quiet machine, but a worker that imports torch
    # while other jobs load both cores took over 60 s (a fresh-clone CI run beside a benchmark).
    def wait_state(self, job_id: str, states: set[str], timeout: float = 180) -> dict[str, Any]:
        seen: dict[str, Any] = {}

        def reached() -> bool:
            seen.update(self.job(job_id))
            return seen["state"] in states

        wait_for(reached, timeout, f"job {job_id} to reach {states}", lambda: f"last: {seen}\n{self.logs()}")
        return seen

    def wait_stage(self, job_id: str, stage: str, timeout: float = 180) -> dict[str, Any]:
        seen: dict[str, Any] = {}

        def reached() -> bool:
            seen.update(self.job(job_id))
            return seen["state"] == "running" and seen["stage"] == stage

        wait_for(reached, timeout, f"job {job_id} to run {stage}", lambda: f"last: {seen}\n{self.logs()}", 0.05)
        return seen

    def worker_of(self, job_id: str) -> str:
        return worker_of(self.procs, self.procs.env["PANOGS_DATABASE_URL_DIRECT"], job_id)

    def add_worker(self) -> str:
        name = f"worker{next(self.serial)}"
        self.workers.append(name)
        self.procs.worker(name)
        return name

    def logs(self) -> str:
        return "\n".join(f"--- {n}\n{self.procs.tail(n, 15)()}" for n in self.procs.procs)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Cluster]:
    require_postgres(PG_ADMIN_URL)
    require_redis(REDIS_URL)
    tmp = tmp_path_factory.mktemp("faults")
    prefix = new_redis_prefix()
    redis_port = int(REDIS_URL.split(":")[2].split("/")[0])
    with temp_postgres(PG_ADMIN_URL) as db_url:
        from sqlalchemy import make_url

        pg_proxy = TcpProxy(make_url(db_url).port or 5432)
        redis_proxy = TcpProxy(redis_port)
        env = {
            "PANOGS_DATABASE_URL": make_url(db_url).set(port=pg_proxy.port).render_as_string(hide_password=False),
            "PANOGS_DATABASE_URL_DIRECT": db_url,
            "PANOGS_BROKER_URL": f"redis://127.0.0.1:{redis_proxy.port}/{REDIS_URL.rsplit('/', 1)[1]}",
            "PANOGS_BROKER_KEY_PREFIX": prefix,
            "PANOGS_DATA_DIR": str(tmp / "data"),
            STAND_IN: SCRIPTED_PIPELINE,
            "PANOGS_SCRIPTED_STAGE_S": str(STAGE_S),
            "PANOGS_HEARTBEAT_INTERVAL_S": "0.5",
            "PANOGS_HEARTBEAT_TIMEOUT_S": str(HEARTBEAT_TIMEOUT_S),
            "PANOGS_REAPER_INTERVAL_S": "0.5",
            "PANOGS_PROGRESS_INTERVAL_S": "0.1",
            "PANOGS_MAX_ATTEMPTS": "2",
            "PANOGS_TRANSIENT_RETRY_S": "30",
        }
        procs = Procs(env, tmp)
        try:
            key = subprocess.run(
                [sys.executable, "-m", "service.cli", "keys", "create", "--name", "faults"],
                env=procs.env, cwd=tmp, capture_output=True, text=True, check=True, timeout=120,
            ).stdout.strip()  # fmt: skip
            url = procs.api()
            headers = {"Authorization": f"Bearer {key}"}
            cluster = Cluster(procs, url, headers, "", pg_proxy, redis_proxy, [])
            cluster.scene_id = _scene(cluster, tmp)
            for _ in range(2):
                cluster.add_worker()
            yield cluster
        finally:
            procs.kill_all()  # the API and the workers: nothing here checks their shutdown
            pg_proxy.close()
            redis_proxy.close()
            drop_redis_prefix(REDIS_URL, prefix)


def _scene(cluster: Cluster, tmp: Path) -> str:
    data = pack(write_tiny_bundle(tmp / "bundle"))
    with cluster.client() as c:
        headers = {"Upload-Length": str(len(data)), "Content-Type": "application/offset+octet-stream"}
        created = c.post("/v1/uploads", content=data, headers=headers)
        assert created.status_code == 201, created.text
        scene = c.post("/v1/scenes", json={"upload_id": created.json()["id"]})
        assert scene.status_code == 201, scene.text
        return str(scene.json()["id"])


def test_killed_worker_job_finished_by_another(cluster: Cluster) -> None:
    job_id = cluster.new_job()
    cluster.wait_stage(job_id, "fusion")
    victim = cluster.worker_of(job_id)
    cluster.procs.kill(victim)  # kill -9 the whole worker
    cluster.workers.remove(victim)
    done = cluster.wait_state(job_id, {"succeeded", "failed"}, timeout=HEARTBEAT_TIMEOUT_S + 30)
    assert done["state"] == "succeeded", done
    assert done["attempts"] == 2
    assert set(done["stage_timings"]) >= {"validate", "primitives", "export"}
    cluster.add_worker()


def test_job_whose_workers_keep_dying_fails_with_a_reason(cluster: Cluster) -> None:
    job_id = cluster.new_job()
    for attempt in (1, 2):  # PANOGS_MAX_ATTEMPTS=2
        wait_for(lambda a=attempt: cluster.job(job_id)["attempts"] == a, HEARTBEAT_TIMEOUT_S + 30,
                 f"attempt {attempt}", cluster.logs)  # fmt: skip
        cluster.wait_stage(job_id, "primitives")
        victim = cluster.worker_of(job_id)
        cluster.procs.kill(victim)
        cluster.workers.remove(victim)
        cluster.add_worker()
    failed = cluster.wait_state(job_id, {"failed", "succeeded"}, timeout=HEARTBEAT_TIMEOUT_S + 30)
    assert failed["state"] == "failed"
    assert failed["error"]["type"] == "WorkerLost"
    assert "stopped responding" in failed["error"]["message"]


def test_api_restart_loses_nothing(cluster: Cluster) -> None:
    job_id = cluster.new_job()
    data = b"z" * 3_000_000
    with cluster.client() as c:
        upload = c.post("/v1/uploads", headers={"Upload-Length": str(len(data))}).json()
        patch = {"Content-Type": "application/offset+octet-stream", "Upload-Offset": "0"}
        assert c.patch(f"/v1/uploads/{upload['id']}", content=data[:1_000_000], headers=patch).status_code == 204
    cluster.wait_stage(job_id, "primitives")
    port = int(cluster.url.rsplit(":", 1)[1])
    cluster.procs.kill("api")
    time.sleep(1.0)  # the job runs on while no API is up
    cluster.url = cluster.procs.api(port=port)
    done = cluster.wait_state(job_id, {"succeeded", "failed"})
    assert done["state"] == "succeeded"
    assert done["attempts"] == 1
    with cluster.client() as c:
        offset = int(c.head(f"/v1/uploads/{upload['id']}").headers["upload-offset"])
        assert offset == 1_000_000
        patch = {"Content-Type": "application/offset+octet-stream", "Upload-Offset": str(offset)}
        assert c.patch(f"/v1/uploads/{upload['id']}", content=data[offset:], headers=patch).status_code == 204
        assert c.get(f"/v1/uploads/{upload['id']}").json()["state"] == "complete"


def test_database_briefly_away(cluster: Cluster) -> None:
    job_id = cluster.new_job()
    cluster.wait_stage(job_id, "primitives")
    with cluster.pg.outage(2.0):
        time.sleep(0.5)
        with cluster.client() as c:
            response = c.get(f"/v1/jobs/{job_id}")
        assert response.status_code == 503, response.text
        assert response.json()["type"] == "service_unavailable"
    done = cluster.wait_state(job_id, {"succeeded", "failed"})
    assert done["state"] == "succeeded", done
    assert done["attempts"] == 1


def test_broker_briefly_away(cluster: Cluster) -> None:
    running = cluster.new_job()
    cluster.wait_stage(running, "primitives")
    with cluster.redis.outage(2.0):
        created_during = cluster.new_job()  # accepted; published by the reaper once the broker is back
    for job_id in (running, created_during):
        done = cluster.wait_state(job_id, {"succeeded", "failed"}, timeout=90)
        assert done["state"] == "succeeded", done


def test_nothing_left_running(cluster: Cluster) -> None:
    with cluster.client() as c:
        wait_for(lambda: c.get("/v1/jobs", params={"state": "running"}).json()["count"] == 0, 30,
                 "no job left running", cluster.logs)  # fmt: skip
        assert c.get("/v1/jobs", params={"state": "queued"}).json()["count"] == 0


def test_processes_do_not_import_torch(cluster: Cluster) -> None:
    """The API process never imports torch (checked from outside, in /proc)."""
    pid = cluster.procs.procs["api"].pid
    maps = Path(f"/proc/{pid}/maps").read_text()
    assert "libtorch" not in maps
    assert REPO.is_dir()
