"""Helpers of the service tests: a recording task sender, tiny bundles, archives, one-call upload and
scene."""

from __future__ import annotations

import base64
import io
import json
import tarfile
import uuid
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.db.base import utcnow
from service.db.models import FitState, Job, JobState
from service.db.session import get_session_factory, session_scope
from service.storage import Storage
from worker.job_io import collect_artifacts
from worker.runner import FITTED_FILES

# Run a test on PostgreSQL and on the embedded SQLite (the ``settings`` fixture reads the parameter).
BOTH_BACKENDS = pytest.mark.parametrize("settings", ["postgres", "sqlite"], indirect=True)


# Inline classes with vectors in the tiny bundle's 8-d space: the scripted pipeline's run folder then answers
# instances and queries (it writes vocabulary.json, vocabulary.npy and instance_features.npy from them).
VOCABULARY_8D = {
    "classes": [{"name": n, "embedding": [float(i == k) for i in range(8)]} for k, n in enumerate(("chair", "table"))]
}


@dataclass
class RecordingSender:
    """Stands in for the Celery app: records ``send_task`` calls; can be told to fail like a broker that is
    away."""

    calls: list[tuple[str, list[str], str | None]] = field(default_factory=list)
    fail: bool = False

    def send_task(self, name: str, args: list[str] | None = None, queue: str | None = None) -> object:
        if self.fail:
            raise ConnectionError("broker unavailable (test)")
        self.calls.append((name, list(args or []), queue))
        return object()


# Bundles ---------------------------------------------------------------------------------------------------


def write_tiny_bundle(root: Path, *, dim: int = 8, mutate: Callable[[Path], None] | None = None) -> Path:
    """A valid 2-frame bundle (64x48, D=dim, a vocabulary), optionally broken by ``mutate(root)``."""
    from panogs_core.io.bundle.writer import BundleWriter
    from panogs_core.types import Camera, Vocabulary

    camera = Camera(width=64, height=48, fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    rng = np.random.default_rng(0)
    writer = BundleWriter(root, name="tiny", camera=camera, feature_dim=dim, feature_space="test-space")
    for i in range(2):
        pose = np.eye(4)
        pose[0, 3] = 0.1 * i
        writer.add_frame(
            f"{i:06d}", pose, rng.uniform(0.5, 3.0, (48, 64)),
            color=rng.integers(0, 256, (48, 64, 3), dtype=np.uint8),
            features=rng.normal(size=(6, 8, dim)).astype(np.float32),
            masks=rng.integers(0, 4, (48, 64)),
        )  # fmt: skip
    writer.write_geometry(rng.normal(size=(20, 3)))
    writer.write_vocabulary(
        Vocabulary(("wall", "chair", "table"), ("stuff", "thing", "thing"), rng.normal(size=(3, dim)))
    )
    out = writer.close()
    if mutate is not None:
        mutate(out)
    return out


def pack(folder: Path, kind: str = "zip") -> bytes:
    """The folder as a .zip or .tar.gz archive, in memory (test bundles are small)."""
    buffer = io.BytesIO()
    if kind == "zip":
        with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as zf:
            for path in sorted(folder.rglob("*")):
                zf.write(path, path.relative_to(folder).as_posix())
    else:
        with tarfile.open(fileobj=buffer, mode="w:gz") as tf:
            tf.add(folder, arcname=".")
    return buffer.getvalue()


def edit_manifest(root: Path, edit: Callable[[dict[str, Any]], None]) -> None:
    """Apply ``edit`` to scene.json."""
    manifest = json.loads((root / "scene.json").read_text())
    edit(manifest)
    (root / "scene.json").write_text(json.dumps(manifest))


def upload_bytes(client: TestClient, auth: dict[str, str], data: bytes, **metadata: str) -> dict[str, Any]:
    """One-request tus upload (creation-with-upload); returns the upload JSON."""
    headers = {**auth, "Tus-Resumable": "1.0.0", "Upload-Length": str(len(data)),
               "Content-Type": "application/offset+octet-stream"}  # fmt: skip
    if metadata:
        headers["Upload-Metadata"] = ",".join(
            f"{k} {base64.b64encode(v.encode()).decode()}" for k, v in metadata.items()
        )
    response = client.post("/v1/uploads", content=data, headers=headers)
    assert response.status_code == 201, response.text
    return dict(response.json())


def make_scene(client: TestClient, auth: dict[str, str], data: bytes) -> dict[str, Any]:
    """Upload ``data`` and make a scene of it; returns the scene JSON."""
    upload = upload_bytes(client, auth, data, filename="tiny.zip")
    response = client.post("/v1/scenes", json={"upload_id": upload["id"]}, headers=auth)
    assert response.status_code == 201, response.text
    return dict(response.json())


def new_key(settings: Any, name: str = "tester") -> dict[str, str]:
    """Authorization header of a fresh API key."""
    from service.auth import create_api_key
    from service.db.session import get_session_factory, session_scope

    with session_scope(get_session_factory(settings.database)) as session:
        _row, key = create_api_key(session, name)
    return {"Authorization": f"Bearer {key}"}


def mark_succeeded(settings: Any, job_id: uuid.UUID) -> None:
    """Mark a job succeeded with the artifacts of the result folder the test wrote for it (as the worker does)."""
    storage = Storage(settings.storage)
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        job.state = JobState.SUCCEEDED
        job.results_at = job.finished_at = utcnow()
        job.fit_state, job.fit_progress = FitState.SUCCEEDED, 1.0
        job.artifacts.clear()  # the rows recorded with the results, if any: replaced as the worker does
        session.flush()
        session.add_all(collect_artifacts(job_id, storage.job_dir(job_id), storage))
        session.commit()


def mark_results_ready(
    settings: Any, job_id: uuid.UUID, *, fit_progress: float = 0.25, fit_state: Any = None, state: Any = None
) -> None:
    """Mark a job as the worker does once its results are written and its fit runs (or ended as ``fit_state``
    says, the job then in ``state``): the result folder's artifacts but gaussians.ply."""
    storage = Storage(settings.storage)
    with session_scope(get_session_factory(settings.database)) as session:
        job = session.get(Job, job_id)
        assert job is not None
        job.state = state or JobState.RUNNING
        job.results_at = utcnow()
        job.fit_state, job.fit_progress = fit_state or FitState.RUNNING, fit_progress
        if job.fit_state == FitState.FAILED:
            job.fit_error = "NumericalError: the loss is NaN"
        session.add_all(collect_artifacts(job_id, storage.job_dir(job_id), storage, exclude=FITTED_FILES))
        session.commit()
