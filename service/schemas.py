"""Request and response bodies, in families (``XCreate / XPublic / XsPublic``), apart from the ORM models."""

from __future__ import annotations

import math
import re
import uuid
from datetime import datetime
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Discriminator,
    Field,
    StringConstraints,
    Tag,
    field_validator,
    model_validator,
)

from panogs_core.language.label_sets import BUILTIN_VOCABULARIES, describe_name, is_builtin_name
from service.db.models import FitState, JobState, TileState, UploadState

MAX_QUERY_CHARS = 1_000
MAX_VECTOR_DIM = 8_192
# An inline vocabulary (POST /v1/jobs): classes, characters per name, and numbers over all embeddings. The JSON body
# cap (PANOGS_MAX_JSON_BODY_BYTES, 1 MiB by default) is usually the tighter bound on the embeddings.
MAX_VOCABULARY_CLASSES = 1_000
MAX_CLASS_NAME_CHARS = 200
MAX_VOCABULARY_VALUES = 1 << 20


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
    fit: FitPublic | None = Field(
        default=None, description="type fit_not_ready: the job's appearance fit (gaussians.ply and renders wait for it)"
    )


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
    has_feature_maps: bool = Field(description="the bundle brings language feature maps; else a job names a model")
    has_mask_maps: bool = Field(description="the bundle brings instance mask maps; else a job names a model")
    bundle_sha256: str | None
    size_bytes: int
    created_at: datetime


class ScenesPublic(BaseModel):
    """A page of scenes, newest first."""

    data: list[ScenePublic]
    count: int
    page: Page


# Jobs ------------------------------------------------------------------------------------------------------


def _builtin_name(value: str) -> str:
    if not is_builtin_name(value):
        raise ValueError(
            f"{describe_name(value)} is not a built-in label set (known: {', '.join(BUILTIN_VOCABULARIES)}); "
            'a job\'s vocabulary is one of those names or an inline {"classes": [...]}, never a file'
        )
    return value.strip().lower()


def _any_case(name: str) -> str:
    """A JSON-Schema (ECMA) pattern of ``name`` in any letter case: ``[sS][cC]...``."""
    return "".join(f"[{c.lower()}{c.upper()}]" if c.isalpha() else re.escape(c) for c in name)


# The names as a pattern in the schema, so that a schema-valid request names a label set that exists; the
# validator says which exist when one does not.
BUILTIN_NAME_PATTERN = r"^\s*(" + "|".join(_any_case(n) for n in BUILTIN_VOCABULARIES) + r")\s*$"
BuiltinVocabularyName = Annotated[
    str,
    StringConstraints(min_length=1, max_length=64),
    AfterValidator(_builtin_name),
    Field(
        description=f"a shipped label set: {' | '.join(BUILTIN_VOCABULARIES)} (case-insensitive)",
        json_schema_extra={"pattern": BUILTIN_NAME_PATTERN},
    ),
]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]


class VocabularyClassIn(BaseModel):
    """One class of an inline vocabulary."""

    model_config = ConfigDict(extra="forbid")

    name: Annotated[str, StringConstraints(strip_whitespace=True, min_length=1, max_length=MAX_CLASS_NAME_CHARS)]
    kind: Literal["thing", "stuff"] | None = Field(
        default=None, description="default: stuff for wall, floor and ceiling, thing otherwise"
    )
    embedding: list[FiniteFloat] | None = Field(
        default=None,
        min_length=1,
        max_length=MAX_VECTOR_DIM,
        description="(D,) text embedding in the scene's feature space (D = the scene's feature_dim); "
        "give one for every class or for none (the worker then embeds the names)",
    )

    @field_validator("name")
    @classmethod
    def _printable(cls, v: str) -> str:
        if not v.isprintable():
            raise ValueError("the class name holds control or separator characters")
        return v

    @field_validator("embedding")
    @classmethod
    def _not_zero(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and not any(v):
            raise ValueError("the embedding is all zeros (it has no direction)")
        if v is not None:
            # The worker holds embeddings as float32 and normalises them: 1e39 passed here as a finite float and
            # became inf there. Refuse what float32 cannot hold, or whose float32 length is inf or 0.
            as_stored = np.asarray(v, dtype=np.float32)
            length = float(np.linalg.norm(as_stored))
            if not np.isfinite(as_stored).all() or not np.isfinite(length) or length == 0:
                raise ValueError(
                    "the embedding does not fit float32 (a value past 3.4e38, or a length that over- or underflows "
                    "it); send a unit vector"
                )
        return v


class InlineVocabulary(BaseModel):
    """A label set given in the request: class names, optional kinds, optional embeddings."""

    model_config = ConfigDict(extra="forbid")

    classes: list[VocabularyClassIn] = Field(min_length=1, max_length=MAX_VOCABULARY_CLASSES)

    @model_validator(mode="after")
    def _consistent(self) -> InlineVocabulary:
        first: dict[str, int] = {}
        for i, entry in enumerate(self.classes):
            j = first.setdefault(entry.name.lower(), i)
            if j != i:
                raise ValueError(f"classes[{i}].name {entry.name!r} repeats classes[{j}] (compared case-insensitively)")
        given = [entry.embedding is not None for entry in self.classes]
        if any(given) and not all(given):
            missing = given.index(False) if given[0] else given.index(True)
            raise ValueError(f"classes[{missing}]: give an embedding for every class or for none")
        dims = [len(entry.embedding) for entry in self.classes if entry.embedding is not None]
        if dims and any(d != dims[0] for d in dims):
            other = next(i for i, d in enumerate(dims) if d != dims[0])
            raise ValueError(f"classes[{other}].embedding has {dims[other]} values, classes[0].embedding {dims[0]}")
        if sum(dims) > MAX_VOCABULARY_VALUES:
            raise ValueError(f"the embeddings hold {sum(dims)} numbers, over the limit of {MAX_VOCABULARY_VALUES}")
        return self

    @property
    def embedding_dim(self) -> int | None:
        """D of the embeddings, or None when the classes carry none."""
        first = self.classes[0].embedding
        return None if first is None else len(first)


def _vocabulary_form(value: Any) -> str | None:
    if isinstance(value, str):
        return "builtin"
    if isinstance(value, dict | InlineVocabulary):
        return "inline"
    return None


JobVocabulary = Annotated[
    Annotated[BuiltinVocabularyName, Tag("builtin")] | Annotated[InlineVocabulary, Tag("inline")],
    Discriminator(
        _vocabulary_form,
        custom_error_type="vocabulary_form",
        custom_error_message='expected a built-in label-set name or an inline {"classes": [...]}',
    ),
]


class JobTiling(BaseModel):
    """How a job is split into tiles that run on several workers and merge into one result (docs/service.md,
    "Tiled jobs"); the planner's settings are ``panogs_core.tiling.plan.TilingConfig``'s."""

    model_config = ConfigDict(extra="forbid")

    tiles: str = Field(
        default="auto",
        pattern=r"^(auto|off|[1-9][0-9]?x[1-9][0-9]?)$",
        description="auto: tiled only when one process could not hold the scene; off: never; NxM: N tiles along "
        "x by M along y",
    )
    halo_m: float | None = Field(default=None, gt=0, le=10, description="metres of halo around a tile's core")
    memory_target_bytes: float | None = Field(default=None, gt=0, description="what one tile may use")
    whole_limit_bytes: float | None = Field(
        default=None, gt=0, description="auto leaves a scene whole up to this estimate; default: half the memory"
    )


class JobMaps(BaseModel):
    """The operator's 2D models a job computes its scene's missing maps with (docs/service.md, "2D maps"): entry
    names of ``PANOGS_MAP_MODELS``, never paths."""

    model_config = ConfigDict(extra="forbid")

    masks: str | None = Field(
        default=None, max_length=64, description="entry name of a masks (SAM-family) model; null: the bundle's masks"
    )
    features: str | None = Field(
        default=None,
        max_length=64,
        description="entry name of a features (CLIP) model; null: the bundle's feature maps",
    )


class MapModelsPublic(BaseModel):
    """The operator's 2D models a job may name (``PANOGS_MAP_MODELS``): entry names per kind, never their folders."""

    masks: list[str] = Field(description="entries of masks (SAM-family) models, sorted")
    features: list[str] = Field(description="entries of features (CLIP) models, sorted")


class JobCreate(BaseModel):
    """Run the pipeline on a scene."""

    model_config = ConfigDict(extra="forbid")

    scene_id: uuid.UUID
    config: dict[str, Any] = Field(
        default_factory=dict,
        description="PipelineConfig overrides, nested by stage; unknown keys are refused",
    )
    vocabulary: JobVocabulary | None = Field(
        default=None,
        description="label set for this run: a built-in name, or inline classes; default: the bundle's own "
        "(docs/service.md, Which request fields reach the host: never a file)",
    )
    tiling: JobTiling | None = Field(
        default=None, description="split the scene into tiles run on several workers; default: not tiled"
    )
    maps: JobMaps | None = Field(
        default=None,
        description="compute 2D masks and/or feature maps with models the operator declared "
        "(PANOGS_MAP_MODELS entry names; an unknown name is refused with the known ones); required for each kind "
        "of map the scene's bundle lacks",
    )


class VocabularyClassPublic(BaseModel):
    """One class of a job's inline vocabulary, with its kind as the run uses it."""

    name: str
    kind: Literal["thing", "stuff"]


class InlineVocabularyPublic(BaseModel):
    """A job's inline vocabulary as the API shows it: the classes (embeddings are not echoed)."""

    classes: list[VocabularyClassPublic]


class JobError(BaseModel):
    """Why a job failed."""

    type: str
    message: str


class FitPublic(BaseModel):
    """The appearance fit of a job whose results are ready: it runs after them."""

    state: FitState = Field(description="running, succeeded, skipped (no fit made), failed or canceled")
    progress: float = Field(description="0..1 over the fit alone")
    error: str | None = Field(default=None, description="why the fit failed or stopped")


class TilePublic(BaseModel):
    """One tile of a tiled job (or its merge, last)."""

    index: int
    kind: Literal["tile", "merge"]
    name: str
    state: TileState = Field(description="pending (the merge, until every tile is done), queued, running, ...")
    stage: str | None
    progress: float = Field(description="0..1 over the tile's stages")
    weight: float = Field(description="its share of the job's progress: the plan's estimated bytes")
    attempts: int
    wall_s: float | None = Field(description="seconds, once finished")
    peak_rss_mb: float | None = Field(description="peak memory, once finished")


class JobPublic(BaseModel):
    """A job's state and progress."""

    id: uuid.UUID
    scene_id: uuid.UUID
    state: JobState
    stage: str | None
    progress: float = Field(description="0..1 over all stages; of a tiled job, its tiles' weighted by their cost")
    stage_timings: dict[str, float] = Field(description="seconds per finished stage")
    stage_cached: dict[str, bool] = Field(
        description="per finished stage: true when it was taken from a checkpoint of an earlier job on the scene "
        "(same inputs and settings), not computed by this job"
    )
    error: JobError | None
    results_ready: bool = Field(
        description="the instances, queries, viewer scene and label artifacts answer (before the fit is done)"
    )
    fit: FitPublic | None = Field(description="the appearance fit, once the results are ready; else null")
    config: dict[str, Any]
    vocabulary: str | InlineVocabularyPublic | None = Field(
        description="the built-in label set asked for, the inline classes, or null: the bundle's own"
    )
    tiling: JobTiling | None = Field(default=None, description="the tiling asked for; null: not tiled")
    maps: JobMaps | None = Field(default=None, description="the 2D models asked for; null: the bundle's maps")
    tiles: list[TilePublic] = Field(
        default_factory=list, description="a tiled job's tiles, then its merge; empty when the scene ran whole"
    )
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

    # "exactly one" in the schema as well: one of the two is a string / an array, the other absent or null.
    model_config = ConfigDict(
        extra="forbid",
        json_schema_extra={
            "oneOf": [
                {"required": ["text"], "properties": {"text": {"type": "string", "pattern": r"\S"}}},
                {"required": ["vector"], "properties": {"vector": {"type": "array"}}},
            ]
        },
    )

    text: str | None = Field(default=None, min_length=1, max_length=MAX_QUERY_CHARS)
    vector: list[float] | None = Field(
        default=None, min_length=1, max_length=MAX_VECTOR_DIM, description="(D,) in the scene's feature space"
    )
    top_k: int = Field(default=10, ge=1, le=1000, description="at most this many hits")
    min_score: float | None = Field(
        default=None,
        ge=-1.0,
        le=1.0,
        description="the threshold a hit's score reaches (default 0.5: the query beats the other classes together)",
    )
    candidates: int = Field(
        default=3,
        ge=0,
        le=100,
        description="at most this many of the best instances under min_score, listed apart in `candidates` "
        "(0: none); the hits are the same whatever this is",
    )

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
    candidates: list[QueryHitPublic] = Field(
        default_factory=list,
        description="the best instances scoring under min_score, best first: no hits, shown so that a query that "
        "matched nothing well still says what came closest and how close",
    )
    min_score: float = Field(description="the threshold the hits reached")
    query_kind: Literal["class", "text", "vector"]
    took_ms: float


# Health ----------------------------------------------------------------------------------------------------


class Health(BaseModel):
    """Liveness or readiness."""

    status: Literal["ok", "unavailable"]
    checks: dict[str, str] = Field(default_factory=dict)
