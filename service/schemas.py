"""Request and response bodies, in families (``XCreate / XPublic / XsPublic``), apart from the ORM models."""

from __future__ import annotations

import math
import uuid
from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from service.db.models import JobState, UploadState

MAX_VOCABULARY_CHARS = 20_000
MAX_QUERY_CHARS = 1_000
MAX_VECTOR_DIM = 8_192


MAX_OFFSET = 1_000_000_000  # list offsets beyond this are refused (they could never find a row)


def error_responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` for the error statuses a route can answer, besides those every route can."""
    common = (400, 401, 422, 503)  # malformed body, API key, validation, database away
    return {code: {"model": ErrorBody, "description": "error"} for code in sorted({*common, *codes})}


class Page(BaseModel):
    """Pagination echo of a list response."""

    limit: int
    offset: int


class ErrorBody(BaseModel):
    """Every error response."""

    type: str = Field(description="stable machine-readable error kind, e.g. not_found, invalid_bundle")
    message: str
    problems: list[str] | None = Field(default=None, description="one line per problem, when there are several")


# Uploads ---------------------------------------------------------------------------------------------------


class UploadPublic(BaseModel):
    """An upload (tus 1.0): ``offset`` of ``length`` bytes received so far."""

    model_config = ConfigDict(from_attributes=True)

    id: uuid.UUID
    filename: str | None
    length: int
    offset: int
    state: UploadState
    sha256: str | None = Field(description="SHA-256 of the whole upload, once complete")
    created_at: datetime
    completed_at: datetime | None


# Scenes ----------------------------------------------------------------------------------------------------


class SceneCreate(BaseModel):
    """Make a scene from a complete upload; the bundle is validated and extracted."""

    model_config = ConfigDict(extra="forbid")

    upload_id: uuid.UUID
    name: str | None = Field(default=None, max_length=255, description="defaults to scene.json's name")


class ScenePublic(BaseModel):
    """A validated scene."""

    model_config = ConfigDict(from_attributes=True)

    id: uuid.UUID
    name: str
    feature_dim: int
    feature_space: str
    num_frames: int
    has_vocabulary: bool
    has_ground_truth: bool
    bundle_sha256: str | None
    size_bytes: int
    created_at: datetime


class ScenesPublic(BaseModel):
    """A page of scenes, newest first."""

    data: list[ScenePublic]
    count: int
    page: Page


# Jobs ------------------------------------------------------------------------------------------------------


class JobCreate(BaseModel):
    """Run the pipeline on a scene."""

    model_config = ConfigDict(extra="forbid")

    scene_id: uuid.UUID
    config: dict[str, Any] = Field(
        default_factory=dict,
        description="PipelineConfig overrides, nested by stage; unknown keys are refused",
    )
    vocabulary: str | None = Field(
        default=None,
        max_length=MAX_VOCABULARY_CHARS,
        description="label set for this run (as `panogs run --vocabulary`); default: the bundle's",
    )


class JobError(BaseModel):
    """Why a job failed."""

    type: str
    message: str


class JobPublic(BaseModel):
    """A job's state and progress."""

    id: uuid.UUID
    scene_id: uuid.UUID
    state: JobState
    stage: str | None
    progress: float = Field(description="0..1 over all stages")
    stage_timings: dict[str, float] = Field(description="seconds per finished stage")
    error: JobError | None
    config: dict[str, Any]
    vocabulary: str | None
    cancel_requested: bool
    attempts: int
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None


class JobsPublic(BaseModel):
    """A page of jobs, newest first."""

    data: list[JobPublic]
    count: int
    page: Page


# Results ---------------------------------------------------------------------------------------------------


class InstancePublic(BaseModel):
    """One instance of a finished job (instances.json)."""

    id: int
    class_name: str
    class_index: int
    kind: str
    score: float
    num_points: int
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]


class InstancesPublic(BaseModel):
    """Every instance of a finished job."""

    data: list[InstancePublic]
    count: int


class ArtifactPublic(BaseModel):
    """A downloadable output of a finished job."""

    model_config = ConfigDict(from_attributes=True)

    name: str
    size_bytes: int
    sha256: str
    media_type: str
    url: str


class ArtifactsPublic(BaseModel):
    """Every downloadable output of a finished job."""

    data: list[ArtifactPublic]
    count: int


class QueryCreate(BaseModel):
    """A text or a vector; exactly one."""

    model_config = ConfigDict(extra="forbid")

    text: str | None = Field(default=None, min_length=1, max_length=MAX_QUERY_CHARS)
    vector: list[float] | None = Field(
        default=None, min_length=1, max_length=MAX_VECTOR_DIM, description="(D,) in the scene's feature space"
    )
    top_k: int = Field(default=10, ge=1, le=1000)
    min_score: float | None = Field(default=None, ge=-1.0, le=1.0)

    @field_validator("vector")
    @classmethod
    def _finite(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and not all(math.isfinite(x) for x in v):
            raise ValueError("vector holds NaN or infinite values")
        return v

    @field_validator("text")
    @classmethod
    def _not_blank(cls, v: str | None) -> str | None:
        if v is not None and not v.strip():
            raise ValueError("text is blank")
        return v

    @model_validator(mode="after")
    def _exactly_one(self) -> QueryCreate:
        if (self.text is None) == (self.vector is None):
            raise ValueError("give exactly one of text or vector")
        return self


class QueryHitPublic(BaseModel):
    """One ranked instance."""

    instance_id: int
    class_name: str
    score: float
    centroid: list[float]
    bbox_min: list[float]
    bbox_max: list[float]


class QueryResult(BaseModel):
    """Instances ranked by similarity to the query, best first."""

    hits: list[QueryHitPublic]
    query_kind: Literal["class", "text", "vector"]
    took_ms: float


# Health ----------------------------------------------------------------------------------------------------


class Health(BaseModel):
    """Liveness or readiness."""

    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = Field(default_factory=dict)
