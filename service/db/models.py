"""The tables: API keys (tenants), uploads, scenes, jobs, their tiles and their artifacts.

Every upload, scene and job belongs to the API key that created it; every query filters by it. Paths are
stored relative to ``Settings.storage`` so that a shared volume may be mounted anywhere.
"""

from __future__ import annotations

import enum
import uuid
from datetime import datetime
from typing import Any

from sqlalchemy import JSON, BigInteger, Boolean, Enum, Float, ForeignKey, Index, Integer, String, Text, true
from sqlalchemy import UniqueConstraint as Unique
from sqlalchemy.orm import Mapped, mapped_column, relationship

from panogs_core.pipeline.result import FitState as FitState  # the pipeline's own states, one enum for both
from service.db.base import Base, IdMixin, TimestampedMixin, UTCDateTime


def _str_enum(cls: type[enum.Enum]) -> Enum:
    # Stored as plain strings (no native enum type, no CHECK): adding a state needs no migration.
    return Enum(
        cls,
        native_enum=False,
        create_constraint=False,
        length=16,
        values_callable=lambda e: [m.value for m in e],
    )


class UploadState(enum.StrEnum):
    """Lifecycle of an upload."""

    RECEIVING = "receiving"  # bytes still arriving (resumable)
    COMPLETE = "complete"  # every byte arrived and the checksum matched
    CONSUMED = "consumed"  # a scene was made from it; the archive is gone


class JobState(enum.StrEnum):
    """Lifecycle of a job: queued -> running -> succeeded | failed | canceled."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"

    @property
    def is_terminal(self) -> bool:
        """True for the states a job never leaves."""
        return self in TERMINAL_STATES


TERMINAL_STATES = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELED})


class TileKind(enum.StrEnum):
    """What a row of ``job_tile`` runs: one tile of a tiled job's plan, or the merge of all of them."""

    TILE = "tile"
    MERGE = "merge"


class TileState(enum.StrEnum):
    """Lifecycle of a tile (and of a tiled job's merge): pending (the merge, until the last tile is done) -> queued
    -> running -> succeeded | failed | canceled. Lease, heartbeat and attempts follow a job's rules."""

    PENDING = "pending"
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"


class ApiKey(IdMixin, TimestampedMixin, Base):
    """A tenant. Only the SHA-256 of the secret is stored; the prefix finds the row."""

    __tablename__ = "api_key"

    name: Mapped[str] = mapped_column(String(100))
    prefix: Mapped[str] = mapped_column(String(16), unique=True)
    key_hash: Mapped[str] = mapped_column(String(64))
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class Upload(IdMixin, TimestampedMixin, Base):
    """A resumable upload of a bundle archive (tus 1.0)."""

    __tablename__ = "upload"

    api_key_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("api_key.id", ondelete="CASCADE"), index=True)
    filename: Mapped[str | None] = mapped_column(String(255))
    length: Mapped[int] = mapped_column(BigInteger)
    offset: Mapped[int] = mapped_column(BigInteger, default=0)
    state: Mapped[UploadState] = mapped_column(_str_enum(UploadState), default=UploadState.RECEIVING)
    expected_sha256: Mapped[str | None] = mapped_column(String(64))
    sha256: Mapped[str | None] = mapped_column(String(64))
    path: Mapped[str] = mapped_column(String(512))
    # With object storage, the multipart upload the bytes go into at ``offset``: its id, the parts sent (number,
    # size, tag) and the tail's length (service/storage/parts.py), moved with the offset in one statement. NULL with
    # the local backend, and on uploads begun before it was kept here (their state is an object).
    multipart: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    completed_at: Mapped[datetime | None] = mapped_column(UTCDateTime)


class Scene(IdMixin, TimestampedMixin, Base):
    """A validated bundle, extracted under the storage folder."""

    __tablename__ = "scene"

    api_key_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("api_key.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(255))
    feature_dim: Mapped[int] = mapped_column(Integer)
    feature_space: Mapped[str] = mapped_column(String(64))
    num_frames: Mapped[int] = mapped_column(Integer)
    has_vocabulary: Mapped[bool] = mapped_column(Boolean)
    has_ground_truth: Mapped[bool] = mapped_column(Boolean)
    bundle_path: Mapped[str] = mapped_column(String(512))
    bundle_sha256: Mapped[str | None] = mapped_column(String(64))
    size_bytes: Mapped[int] = mapped_column(BigInteger, default=0)
    # Whether the bundle brings its own 2D maps (some frame has one); a kind it lacks needs a job that names a model
    # to compute it (service.map_models). Rows from before bundles could lack maps had both.
    has_feature_maps: Mapped[bool] = mapped_column(Boolean, default=True, server_default=true())
    has_mask_maps: Mapped[bool] = mapped_column(Boolean, default=True, server_default=true())


class Job(IdMixin, TimestampedMixin, Base):
    """One pipeline run on a scene; its progress, timings, error and lease live here, not in the broker."""

    __tablename__ = "job"
    __table_args__ = (
        Unique("api_key_id", "idempotency_key"),
        Index("ix_job_state_heartbeat_at", "state", "heartbeat_at"),
    )

    api_key_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("api_key.id", ondelete="CASCADE"), index=True)
    scene_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("scene.id", ondelete="CASCADE"), index=True)
    state: Mapped[JobState] = mapped_column(_str_enum(JobState), default=JobState.QUEUED)
    stage: Mapped[str | None] = mapped_column(String(64))
    progress: Mapped[float] = mapped_column(Float, default=0.0)  # 0..1 over all stages
    stage_timings: Mapped[dict[str, float]] = mapped_column(JSON, default=dict)  # stage -> seconds
    # The stages this job took from another job's checkpoint of its scene instead of computing them (the shared
    # checkpoints, docs/service.md); NULL on rows from before it was recorded: none known.
    cached_stages: Mapped[list[str] | None] = mapped_column(JSON(none_as_null=True))
    config: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)  # overrides as given
    # The label set: a built-in name in ``vocabulary``, or an inline list in ``vocabulary_classes`` (name and kind per
    # class) with its (L, D) ``vocabulary_embeddings`` (or NULL: the worker embeds the names); both NULL: the
    # bundle's own. Never a path (docs/service.md). The embeddings are deferred: the status poll never reads them.
    vocabulary: Mapped[str | None] = mapped_column(Text)
    vocabulary_classes: Mapped[list[dict[str, str]] | None] = mapped_column(JSON(none_as_null=True))
    vocabulary_embeddings: Mapped[list[list[float]] | None] = mapped_column(JSON(none_as_null=True), deferred=True)
    queue: Mapped[str] = mapped_column(String(64))
    idempotency_key: Mapped[str | None] = mapped_column(String(255))
    request_hash: Mapped[str] = mapped_column(String(64))  # tells a retry from a reuse of the key
    error_type: Mapped[str | None] = mapped_column(String(100))
    error_message: Mapped[str | None] = mapped_column(Text)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    attempts: Mapped[int] = mapped_column(Integer, default=0)  # times a worker claimed it
    lease: Mapped[str | None] = mapped_column(String(64))  # the claiming task's id; guards every write
    worker: Mapped[str | None] = mapped_column(String(255))
    enqueued_at: Mapped[datetime | None] = mapped_column(UTCDateTime)  # NULL: not yet handed to the broker
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # The results come before the appearance fit: ``results_at`` is when the labels, instances and their artifacts
    # were recorded (NULL: not yet), and from then on ``fit_state`` / ``fit_progress`` (0..1 over the fit alone) /
    # ``fit_error`` follow the fit (docs/service.md, "Results before the fit").
    results_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    fit_state: Mapped[FitState | None] = mapped_column(_str_enum(FitState))
    fit_progress: Mapped[float | None] = mapped_column(Float)
    fit_error: Mapped[str | None] = mapped_column(Text)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # How the job asked to be tiled (``JobTiling``: tiles auto | off | NxM, planner settings); NULL: not tiled. Whether
    # it was is told by its ``job_tile`` rows (docs/service.md, "Tiled jobs").
    tiling: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    # The operator's 2D models the job computes maps with: entry names of PANOGS_MAP_MODELS per kind ({"masks": name
    # or null, "features": name or null}), never paths; NULL: the bundle's maps (docs/service.md, "2D maps").
    maps: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))

    artifacts: Mapped[list[Artifact]] = relationship(
        back_populates="job", cascade="all, delete-orphan", order_by="Artifact.name"
    )


class JobTile(IdMixin, TimestampedMixin, Base):
    """One tile of a tiled job, or its merge (``kind``), run by its own task under the same lease, heartbeat and
    attempt rules as a job; the job's progress is the tiles' weighted by ``weight`` (docs/service.md, "Tiled jobs")."""

    __tablename__ = "job_tile"
    __table_args__ = (
        Unique("job_id", "tile_index"),
        Index("ix_job_tile_state_heartbeat_at", "state", "heartbeat_at"),
    )

    job_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"), index=True)
    tile_index: Mapped[int] = mapped_column(Integer)  # the plan's tile index; the merge comes after the last tile
    kind: Mapped[TileKind] = mapped_column(_str_enum(TileKind))
    name: Mapped[str] = mapped_column(String(64))  # the tile's folder under the job's tiles/ (the plan's name)
    state: Mapped[TileState] = mapped_column(_str_enum(TileState))
    stage: Mapped[str | None] = mapped_column(String(64))
    progress: Mapped[float] = mapped_column(Float, default=0.0)  # 0..1 over the tile's stages
    weight: Mapped[float] = mapped_column(Float)  # the plan's estimated bytes of the tile (of the merge: a share)
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    lease: Mapped[str | None] = mapped_column(String(64))
    worker: Mapped[str | None] = mapped_column(String(255))
    enqueued_at: Mapped[datetime | None] = mapped_column(UTCDateTime)  # NULL: not yet handed to the broker
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    wall_s: Mapped[float | None] = mapped_column(Float)  # the finished run's wall time
    peak_rss_mb: Mapped[float | None] = mapped_column(Float)  # the finished run's peak memory
    # A finished tile's row of the tiled report.json (core and halo primitives, frames, instances)
    report: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    error_type: Mapped[str | None] = mapped_column(String(100))
    error_message: Mapped[str | None] = mapped_column(Text)


class Artifact(IdMixin, TimestampedMixin, Base):
    """A downloadable file of a finished job."""

    __tablename__ = "artifact"
    __table_args__ = (Unique("job_id", "name"),)

    job_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("job.id", ondelete="CASCADE"), index=True)
    name: Mapped[str] = mapped_column(String(255))
    path: Mapped[str] = mapped_column(String(512))
    size_bytes: Mapped[int] = mapped_column(BigInteger)
    sha256: Mapped[str] = mapped_column(String(64))
    media_type: Mapped[str] = mapped_column(String(100))

    job: Mapped[Job] = relationship(back_populates="artifacts")


class AppSession(IdMixin, TimestampedMixin, Base):
    """A signed-in browser of the app: the API key was exchanged once for a random token held in an HttpOnly
    cookie. Only the token's SHA-256 is stored; the row dies with its key (revoked: refused; deleted: cascade)."""

    __tablename__ = "app_session"

    api_key_id: Mapped[uuid.UUID] = mapped_column(ForeignKey("api_key.id", ondelete="CASCADE"), index=True)
    token_hash: Mapped[str] = mapped_column(String(64), unique=True)
    expires_at: Mapped[datetime] = mapped_column(UTCDateTime)
