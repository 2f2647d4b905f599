"""Two hosts, no shared directory: the API and the workers as separate processes, each with a data folder of its
own, their objects only in S3 (a SeaweedFS of this module), PostgreSQL and Redis as in the other process tests.

The session of the README against them (a tus upload in 4 MiB PATCHes and a single-request upload, a scene, a job,
polling, instances, a query, a ranged download answered 206 with the same bytes, a delete), then faults: a worker
killed mid-stage (another finishes the job from the checkpoints it stored), SeaweedFS restarted while a job is
queued and while one runs (the job succeeds), and an aborted upload (no multipart part left). The pipeline is the
scripted stand-in (known stage times, checkpoints, no torch), so that "mid-stage" is a moment the test controls.
"""

from __future__ import annotations

import base64
import hashlib
import itertools
import os
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
from procs import Procs, job_row, wait_for, worker_of
from seaweedfs import SeaweedFS, seaweedfs
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
from svc_helpers import VOCABULARY_8D, pack, write_tiny_bundle

pytestmark = pytest.mark.slow

STAGE_S = 0.6  # each of the scripted job's 7 stages
MIB = 1024 * 1024
TUS = {"Tus-Resumable": "1.0.0", "Content-Type": "application/offset+octet-stream"}


@dataclass
class Hosts:
    procs: Procs
    s3: SeaweedFS
    url: str
    headers: dict[str, str]
    tmp: Path
    workers: list[str] = field(default_factory=list)
    serial: Iterator[int] = field(default_factory=lambda: itertools.count(1))

    def client(self) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=self.headers, timeout=60)

    def add_worker(self) -> str:
        name = f"worker{next(self.serial)}"
        self.workers.append(name)
        self.procs.worker(name, PANOGS_DATA_DIR=str(self.tmp / f"{name}-data"))
        return name

    def job(self, job_id: str) -> dict[str, Any]:
        with self.client() as c:
            answer = c.get(f"/v1/jobs/{job_id}")
        assert answer.status_code == 200, answer.text
        return dict(answer.json())

    def wait(self, job_id: str, done: Any, what: str, timeout: float = 180, interval: float = 0.2) -> dict[str, Any]:
        seen: dict[str, Any] = {}

        def reached() -> bool:
            seen.update(self.job(job_id))
            return bool(done(seen))

        wait_for(reached, timeout, what, lambda: f"last: {seen}\n{self.logs()}", interval)
        return seen

    def finished(self, job_id: str, timeout: float = 180) -> dict[str, Any]:
        return self.wait(job_id, lambda j: j["state"] in ("succeeded", "failed", "canceled"), f"job {job_id}", timeout)

    def worker_of(self, job_id: str) -> str:
        return worker_of(self.procs, self.procs.env["PANOGS_DATABASE_URL"], job_id)

    def job_row(self, job_id: str) -> dict[str, Any]:
        return job_row(self.procs.env["PANOGS_DATABASE_URL"], job_id)

    def keys(self, prefix: str) -> list[str]:
        client = self.s3.client()
        pages = client.get_paginator("list_objects_v2").paginate(Bucket=self.s3.bucket, Prefix=f"two-hosts/{prefix}")
        return [item["Key"] for page in pages for item in page.get("Contents", [])]

    def logs(self) -> str:
        return (
            "\n".join(f"--- {n}\n{self.procs.tail(n, 15)()}" for n in self.procs.procs)
            + f"\n--- s3\n{self.s3.tail(10)}"
        )


def _files(folder: Path) -> list[str]:
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file()) if folder.exists() else []


@pytest.fixture(scope="module")
def hosts(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Hosts]:
    require_postgres(PG_ADMIN_URL)
    require_redis(REDIS_URL)
    tmp = tmp_path_factory.mktemp("two-hosts")
    prefix = new_redis_prefix()
    with seaweedfs(tmp / "seaweedfs") as s3, temp_postgres(PG_ADMIN_URL) as db_url:
        env = {
            **s3.env("two-hosts"),
            "PANOGS_DATABASE_URL": db_url,
            "PANOGS_BROKER_URL": REDIS_URL,
            "PANOGS_BROKER_KEY_PREFIX": prefix,
            STAND_IN: SCRIPTED_PIPELINE,
            "PANOGS_SCRIPTED_STAGE_S": str(STAGE_S),
            "PANOGS_HEARTBEAT_INTERVAL_S": "0.5",
            "PANOGS_HEARTBEAT_TIMEOUT_S": str(HEARTBEAT_TIMEOUT_S),
            "PANOGS_REAPER_INTERVAL_S": "0.5",
            "PANOGS_PROGRESS_INTERVAL_S": "0.1",
            "PANOGS_MAX_ATTEMPTS": "3",
        }
        procs = Procs(env, tmp)
        api_data = tmp / "api-data"
        try:
            key = subprocess.run(
                [sys.executable, "-m", "service.cli", "keys", "create", "--name", "two-hosts"],
                env={**procs.env, "PANOGS_DATA_DIR": str(api_data)}, cwd=tmp, capture_output=True, text=True,
                check=True, timeout=120,
            ).stdout.strip()  # fmt: skip
            url = procs.api(PANOGS_DATA_DIR=str(api_data))
            hosts = Hosts(procs, s3, url, {"Authorization": f"Bearer {key}"}, tmp)
            for _ in range(2):
                hosts.add_worker()
            yield hosts
        finally:
            procs.kill_all()
            drop_redis_prefix(REDIS_URL, prefix)


def _tus(c: httpx.Client, data: bytes, chunk: int) -> str:
    sha = base64.b64encode(hashlib.sha256(data).hexdigest().encode()).decode()
    created = c.post(
        "/v1/uploads", headers={**TUS, "Upload-Length": str(len(data)), "Upload-Metadata": f"sha256 {sha}"}
    )
    assert created.status_code == 201, created.text
    upload_id = str(created.json()["id"])
    for offset in range(0, len(data), chunk):
        answer = c.patch(f"/v1/uploads/{upload_id}", content=data[offset : offset + chunk],
                         headers={**TUS, "Upload-Offset": str(offset)})  # fmt: skip
        assert answer.status_code == 204, answer.text
    return upload_id


def _scene(hosts: Hosts) -> str:
    data = pack(write_tiny_bundle(hosts.tmp / "bundle"))
    with hosts.client() as c:
        created = c.post("/v1/uploads", content=data, headers={**TUS, "Upload-Length": str(len(data))})  # one request
        assert created.status_code == 201, created.text
        scene = c.post("/v1/scenes", json={"upload_id": created.json()["id"]})
        assert scene.status_code == 201, scene.text
        return str(scene.json()["id"])


def _job(hosts: Hosts, scene_id: str, config: dict[str, Any] | None = None) -> str:
    body = {"scene_id": scene_id, "config": config or {}, "vocabulary": VOCABULARY_8D}
    with hosts.client() as c:
        answer = c.post("/v1/jobs", json=body)
    assert answer.status_code == 202, answer.text
    return str(answer.json()["id"])


def test_session_across_two_hosts(hosts: Hosts) -> None:
    blob = os.urandom(13 * MIB + 17)
    with hosts.client() as c:
        upload_id = _tus(c, blob, 4 * MIB)  # 4 MiB PATCHes: parts of a multipart upload
        status = c.get(f"/v1/uploads/{upload_id}").json()
        assert status["state"] == "complete"
        assert status["sha256"] == hashlib.sha256(blob).hexdigest()
        assert c.delete(f"/v1/uploads/{upload_id}").status_code == 204
    scene_id = _scene(hosts)
    job_id = _job(hosts, scene_id)
    done = hosts.finished(job_id)
    assert done["state"] == "succeeded", done
    with hosts.client() as c:
        instances = c.get(f"/v1/jobs/{job_id}/instances").json()["data"]
        assert [i["class_name"] for i in instances] == ["chair", "table"]
        hits = c.post(f"/v1/jobs/{job_id}/query", json={"text": "chair", "top_k": 1, "min_score": 0}).json()["hits"]
        assert hits[0]["class_name"] == "chair"
        whole = c.get(f"/v1/jobs/{job_id}/artifacts/labels.npz")
        assert whole.status_code == 200
        part = c.get(f"/v1/jobs/{job_id}/artifacts/labels.npz", headers={"Range": "bytes=100-"})
        assert part.status_code == 206
        assert part.content == whole.content[100:]
    assert not any(done["stage_cached"].values())  # the scene's first job computed every stage
    rerun = hosts.finished(_job(hosts, scene_id, {"settings": {"clustering": 2}}))  # other clustering settings
    assert rerun["state"] == "succeeded", rerun
    reused = {"validate", "primitives", "fusion"}  # the stages before clustering, from the first job's checkpoints
    assert rerun["stage_cached"] == {stage: stage in reused for stage in done["stage_timings"]}
    checkpoints = [k for k in hosts.keys(f"scenes/{scene_id}/stages/") if k.endswith(".ckpt")]
    assert len(checkpoints) == 2 * len(done["stage_timings"]) - len(reused)  # one per key, the rerun's new ones too
    for job in (job_id, rerun["id"]):  # kept once: under the scene, not again with the job's files
        assert not [k for k in hosts.keys(f"artifacts/{job}/") if k.endswith(".done")], job
    # Neither host holds the other's files: the API wrote no object to its disk, the workers' scratch is gone.
    assert _files(hosts.tmp / "api-data" / "storage") == []
    assert not [f for f in _files(hosts.tmp / "api-data") if "scratch" in f]
    for name in hosts.workers:  # nothing but the bundle cache: this scene's bundle, kept for its next job
        kept = _files(hosts.tmp / f"{name}-data")
        assert all(f.startswith(f"work/bundles/{scene_id}") for f in kept), (name, kept)
    with hosts.client() as c:
        assert c.delete(f"/v1/scenes/{scene_id}").status_code == 204
    assert hosts.keys(f"scenes/{scene_id}/") == []
    assert hosts.keys(f"artifacts/{job_id}/") == []
    assert hosts.keys(f"uploads/{upload_id}/") == []


def test_killed_worker_job_finished_by_another(hosts: Hosts) -> None:
    scene_id = _scene(hosts)
    job_id = _job(hosts, scene_id)
    hosts.wait(job_id, lambda j: j["state"] == "running" and j["stage"] == "clustering", "clustering", interval=0.05)
    victim = hosts.worker_of(job_id)
    hosts.procs.kill(victim)  # kill -9: its scratch folder stays on its disk, nobody reads it
    hosts.workers.remove(victim)
    done = hosts.finished(job_id, timeout=HEARTBEAT_TIMEOUT_S + 120)
    assert done["state"] == "succeeded", done
    assert hosts.job_row(job_id)["attempts"] == 2
    hosts.add_worker()


@pytest.mark.parametrize("when", ["queued", "running"])
def test_seaweedfs_restart_while_a_job_is(hosts: Hosts, when: str) -> None:
    scene_id = _scene(hosts)
    if when == "queued":
        hosts.s3.kill()
        job_id = _job(hosts, scene_id)  # the job row and its message need no storage
        time.sleep(2)  # a worker claims it, cannot fetch the bundle, hands it back
    else:
        job_id = _job(hosts, scene_id)
        hosts.wait(job_id, lambda j: j["state"] == "running" and j["stage"] == "fusion", "fusion", interval=0.05)
        hosts.s3.kill()
        time.sleep(2)
    hosts.s3.start()  # the same ports and data
    done = hosts.finished(job_id, timeout=240)
    assert done["state"] == "succeeded", f"{done}\n{hosts.logs()}"


def test_an_aborted_upload_leaves_no_parts(hosts: Hosts) -> None:
    with hosts.client() as c:
        created = c.post("/v1/uploads", headers={**TUS, "Upload-Length": str(40 * MIB)})
        upload_id = created.json()["id"]
        for offset in range(0, 12 * MIB, 4 * MIB):
            c.patch(
                f"/v1/uploads/{upload_id}", content=os.urandom(4 * MIB), headers={**TUS, "Upload-Offset": str(offset)}
            )
        uploads = hosts.s3.client().list_multipart_uploads(
            Bucket=hosts.s3.bucket, Prefix=f"two-hosts/uploads/{upload_id}/"
        )
        assert len(uploads.get("Uploads", [])) == 1
        assert c.delete(f"/v1/uploads/{upload_id}").status_code == 204
    uploads = hosts.s3.client().list_multipart_uploads(Bucket=hosts.s3.bucket, Prefix=f"two-hosts/uploads/{upload_id}/")
    assert uploads.get("Uploads", []) == []
    assert hosts.keys(f"uploads/{upload_id}/") == []
