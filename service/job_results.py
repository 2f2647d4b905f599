"""A job's results as the API serves them: instances and queries, loaded once and kept warm.

Results are ready before the job has finished: the pipeline writes them before the appearance fit, and the worker
records ``results_at`` then (docs/service.md, "Results before the fit"). The Gaussian scene (renders,
``gaussians.ply``) waits for the fit: :func:`check_fitted` answers 409 ``fit_not_ready`` with its progress.

Results are read with ``panogs_core.io.run_folder.load_result`` (numpy only) and kept in a small LRU per API
process; a finished job's folder never changes, so the cache needs no invalidation beyond the job id.
Free text is encoded by :mod:`service.encoder` (a child process); class names and vectors need no encoder.
"""

from __future__ import annotations

import json
import threading
import time
import uuid
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

from sqlalchemy import Engine

from service.db import crud
from service.db.models import FitState
from service.encoder import EncoderFailed, EncoderProcess, RemoteTextEncoder
from service.errors import Conflict, FitNotReady, InvalidInput, NotFound, ServiceUnavailable
from service.schemas import InstancePublic, InstancesPublic, QueryCreate, QueryHitPublic, QueryResult
from service.storage import Storage

FIT_RETRY_AFTER_S = 5  # what a 409 fit_not_ready asks a client to wait while the fit runs


@dataclass(frozen=True)
class Loaded:
    """A finished job's result as the API serves it."""

    result: Any  # panogs_core.io.run_folder.LoadedResult: instances (with features), vocabulary, feature space
    instances_body: bytes  # the JSON of GET /instances


class ResultCache:
    """Loaded results of finished jobs, least recently used dropped first."""

    def __init__(self, capacity: int) -> None:
        self._capacity = capacity
        self._items: OrderedDict[uuid.UUID, Loaded] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, job_id: uuid.UUID, out_dir: Path) -> Loaded:
        """The loaded result of a finished job (read from its folder on first use)."""
        with self._lock:
            if job_id in self._items:
                self._items.move_to_end(job_id)
                return self._items[job_id]
        from panogs_core.io.run_folder import load_result

        rows = [InstancePublic.model_validate(r) for r in read_instances(out_dir)]
        body = InstancesPublic(data=rows, count=len(rows)).model_dump_json().encode()
        loaded = Loaded(result=load_result(out_dir), instances_body=body)
        with self._lock:
            self._items[job_id] = loaded
            while len(self._items) > self._capacity:
                self._items.popitem(last=False)
        return loaded

    def peek(self, job_id: uuid.UUID) -> Loaded | None:
        """The loaded result when it is here, else None."""
        with self._lock:
            hit = self._items.get(job_id)
            if hit is not None:
                self._items.move_to_end(job_id)
            return hit

    def drop(self, job_id: uuid.UUID) -> None:
        """Forget a job's result (it was deleted)."""
        with self._lock:
            self._items.pop(job_id, None)


def read_instances(out_dir: Path) -> list[dict[str, Any]]:
    """instances.json of a finished job."""
    from panogs_core.io.run_folder import INSTANCES_JSON

    data = json.loads(INSTANCES_JSON.path(out_dir).read_text())
    return list(data if isinstance(data, list) else data.get("instances", []))


def finished(engine: Engine, cache: ResultCache, storage: Storage, job_id: uuid.UUID, tenant_id: uuid.UUID) -> Loaded:
    """The result of a tenant's job whose results are ready, the fit done or not (one autocommit SELECT, then the
    cache)."""
    with engine.connect() as conn:
        row = crud.read_job_row(conn, job_id, tenant_id)
    if row is None:
        raise NotFound("job", job_id)
    if row.results_at is None:
        raise Conflict(f"job {job_id} is {row.state.value}; results exist once its labelling is done")
    hit = cache.peek(job_id)  # a warm result asks the storage nothing
    return hit if hit is not None else cache.get(job_id, storage.run_folder(job_id))


def fitted_scene(engine: Engine, job_id: uuid.UUID, tenant_id: uuid.UUID) -> None:
    """Check that a tenant's job has its final Gaussian scene (renders, ``gaussians.ply``).

    Raises:
        NotFound: no such job of the tenant.
        Conflict: its results are not ready.
        FitNotReady: its results are ready, its fit is not done (or failed, or was canceled); the body says how far.
    """
    with engine.connect() as conn:
        row = crud.read_job_row(conn, job_id, tenant_id)
    if row is None:
        raise NotFound("job", job_id)
    check_fitted(row)


def check_fitted(job: Any) -> None:
    """Raise :class:`Conflict` or :class:`FitNotReady` unless the job's Gaussian scene is final (a row or a model)."""
    if job.results_at is None:
        raise Conflict(f"job {job.id} is {job.state.value}; results exist once its labelling is done")
    fit: FitState | None = job.fit_state
    if fit is not None and fit.scene_ready:
        return
    progress = round(float(job.fit_progress or 0.0), 4)
    body = {"state": (fit or FitState.RUNNING).value, "progress": progress, "error": job.fit_error}
    if fit in (FitState.FAILED, FitState.CANCELED):
        raise FitNotReady(
            f"job {job.id}: the Gaussian fit {fit.value}; its results stand, but gaussians.ply holds only the "
            "initialisation and is neither served nor rendered",
            body,
        )
    if job.state.is_terminal:  # the job ended during its fit without saying how (a worker lost for good)
        body["state"] = FitState.FAILED.value
        raise FitNotReady(f"job {job.id} is {job.state.value}; its Gaussian fit did not finish", body)
    raise FitNotReady(
        f"job {job.id}: the Gaussian fit is {progress:.0%} done; gaussians.ply and renders exist once it has "
        "succeeded (the instances and queries answer now)",
        body,
        retry_after_s=FIT_RETRY_AFTER_S,
    )


def answer_query(
    engine: Engine,
    cache: ResultCache,
    storage: Storage,
    job_id: uuid.UUID,
    tenant_id: uuid.UUID,
    body: QueryCreate,
    encoder: EncoderProcess | None,
) -> QueryResult:
    """Rank a tenant's succeeded job's instances against ``body``."""
    return run_query(finished(engine, cache, storage, job_id, tenant_id).result, body, encoder)


def run_query(loaded: Any, body: QueryCreate, encoder: EncoderProcess | None) -> QueryResult:
    """Rank a finished job's instances against a text or vector query."""
    import numpy as np

    from panogs_core.errors import EncoderUnavailableError, InputError
    from panogs_core.language.query import rank_instances

    start = time.perf_counter()
    vocabulary = loaded.vocabulary
    dim = int(np.asarray(vocabulary.embeddings).shape[1])
    query: str | np.ndarray
    kind: Literal["class", "text", "vector"]
    if body.vector is not None:
        if len(body.vector) != dim:
            raise InvalidInput(f"vector has {len(body.vector)} values; this scene's features have {dim}")
        query, kind = np.asarray(body.vector, dtype=np.float32), "vector"
    else:
        assert body.text is not None
        query = body.text
        named = body.text.strip().lower() in {n.lower() for n in vocabulary.names}
        kind = "class" if named else "text"
    remote = (
        RemoteTextEncoder(encoder, loaded.feature_space, dim)
        if encoder is not None
        else _NoEncoder(loaded.feature_space, dim)
    )
    options: dict[str, Any] = {"top_k": body.top_k, "candidates": body.candidates}
    if body.min_score is not None:
        options["min_score"] = body.min_score
    try:
        answer = rank_instances(
            loaded.instances, vocabulary, query, feature_space=loaded.feature_space, encoder=remote, **options
        )
    except EncoderUnavailableError as exc:
        raise InvalidInput(f"free-text query not possible: {exc}{_text_extra_hint(str(exc))}") from exc
    except InputError as exc:
        raise InvalidInput(str(exc)) from exc
    except EncoderFailed as exc:
        raise ServiceUnavailable(f"text encoder unavailable: {exc}") from exc
    took_ms = (time.perf_counter() - start) * 1000.0
    return QueryResult(
        hits=[QueryHitPublic(**hit.to_json()) for hit in answer.hits],
        candidates=[QueryHitPublic(**hit.to_json()) for hit in answer.candidates],
        min_score=answer.min_score,
        query_kind=kind,
        took_ms=round(took_ms, 3),
    )


def _text_extra_hint(reason: str) -> str:
    """How to add the text encoders where the reason is their absence: pip for a host, a build argument for the
    docker deployment's API image (its default build is slim)."""
    if "panogs[text]" not in reason:
        return ""
    return (
        "; in the docker deployment, rebuild the API image with --build-arg API_KIND=full "
        "(docker compose: PANOGS_API_KIND=full, its default; docs/service.md, Deployment)"
    )


class _NoEncoder:
    """Stands in for an encoder where free-text queries are switched off (``PANOGS_QUERY_ENCODER=off``)."""

    def __init__(self, space: str, dim: int) -> None:
        self.space = space
        self.dim = dim

    def encode(self, texts: list[str]) -> Any:
        from panogs_core.errors import EncoderUnavailableError

        raise EncoderUnavailableError(
            "free-text queries are switched off on this server; query a vocabulary class name or a vector"
        )
