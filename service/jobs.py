"""Creating jobs (validated config and vocabulary, idempotency keys) and presenting them."""

from __future__ import annotations

import hashlib
import json
import uuid
from collections.abc import Sequence
from typing import Any

from sqlalchemy import Engine, Row
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session

from service.db import crud
from service.db.models import Job, JobState, Scene
from service.errors import InvalidInput, NotFound
from service.lifecycle import reserve_job_slots
from service.map_models import check_job_maps, job_queue
from service.schemas import (
    FitPublic,
    InlineVocabulary,
    InlineVocabularyPublic,
    JobCreate,
    JobError,
    JobMaps,
    JobPublic,
    JobTiling,
    TilePublic,
)
from service.settings import Settings
from service.stored_text import printable_text


def pipeline_config(overrides: dict[str, Any]) -> Any:
    """A job's pipeline config from its overrides: ``PipelineConfig.from_dict``, which the API checks them with and
    the worker runs them with. Tests put their stand-in pipeline's here (tests/support/pipeline_stand_in.py)."""
    from panogs_core.pipeline.config import PipelineConfig

    return PipelineConfig.from_dict(overrides)


def validate_config(overrides: dict[str, Any]) -> None:
    """Refuse overrides that the pipeline's config refuses (unknown keys, bad values), with its message."""
    from panogs_core.errors import ConfigError

    try:
        pipeline_config(overrides)
    except ConfigError as exc:
        raise InvalidInput("the pipeline config overrides are not valid", problems=[_shortened(str(exc))]) from exc


MAX_PROBLEM_CHARS = 1_000  # a config with a million unknown keys must not come back as megabytes of message


def _shortened(message: str) -> str:
    if len(message) <= MAX_PROBLEM_CHARS:
        return message
    return f"{message[:MAX_PROBLEM_CHARS]} ... ({len(message) - MAX_PROBLEM_CHARS} more characters)"


def validate_tiling(tiling: JobTiling | None) -> None:
    """Refuse planner settings that the planner refuses, with its message."""
    from panogs_core.errors import ConfigError
    from panogs_core.tiling.plan import TilingConfig

    if tiling is None:
        return
    try:
        TilingConfig(**tiling.model_dump(exclude={"tiles"}, exclude_none=True))
    except ConfigError as exc:
        raise InvalidInput("the tiling settings are not valid", problems=[_shortened(str(exc))]) from exc


MIN_TILE_CAP = 8  # tiles any scene may be split into, however few its frames


def tile_cap(settings: Settings, num_frames: int) -> int:
    """The most tiles a job on a scene of ``num_frames`` frames may have: ``max_tiles_per_job``, and no more than one
    per frame (a tile no frame of its own sees is work without gain) with ``MIN_TILE_CAP`` for any scene."""
    return min(settings.max_tiles_per_job, max(MIN_TILE_CAP, num_frames))


def tile_cap_rule(settings: Settings, cap: int) -> str:
    """How :func:`tile_cap` came to ``cap``, for the messages that refuse a job over it."""
    return f"at most {cap} (one per frame, at least {MIN_TILE_CAP}, at most {settings.max_tiles_per_job}: " \
        "PANOGS_MAX_TILES_PER_JOB)"  # fmt: skip


def check_tile_cap(settings: Settings, scene: Scene, tiling: JobTiling | None) -> int:
    """Refuse (422) an ``NxM`` tiling past :func:`tile_cap`; returns the concurrent-job slots the job holds (one per
    tile asked, ``crud.job_slots``; an ``auto`` job is counted by its planned tiles once planned)."""
    if tiling is None or "x" not in tiling.tiles:
        return 1
    columns, _, rows = tiling.tiles.partition("x")
    tiles = int(columns) * int(rows)
    cap = tile_cap(settings, scene.num_frames)
    if tiles > cap:
        raise InvalidInput(
            f"tiling.tiles {tiling.tiles!r} makes {tiles} tiles; a job on scene {scene.id} ({scene.num_frames} "
            f"frames) may have {tile_cap_rule(settings, cap)}"
        )
    return tiles


def request_hash(body: JobCreate) -> str:
    """Fingerprint of a creation request, to tell a retry from a reuse of its Idempotency-Key."""
    fields = body.model_dump(mode="json")
    for optional in ("tiling", "maps"):  # a request without one keeps the fingerprint it had before it existed
        if fields.get(optional) is None:
            fields.pop(optional, None)
    canonical = json.dumps(fields, sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def create_job(
    session: Session, settings: Settings, tenant_id: uuid.UUID, body: JobCreate, idempotency_key: str | None
) -> tuple[Job, bool]:
    """The new job and True, or the job an earlier request with the same Idempotency-Key made and False.

    Raises:
        NotFound: the scene does not exist for this tenant.
        InvalidInput: bad config overrides, or the key was used before with a different request.
    """
    fingerprint = request_hash(body)
    if idempotency_key is not None:
        printable_text(idempotency_key, "Idempotency-Key")
        earlier = _same_request(session, tenant_id, idempotency_key, fingerprint)
        if earlier is not None:
            return earlier, False
    scene = crud.get_owned(session, Scene, body.scene_id, tenant_id)
    if scene is None:
        raise NotFound("scene", body.scene_id)
    validate_config(body.config)
    validate_tiling(body.tiling)
    slots = check_tile_cap(settings, scene, body.tiling)
    check_vocabulary(body, scene)
    maps = check_job_maps(settings, body, scene)
    reserve_job_slots(session, settings, tenant_id, slots)  # held until the job's row is committed
    job = Job(
        api_key_id=tenant_id,
        scene_id=body.scene_id,
        state=JobState.QUEUED,
        config=body.config,
        tiling=None if body.tiling is None else body.tiling.model_dump(mode="json"),
        **vocabulary_columns(body),
        maps=maps if any(maps.values()) else None,
        queue=job_queue(settings, maps),
        idempotency_key=idempotency_key,
        request_hash=fingerprint,
        stage_timings={},
    )
    session.add(job)
    try:
        session.commit()
    except IntegrityError:  # a concurrent request with the same key won the insert
        session.rollback()
        earlier = _same_request(session, tenant_id, idempotency_key or "", fingerprint)
        if earlier is None:
            raise
        return earlier, False
    return job, True


def check_vocabulary(body: JobCreate, scene: Scene) -> None:
    """Refuse inline embeddings whose width is not the scene's feature dimension (422), before any row is made."""
    inline = body.vocabulary
    if not isinstance(inline, InlineVocabulary) or inline.embedding_dim in (None, scene.feature_dim):
        return
    if not scene.has_feature_maps:  # the job's features model decides the width (service.map_models)
        return
    raise InvalidInput(
        f"vocabulary.classes[*].embedding: {inline.embedding_dim} values per class, but scene {scene.id}'s "
        f"{scene.feature_space!r} features are {scene.feature_dim}-d; give {scene.feature_dim}-d embeddings or "
        "leave them out to have the names embedded"
    )


def vocabulary_columns(body: JobCreate) -> dict[str, Any]:
    """The job row's vocabulary columns for a request: a built-in name, or the inline classes (each with its
    kind, defaulted as the pipeline would) and their embeddings, or nothing (the bundle's own)."""
    from panogs_core.language.label_sets import default_kind

    vocabulary = body.vocabulary
    if not isinstance(vocabulary, InlineVocabulary):
        return {"vocabulary": vocabulary, "vocabulary_classes": None, "vocabulary_embeddings": None}
    classes = [{"name": c.name, "kind": c.kind or default_kind(c.name)} for c in vocabulary.classes]
    embeddings = None
    if vocabulary.embedding_dim is not None:
        embeddings = [list(c.embedding or ()) for c in vocabulary.classes]
    return {"vocabulary": None, "vocabulary_classes": classes, "vocabulary_embeddings": embeddings}


def public_vocabulary(name: str | None, classes: list[dict[str, str]] | None) -> str | InlineVocabularyPublic | None:
    """The API view of a job's label set: its built-in name, its inline classes, or None (the bundle's)."""
    if classes is not None:
        return InlineVocabularyPublic.model_validate({"classes": classes})
    return name


def _same_request(session: Session, tenant_id: uuid.UUID, key: str, fingerprint: str) -> Job | None:
    earlier = crud.find_idempotent_job(session, tenant_id, key)
    if earlier is not None and earlier.request_hash != fingerprint:
        raise InvalidInput(f"Idempotency-Key {key!r} was already used with a different request")
    return earlier


def read_public(engine: Engine, job_id: uuid.UUID, tenant_id: uuid.UUID) -> JobPublic:
    """A tenant's job as the API shows it: the status-poll path, one autocommit statement and no ORM."""
    with engine.connect() as conn:
        row = crud.read_job_row(conn, job_id, tenant_id)
        tiles = crud.tile_rows(conn, [job_id]).get(job_id, []) if row is not None else []
    if row is None:
        raise NotFound("job", job_id)
    return to_public(row, tiles)


def to_public(job: Job | Row[Any], tiles: Sequence[Row[Any]] = ()) -> JobPublic:
    """The API view of a job, with its tile rows (``crud.tile_rows``) when it was tiled."""
    error = JobError(type=job.error_type, message=job.error_message or "") if job.error_type else None
    return JobPublic(
        id=job.id,
        scene_id=job.scene_id,
        state=job.state,
        stage=job.stage,
        progress=job.progress,
        stage_timings=job.stage_timings or {},
        stage_cached=stage_cached(job.stage_timings or {}, job.cached_stages or []),
        error=error,
        results_ready=results_ready(job),
        fit=fit_public(job),
        config=job.config or {},
        vocabulary=public_vocabulary(job.vocabulary, job.vocabulary_classes),
        tiling=None if job.tiling is None else JobTiling.model_validate(job.tiling),
        maps=None if job.maps is None else JobMaps.model_validate(job.maps),
        tiles=[tile_public(t) for t in tiles],
        cancel_requested=job.cancel_requested,
        attempts=job.attempts,
        created_at=job.created_at,
        started_at=job.started_at,
        finished_at=job.finished_at,
    )


def tile_public(tile: Row[Any]) -> TilePublic:
    """The API view of one tile (or merge) row."""
    return TilePublic(
        index=tile.tile_index,
        kind=tile.kind,
        name=tile.name,
        state=tile.state,
        stage=tile.stage,
        progress=round(float(tile.progress), 4),
        weight=float(tile.weight),
        attempts=tile.attempts,
        wall_s=tile.wall_s,
        peak_rss_mb=tile.peak_rss_mb,
    )


def stage_cached(timings: dict[str, float], cached: list[str]) -> dict[str, bool]:
    """Whether each finished stage was taken from another job's checkpoint (``cached``) or computed."""
    reused = set(cached)
    return {stage: stage in reused for stage in timings}


def results_ready(job: Job | Row[Any]) -> bool:
    """True once a job's results (labels, instances, their artifacts) are recorded: they do not wait for the fit."""
    return job.results_at is not None


def fit_public(job: Job | Row[Any]) -> FitPublic | None:
    """The job's appearance fit, once its results are ready."""
    if job.results_at is None or job.fit_state is None:
        return None
    return FitPublic(state=job.fit_state, progress=round(float(job.fit_progress or 0.0), 4), error=job.fit_error)
