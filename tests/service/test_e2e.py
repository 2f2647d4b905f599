"""End to end with the real pipeline: processes started with the docker-compose commands, a client over HTTP.

Twice: the scaled deployment (uvicorn + a Celery worker on PostgreSQL and Redis) and the embedded default
(``panogs serve`` with nothing configured but a data folder). Each uploads a tiny synthetic bundle in two tus
PATCHes, makes a scene, runs a job, polls it to success, reads the instances, queries a class name and checks
the ids against the ground truth and the library, and downloads ``panoptic.ply`` in two ranges and parses it.
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from procs import Procs, free_port, wait_for
from service_harness import (
    PG_ADMIN_URL,
    REDIS_URL,
    drop_redis_prefix,
    new_redis_prefix,
    python_path,
    require_postgres,
    require_redis,
    temp_postgres,
)

from worker.shared_checkpoints import archive_input_hash

pytestmark = pytest.mark.slow

PREFERRED_QUERY = "chair"
JOB_TIMEOUT_S = 400.0
# No stage's labels read the appearance fit (its checkpoint key feeds none of them): two iterations leave the
# instances, queries and files checked here as they are, at a fifth of the fit's time. The fit has its own tests.
JOB_CONFIG = {"appearance": {"iterations": 2}}


@pytest.fixture(scope="module")
def bundle(tmp_path_factory: pytest.TempPathFactory, synth_tiny: Path) -> tuple[Path, Path]:
    """(folder, zip) of a tiny synthetic scene made by ``panogs synth`` (the session's, only read here)."""
    try:
        import panogs_core.io.run_folder
        import panogs_core.pipeline.run  # noqa: F401
    except ImportError as exc:
        pytest.skip(f"the core pipeline is not importable yet: {exc}")
    tmp = tmp_path_factory.mktemp("e2e-bundle")
    archive = Path(shutil.make_archive(str(tmp / "scene"), "zip", synth_tiny))
    return synth_tiny, archive


def _key(env: dict[str, str], cwd: Path) -> dict[str, str]:
    argv = [sys.executable, "-m", "service.cli", "keys", "create", "--name", "e2e"]
    key = subprocess.run(argv, env=env, cwd=cwd, capture_output=True, text=True, check=True, timeout=120)
    return {"Authorization": f"Bearer {key.stdout.strip()}"}


@pytest.fixture(scope="module")
def scaled(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str], Path]]:
    """The compose deployment as local processes: API + worker on PostgreSQL and Redis."""
    require_postgres(PG_ADMIN_URL)
    require_redis(REDIS_URL)
    tmp = tmp_path_factory.mktemp("e2e-scaled")
    prefix = new_redis_prefix()
    with temp_postgres(PG_ADMIN_URL) as db_url:
        env = {
            "PANOGS_DATABASE_URL": db_url,
            "PANOGS_BROKER_URL": REDIS_URL,
            "PANOGS_BROKER_KEY_PREFIX": prefix,
            "PANOGS_DATA_DIR": str(tmp / "data"),
            "PANOGS_STORAGE_DIR": str(tmp / "shared"),
        }
        procs = Procs(env, tmp)
        try:
            headers = _key(procs.env, tmp)
            url = procs.api()
            procs.worker()
            yield url, headers, tmp / "shared"
        finally:
            procs.kill_all()  # the API and the worker: nothing here checks their shutdown
            drop_redis_prefix(REDIS_URL, prefix)


@pytest.fixture(scope="module")
def embedded(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[str, dict[str, str], Path]]:
    """``panogs serve`` with no configuration (SQLite, filesystem broker, local files) in a fresh folder."""
    tmp = tmp_path_factory.mktemp("e2e-embedded")
    clean = {k: v for k, v in os.environ.items() if not k.startswith("PANOGS_")}
    procs = Procs({}, tmp)
    procs.env = {**clean, "PYTHONPATH": python_path(), "PYTHONUNBUFFERED": "1"}
    try:
        headers = _key(procs.env, tmp)  # the data folder ./panogs-data is created on first use
        port = free_port()
        proc = procs.start("serve", [sys.executable, "-m", "panogs_core.cli", "serve", "--port", str(port)])

        def up() -> bool:
            assert proc.poll() is None, procs.tail("serve")()
            return httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200

        wait_for(up, 60, "panogs serve", procs.tail("serve"))
        yield f"http://127.0.0.1:{port}", headers, tmp / "panogs-data" / "storage"
    finally:
        procs.stop_all()


@pytest.mark.parametrize("deployment", ["scaled", "embedded"])
def test_session(deployment: str, request: pytest.FixtureRequest, bundle: tuple[Path, Path]) -> None:
    url, headers, storage = request.getfixturevalue(deployment)
    folder, archive = bundle
    with httpx.Client(base_url=url, headers=headers, timeout=60) as client:
        scene_id = _upload_scene(client, archive)
        job_body = {"scene_id": scene_id, "config": JOB_CONFIG}
        response = client.post("/v1/jobs", json=job_body, headers={"Idempotency-Key": deployment})
        assert response.status_code == 202, response.text
        job = _poll(client, response.json()["id"])
        assert job["state"] == "succeeded", job
        assert set(job["stage_timings"]) >= {"primitives", "clustering", "labeling"}

        instances = client.get(f"/v1/jobs/{job['id']}/instances").json()["data"]
        assert instances
        assert {"class_name", "score", "bbox_min", "bbox_max"} <= set(instances[0])

        query = _query_class(instances)
        # The best match whatever its score: the score's calibration is the core's business, not the
        # service's.
        body = {"text": query, "top_k": 1, "min_score": 0.0}
        hits = client.post(f"/v1/jobs/{job['id']}/query", json=body).json()
        assert hits["query_kind"] == "class"
        ids = [h["instance_id"] for h in hits["hits"]]
        assert ids, f"no instance answers {query!r}: {instances}"
        assert ids == _library_query(storage / "artifacts" / job["id"], query)
        labels = _download(client, job["id"], "labels.npz")
        _check_against_ground_truth(folder, np.load(labels)["instance"], ids, query)

        ply = _download(client, job["id"], "panoptic.ply", ranged=True)
        _check_ply(ply, instances, len(np.load(labels)["instance"]))
        report = json.loads(_download(client, job["id"], "report.json").read_text())
        _check_devices(report)
        # The stage keys started from the upload's archive hash: no job hashes an uploaded bundle.
        assert report["input_sha256"] == archive_input_hash(hashlib.sha256(archive.read_bytes()).hexdigest())


def _upload_scene(client: httpx.Client, archive: Path) -> str:
    data = archive.read_bytes()
    digest = base64.b64encode(hashlib.sha256(data).hexdigest().encode()).decode()
    metadata = f"filename {base64.b64encode(b'scene.zip').decode()},sha256 {digest}"
    tus = {"Tus-Resumable": "1.0.0"}
    created = client.post("/v1/uploads", headers={**tus, "Upload-Length": str(len(data)), "Upload-Metadata": metadata})
    assert created.status_code == 201, created.text
    upload_id, half = created.json()["id"], len(data) // 2
    for start, end in ((0, half), (half, len(data))):
        headers = {**tus, "Upload-Offset": str(start), "Content-Type": "application/offset+octet-stream"}
        patch = client.patch(f"/v1/uploads/{upload_id}", content=data[start:end], headers=headers)
        assert patch.status_code == 204, patch.text
    scene = client.post("/v1/scenes", json={"upload_id": upload_id})
    assert scene.status_code == 201, scene.text
    return str(scene.json()["id"])


def _poll(client: httpx.Client, job_id: str) -> dict[str, Any]:
    deadline = time.monotonic() + JOB_TIMEOUT_S
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}").json()
        if job["state"] in ("succeeded", "failed", "canceled"):
            return dict(job)
        time.sleep(0.5)
    raise AssertionError(f"job {job_id} did not finish in {JOB_TIMEOUT_S} s: {job}")


def _query_class(instances: list[dict[str, Any]]) -> str:
    """ "chair" when the run found chairs, else the class of its largest thing (what the tiny scene yields
    depends on the pipeline's quality, which is not what this test is about)."""
    things = sorted((i for i in instances if i["kind"] == "thing"), key=lambda i: -i["num_points"])
    names = [i["class_name"] for i in things] or [instances[0]["class_name"]]
    return PREFERRED_QUERY if PREFERRED_QUERY in names else names[0]


def _library_query(out_dir: Path, query: str) -> list[int]:
    """What the library answers on the job's own output folder (the service must answer the same)."""
    from panogs_core.io.run_folder import load_result
    from panogs_core.language.query import query_instances

    loaded = load_result(out_dir)
    space = loaded.feature_space
    hits = query_instances(loaded.instances, loaded.vocabulary, query, feature_space=space, top_k=1, min_score=0.0)
    return [h.instance_id for h in hits]


def _check_against_ground_truth(folder: Path, instance: np.ndarray, ids: list[int], query: str) -> None:
    """Each returned instance is mostly ground-truth points of the queried class (labels per geometry
    vertex)."""
    gt = np.load(folder / "gt" / "labels.npz")
    classes = [c["name"] for c in json.loads((folder / "vocabulary.json").read_text())["classes"]]
    wanted = classes.index(query)
    assert len(gt["semantic"]) == len(instance)
    for instance_id in ids:
        semantic = gt["semantic"][instance == instance_id]
        semantic = semantic[semantic >= 0]
        assert len(semantic) > 0
        majority = np.bincount(semantic).argmax()
        assert majority == wanted, f"instance {instance_id} is mostly {classes[majority]}, not {query}"


def _download(client: httpx.Client, job_id: str, name: str, ranged: bool = False) -> Path:
    import tempfile

    path = Path(tempfile.mkdtemp()) / name
    if not ranged:
        response = client.get(f"/v1/jobs/{job_id}/artifacts/{name}")
        assert response.status_code == 200
        path.write_bytes(response.content)
        return path
    size = next(a["size_bytes"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()["data"] if a["name"] == name)
    first = client.get(f"/v1/jobs/{job_id}/artifacts/{name}", headers={"Range": f"bytes=0-{size // 2 - 1}"})
    rest = client.get(f"/v1/jobs/{job_id}/artifacts/{name}", headers={"Range": f"bytes={size // 2}-"})
    assert (first.status_code, rest.status_code) == (206, 206)
    assert rest.headers["content-range"] == f"bytes {size // 2}-{size - 1}/{size}"
    path.write_bytes(first.content + rest.content)
    return path


def _check_devices(report: dict[str, Any]) -> None:
    """The worker trained on this machine's GPU when it has one (the test and the worker share the machine),
    and the report says so for the language field; every other stage ran on the CPU."""
    import torch

    expected = "cuda" if torch.cuda.is_available() else "cpu"
    devices = {entry["stage"]: entry["device"] for entry in report["stages"]}
    assert devices.pop("language_field") == expected
    assert set(devices.values()) == {"cpu"}


def _check_ply(path: Path, instances: list[dict[str, Any]], num_points: int) -> None:
    from panogs_core.io.ply import read_ply_vertices

    vertices = read_ply_vertices(path)
    assert {"x", "y", "z", "red", "green", "blue", "semantic", "instance"} <= set(vertices)
    assert len(vertices["x"]) == num_points
    assert set(np.unique(vertices["instance"])) - {-1} == {i["id"] for i in instances}
