"""Service benchmarks: status polls while a job runs, warm query latency, upload throughput, service overhead.

Usage:
    python bench/service/bench_service.py [polls query upload overhead] [--backend scaled|embedded]
        [--preset tiny] [--seconds 10] [--upload-mib 512] [--clients 4]

Runs the service as real processes with the docker-compose commands: ``scaled`` is uvicorn + a Celery worker
on the PostgreSQL and Redis of this machine (a throwaway database and Redis key prefix), ``embedded`` is
``panogs serve`` on SQLite and the filesystem broker. Prints one table, with the service's targets
(docs/service.md) beside each number. Numbers depend on the machine: the client, the API and the worker share
its cores.
"""

from __future__ import annotations

import argparse
import asyncio
import base64
import hashlib
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests" / "support"))
os.environ.setdefault("HF_HUB_OFFLINE", "1")

import httpx
import numpy as np
from service_harness import (
    DEFAULT_PG_ADMIN_URL,
    DEFAULT_REDIS_URL,
    REPO,
    Procs,
    drop_redis_prefix,
    free_port,
    new_redis_prefix,
    temp_postgres,
    wait_for,
)

TARGETS = {
    "status polls / s": ">= 300",
    "query p95 ms (class name)": "<= 50",
    "query p95 ms (vector)": "<= 50",
    "query p95 ms (free text)": "<= 50",
    "upload MB/s (one request)": ">= 100",
    "upload MB/s (64 MiB PATCHes)": ">= 100",
    "service overhead %": "<= 10",
}


class Service:
    """A running deployment and a key."""

    def __init__(self, url: str, headers: dict[str, str], storage: Path, database: str) -> None:
        self.url, self.headers, self.storage, self.database = url, headers, storage, database

    def client(self, timeout: float = 120) -> httpx.Client:
        return httpx.Client(base_url=self.url, headers=self.headers, timeout=timeout)


@contextmanager
def deployment(backend: str, tmp: Path, extra: dict[str, str]) -> Iterator[Service]:
    with ExitStack() as stack:
        env: dict[str, str] = {"PANOGS_DATA_DIR": str(tmp / "data"), "PANOGS_LOG_LEVEL": "WARNING", **extra}
        if backend == "scaled":
            db_url = stack.enter_context(temp_postgres(DEFAULT_PG_ADMIN_URL))
            prefix = new_redis_prefix()
            stack.callback(drop_redis_prefix, DEFAULT_REDIS_URL, prefix)
            env |= {"PANOGS_DATABASE_URL": db_url, "PANOGS_BROKER_URL": DEFAULT_REDIS_URL,
                    "PANOGS_BROKER_KEY_PREFIX": prefix}  # fmt: skip
        procs = Procs(env, tmp)
        stack.callback(procs.stop_all)
        argv = [sys.executable, "-m", "service.cli", "keys", "create", "--name", "bench"]
        key = subprocess.run(argv, env=procs.env, cwd=tmp, capture_output=True, text=True, check=True).stdout.strip()
        if backend == "scaled":
            url = procs.api()
            procs.worker()
        else:
            port = free_port()
            procs.start("serve", [sys.executable, "-m", "service.cli", "serve", "--port", str(port)])
            url = f"http://127.0.0.1:{port}"
            wait_for(lambda: httpx.get(f"{url}/readyz", timeout=1).status_code == 200, 60, "serve")
        database = env.get("PANOGS_DATABASE_URL", f"sqlite:///{tmp / 'data' / 'panogs.db'}")
        yield Service(url, {"Authorization": f"Bearer {key}"}, tmp / "data" / "storage", database)


def make_bundle(tmp: Path, preset: str) -> tuple[Path, Path]:
    folder = tmp / f"scene-{preset}"
    argv = [sys.executable, "-m", "panogs_core.cli", "synth", str(folder), "--preset", preset]
    subprocess.run(argv, cwd=REPO, check=True, capture_output=True)
    return folder, Path(shutil.make_archive(str(folder), "zip", folder))


def upload(service: Service, path: Path, chunk: int | None = None) -> tuple[str, float]:
    """Upload a file (one streamed request, or PATCHes of ``chunk`` bytes); returns (upload id, seconds)."""
    size = path.stat().st_size
    digest = base64.b64encode(_sha256(path).encode()).decode()
    octet = {"Content-Type": "application/offset+octet-stream"}
    with service.client(timeout=600) as client:
        start = time.perf_counter()
        if chunk is None:
            headers = {**octet, "Upload-Length": str(size), "Upload-Metadata": f"sha256 {digest}"}
            response = client.post("/v1/uploads", content=_read(path, 0, size), headers=headers)
            upload_id = response.json()["id"]
        else:
            headers = {"Upload-Length": str(size), "Upload-Metadata": f"sha256 {digest}"}
            response = client.post("/v1/uploads", headers=headers)
            upload_id = response.json()["id"]
            for offset in range(0, size, chunk):
                n = min(chunk, size - offset)
                patch = client.patch(f"/v1/uploads/{upload_id}", content=_read(path, offset, n),
                                     headers={**octet, "Upload-Offset": str(offset)})  # fmt: skip
                assert patch.status_code == 204, patch.text
        seconds = time.perf_counter() - start
        state = client.get(f"/v1/uploads/{upload_id}").json()
    assert state["state"] == "complete", state
    return upload_id, seconds


def _read(path: Path, offset: int, length: int) -> Iterator[bytes]:
    with path.open("rb") as f:
        f.seek(offset)
        while length > 0:
            block = f.read(min(1 << 20, length))
            if not block:
                return
            length -= len(block)
            yield block


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    for block in _read(path, 0, path.stat().st_size):
        h.update(block)
    return h.hexdigest()


def start_job(service: Service, archive: Path) -> tuple[str, float]:
    """Upload a bundle, make a scene, create a job; returns (job id, seconds of upload + scene)."""
    upload_id, _ = upload(service, archive)
    with service.client() as client:
        start = time.perf_counter()
        scene = client.post("/v1/scenes", json={"upload_id": upload_id}).json()
        scene_s = time.perf_counter() - start
        job = client.post("/v1/jobs", json={"scene_id": scene["id"]}).json()
    return str(job["id"]), scene_s


def wait_job(service: Service, job_id: str, interval: float = 0.1) -> dict[str, Any]:
    with service.client() as client:
        while True:
            job = client.get(f"/v1/jobs/{job_id}").json()
            if job["state"] in ("succeeded", "failed", "canceled"):
                return dict(job)
            time.sleep(interval)


# Benchmarks ------------------------------------------------------------------------------------------------


def bench_polls(service: Service, archive: Path, seconds: float, clients: int) -> dict[str, float]:
    """GET /v1/jobs/{id} over ``clients`` keep-alive connections while the job runs (a lean asyncio client, so
    that the client's own cost does not cap the number)."""
    job_id, _ = start_job(service, archive)
    with service.client() as client:
        wait_for(lambda: client.get(f"/v1/jobs/{job_id}").json()["state"] == "running", 120, "the job to run")
    rate = asyncio.run(_poll_rate(service, f"/v1/jobs/{job_id}", clients, seconds))
    with service.client() as client:
        still_running = client.get(f"/v1/jobs/{job_id}").json()["state"] == "running"
    wait_job(service, job_id)
    return {"status polls / s": rate, "job still running at the end (1 = yes)": float(still_running)}


async def _poll_rate(service: Service, path: str, connections: int, seconds: float) -> float:
    host, port = service.url.split("//")[1].split(":")
    headers = "".join(f"{k}: {v}\r\n" for k, v in service.headers.items())
    request = f"GET {path} HTTP/1.1\r\nHost: {host}\r\n{headers}\r\n".encode()
    stop = time.perf_counter() + seconds
    counts = [0] * connections

    async def connection(i: int) -> None:
        reader, writer = await asyncio.open_connection(host, int(port))
        while time.perf_counter() < stop:
            writer.write(request)
            head = await reader.readuntil(b"\r\n\r\n")
            assert head.startswith(b"HTTP/1.1 200"), head[:200]
            length = next(int(line.split(b":")[1]) for line in head.split(b"\r\n")
                          if line.lower().startswith(b"content-length:"))  # fmt: skip
            await reader.readexactly(length)
            counts[i] += 1
        writer.close()

    await asyncio.gather(*(connection(i) for i in range(connections)))
    return sum(counts) / seconds


def bench_query(service: Service, archive: Path, num_instances: int = 200, repeats: int = 300) -> dict[str, float]:
    """Warm query latency on a finished job with ``num_instances`` instances (a result folder made here)."""
    job_id, _ = start_job(service, archive)
    done = wait_job(service, job_id)
    assert done["state"] == "succeeded", done
    _replace_result(service, job_id, num_instances)
    url = f"/v1/jobs/{job_id}/query"
    vocabulary = json.loads((service.storage / "artifacts" / job_id / "vocabulary.json").read_text())
    names = [c["name"] for c in vocabulary["classes"]]
    dim = int(np.load(service.storage / "artifacts" / job_id / "vocabulary.npy").shape[1])
    rng = np.random.default_rng(0)
    out: dict[str, float] = {}
    with service.client() as client:
        first = time.perf_counter()
        cold = client.post(url, json={"text": "something to sit on"})
        out["query first free text ms (encoder start)"] = (time.perf_counter() - first) * 1000
        kinds = {
            "class name": lambda i: {"text": names[i % len(names)]},
            "vector": lambda i: {"vector": rng.normal(size=dim).tolist()},
            # distinct texts: every one goes through the encoder (repeated texts are cached by the API)
            "free text": lambda i: {"text": f"the {names[i % len(names)]} number {i}"},
        }
        for kind, body in kinds.items():
            if kind == "free text" and cold.status_code != 200:
                continue
            for i in range(20):  # warm-up
                client.post(url, json=body(repeats + i))
            latencies = []
            for i in range(repeats):
                start = time.perf_counter()
                response = client.post(url, json=body(i))
                latencies.append((time.perf_counter() - start) * 1000)
                assert response.status_code == 200, response.text
            out[f"query p50 ms ({kind})"] = statistics.median(latencies)
            out[f"query p95 ms ({kind})"] = float(np.percentile(latencies, 95))
    return out


def _replace_result(service: Service, job_id: str, num_instances: int) -> None:
    """Give the finished job ``num_instances`` instances (features drawn around its vocabulary's
    embeddings)."""
    out_dir = service.storage / "artifacts" / job_id
    emb = np.load(out_dir / "vocabulary.npy").astype(np.float32)
    kinds = [c["kind"] for c in json.loads((out_dir / "vocabulary.json").read_text())["classes"]]
    names = [c["name"] for c in json.loads((out_dir / "vocabulary.json").read_text())["classes"]]
    rng = np.random.default_rng(1)
    rows, feats = [], []
    for k in range(num_instances):
        cls = k % len(emb)
        centre = rng.uniform(-5, 5, 3)
        rows.append({"id": k, "class_name": names[cls], "class_index": cls, "kind": kinds[cls], "score": 0.8,
                     "num_points": 100, "centroid": centre.tolist(), "bbox_min": (centre - 0.4).tolist(),
                     "bbox_max": (centre + 0.4).tolist()})  # fmt: skip
        f = emb[cls] + 0.1 * rng.normal(size=emb.shape[1])
        feats.append(f / np.linalg.norm(f))
    (out_dir / "instances.json").write_text(json.dumps(rows))
    np.save(out_dir / "instance_features.npy", np.asarray(feats, np.float32))


def bench_upload(service: Service, tmp: Path, mib: int) -> dict[str, float]:
    path = tmp / "upload.bin"
    with path.open("wb") as f:
        for _ in range(mib):
            f.write(os.urandom(1 << 20))
    size_mb = path.stat().st_size / 1e6
    _, one = upload(service, path)
    _, chunked = upload(service, path, chunk=64 << 20)
    path.unlink()
    return {"upload MB/s (one request)": size_mb / one, "upload MB/s (64 MiB PATCHes)": size_mb / chunked}


def bench_overhead(service: Service, folder: Path, archive: Path, tmp: Path, repeats: int) -> dict[str, float]:
    """Job time through the service (POST to observed success) against the pipeline's time.

    ``service overhead %``: the job's wall time from POST to observed success over the same run's own pipeline
    time (its report.json), so that both sides of the ratio saw the same machine load. Also ``panogs run`` on
    the same scene, alternating with the service runs (fastest of each kept): a separate process, so it pays
    the imports and a cold start, and other work on the machine moves single runs by more than the overhead.
    """
    direct, service_s, pipeline_s, own = [], [], [], []
    upload_id, upload_s = upload(service, archive)
    with service.client() as client:
        start = time.perf_counter()
        scene = client.post("/v1/scenes", json={"upload_id": upload_id}).json()
        scene_s = time.perf_counter() - start
    for i in range(repeats):
        out = tmp / f"direct-{i}"
        argv = [sys.executable, "-m", "panogs_core.cli", "run", str(folder), "--out", str(out)]
        start = time.perf_counter()
        subprocess.run(argv, cwd=REPO, check=True, capture_output=True)
        direct.append(time.perf_counter() - start)
        pipeline_s.append(json.loads((out / "report.json").read_text())["total_wall_s"])
        with service.client() as client:
            start = time.perf_counter()
            job = client.post("/v1/jobs", json={"scene_id": scene["id"]}).json()
        done = wait_job(service, job["id"], interval=0.05)
        service_s.append(time.perf_counter() - start)
        assert done["state"] == "succeeded", done
        report = json.loads((service.storage / "artifacts" / job["id"] / "report.json").read_text())
        own.append((service_s[-1] - report["total_wall_s"]) / report["total_wall_s"])
    return {
        "panogs run wall s (CLI process, fastest)": min(direct),
        "pipeline wall s (report.json, fastest)": min(pipeline_s),
        "service job wall s (POST to success, fastest)": min(service_s),
        "upload + scene validation s": upload_s + scene_s,
        "service overhead %": 100.0 * min(own),
        "service job vs panogs run %": 100.0 * (min(service_s) - min(direct)) / min(direct),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("which", nargs="*", default=["polls", "query", "upload", "overhead"])
    parser.add_argument("--backend", choices=["scaled", "embedded"], default="scaled")
    parser.add_argument("--preset", default="tiny")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--clients", type=int, default=8, help="concurrent poll connections")
    parser.add_argument("--status-cache-s", type=float, default=None, help="the API's PANOGS_STATUS_CACHE_S")
    parser.add_argument("--upload-mib", type=int, default=512)
    parser.add_argument("--repeats", type=int, default=2, help="runs of each side for the overhead")
    args = parser.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="panogs-bench-"))
    results: dict[str, float] = {}
    try:
        folder, archive = make_bundle(tmp, args.preset)
        extra = {} if args.status_cache_s is None else {"PANOGS_STATUS_CACHE_S": str(args.status_cache_s)}
        with deployment(args.backend, tmp, extra) as service:
            if "polls" in args.which:
                results |= bench_polls(service, archive, args.seconds, args.clients)
            if "query" in args.which:
                results |= bench_query(service, archive)
            if "upload" in args.which:
                results |= bench_upload(service, tmp, args.upload_mib)
            if "overhead" in args.which:
                results |= bench_overhead(service, folder, archive, tmp, args.repeats)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    cache = "default" if args.status_cache_s is None else f"{args.status_cache_s:g} s"
    print(f"panogs service benchmarks ({args.backend}, preset {args.preset}, {os.cpu_count()} CPUs, "
          f"status cache {cache})")  # fmt: skip
    print(f"{'measure':<44} {'value':>10}  target")
    for name, value in results.items():
        print(f"{name:<44} {value:>10.1f}  {TARGETS.get(name, '')}")
    out = REPO / "bench" / "results"
    out.mkdir(parents=True, exist_ok=True)
    (out / f"service-{args.backend}.json").write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
