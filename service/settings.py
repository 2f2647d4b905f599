"""The one infrastructure configuration of the service and the worker (environment prefix ``PANOGS_``).

With nothing set, everything lives under ``./panogs-data`` (the embedded default): a SQLite database, a
filesystem message broker and local storage. The scaled deployment sets ``PANOGS_DATABASE_URL`` (PostgreSQL),
``PANOGS_BROKER_URL`` (Redis) and ``PANOGS_STORAGE_DIR`` (a shared volume). ``.env.example`` lists every
field.

Placeholder secrets (``changethis``) and the embedded defaults are refused when
``PANOGS_ENVIRONMENT=production``.
"""

from __future__ import annotations

import functools
import json
import re
from pathlib import Path, PurePosixPath
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from panogs_core.threads import available_cores, threads_per_process

PLACEHOLDER_SECRET = "changethis"
# Where an operator sets a secret: the compose stack reads .env (POSTGRES_PASSWORD feeds PANOGS_DATABASE_URL).
_SET_YOUR_OWN = "set your own secret (docker compose: in .env, e.g. POSTGRES_PASSWORD; else the environment)"
GIB = 1024**3


MAP_MODEL_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")


class MapModelEntry(BaseModel):
    """One 2D model the operator lets jobs name (``PANOGS_MAP_MODELS``): its kind and its local folder."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    kind: Literal["masks", "features"]  # masks: a SAM-family model; features: a CLIP model
    path: str  # absolute path of a folder in the Hugging Face layout, on the worker (and the API, for text)


# Read from the environment as JSON by the field's own validator, so that an empty value (what docker compose passes
# for an unset variable) means no entries.
MapModelTable = Annotated[dict[str, MapModelEntry], NoDecode]


class Settings(BaseSettings):
    """Every infrastructure setting; the pipeline's own settings are ``PipelineConfig`` (per job)."""

    model_config = SettingsConfigDict(env_prefix="PANOGS_", env_file=".env", extra="ignore", frozen=True)

    environment: Literal["dev", "production"] = "dev"
    data_dir: Path = Path("panogs-data")  # root of everything embedded (database, broker folders, storage)
    database_url: str | None = None  # default: sqlite:///<data_dir>/panogs.db
    broker_url: str | None = None  # default: filesystem:// with folders under <data_dir>/broker
    broker_key_prefix: str = ""  # Redis key prefix (kombu global_keyprefix); lets tests share a Redis
    storage_dir: Path | None = None  # uploads, scenes, artifacts; default <data_dir>/storage
    storage_url: str | None = None  # s3://bucket/prefix: objects in S3 instead of storage_dir
    s3_endpoint_url: str | None = None  # the S3 server (SeaweedFS, MinIO); empty: AWS
    s3_access_key_id: str | None = None
    s3_secret_access_key: str | None = None
    s3_region: str = "us-east-1"
    # The S3 server as the API's clients reach it (a published port, a DNS name that names the same server): set, a
    # download asked with ?redirect=true answers 307 to a link signed for it; empty: downloads go through the API
    # unless the storage is AWS itself (no endpoint), whose links anyone reaches.
    s3_public_endpoint_url: str | None = None
    # With object storage, a worker keeps the bundles of the scenes it ran on its disk up to this many bytes (least
    # recently used go first), so that a scene's next job does not fetch its bundle again; 0: fetch it every job.
    bundle_cache_bytes: int = Field(default=8 * 1024**3, ge=0)
    signed_link_ttl_s: int = Field(default=900, ge=10, le=7 * 24 * 3600)  # s, how long a redirect's link holds
    storage_signing_key: str | None = None  # signs local download links; default: a secret of each process

    # Uploads.
    max_upload_bytes: int = Field(default=16 * GIB, gt=0)  # largest accepted bundle archive
    bundle_max_bytes: int | None = Field(default=None, gt=0)  # extracted size limit; None: the core's default
    upload_ttl_s: int = Field(default=24 * 3600, gt=0)  # unfinished uploads older than this are deleted

    # Jobs and workers.
    job_queue: str = "cpu"  # queue the API sends new jobs to ("gpu" where GPU workers run)
    worker_queues: str = "cpu"  # comma-separated queues a worker consumes
    worker_pool: Literal["solo", "prefork", "threads"] = "solo"  # one job per worker process by default
    worker_concurrency: int = Field(default=1, gt=0)
    worker_threads: int | None = Field(default=None, gt=0)  # per worker process; None: its share of the cores
    job_time_limit_s: float = Field(default=6 * 3600, gt=0)  # a running job past this fails (checked in progress)
    broker_visibility_timeout_s: int = Field(default=12 * 3600, gt=0)  # must exceed job_time_limit_s
    heartbeat_interval_s: float = Field(default=10.0, gt=0)  # how often a running job proves its worker alive
    heartbeat_timeout_s: float = Field(default=60.0, gt=0)  # silent this long: the worker is presumed lost
    max_attempts: int = Field(default=3, gt=0)  # worker losses before a job is failed instead of re-queued
    progress_interval_s: float = Field(default=0.5, ge=0)  # least time between progress writes/cancel checks
    reaper_interval_s: float = Field(default=5.0, gt=0)  # API-side sweep for lost jobs and undispatched jobs
    transient_retry_s: float = Field(default=120.0, ge=0)  # how long the worker waits out a database outage

    # API.
    api_key_cache_s: float = Field(default=5.0, ge=0)  # a revoked key may work this much longer per process
    status_cache_s: float = Field(default=0.2, ge=0)  # a job's status may be this stale (< progress_interval_s)
    query_encoder: Literal["process", "off"] = "process"  # free-text queries: encoder in a child process
    text_model_path: str | None = None  # local text-encoder weights (panogs_core.language.text_encoders)
    result_cache_size: int = Field(default=32, ge=1)  # finished results kept loaded for queries
    auto_migrate: bool = True  # `panogs serve` upgrades the database to head on start
    max_json_body_bytes: int = Field(default=1024 * 1024, gt=0)  # JSON bodies (not uploads) above this: 413
    max_validation_problems: int = Field(default=5, ge=1)  # a 422 lists this many problems and counts the rest

    # Hostile-input limits: every JSON document from a user (request bodies, a bundle's JSON files)
    # and every image of a bundle. Each may be lowered; the ceiling (le) is the core's own limit, with which the
    # worker validates the bundle again (panogs_core.io.bundle.reader.BundleLimits), so a higher value could not
    # hold there.
    max_json_depth: int = Field(default=64, ge=2, le=64)  # nesting levels of arrays and objects
    max_json_int_digits: int = Field(default=20, ge=1, le=20)  # digits of one integer (20 holds any 64-bit one)
    bundle_max_json_bytes: int = Field(default=16 * 1024**2, gt=0, le=64 * 1024**2)  # scene.json, vocabulary.json
    max_image_pixels: int = Field(default=40_000_000, gt=0, le=100_000_000)  # per image (and feature map) of a bundle
    # A bundle's validation runs in a child process (docs/service.md, "Validation budget"): this many at once per API
    # process (the next request is a 503 with Retry-After), each within this many CPU seconds per GiB of archive.
    validation_slots: int = Field(default=2, ge=1, le=64)
    validation_cpu_s: float = Field(default=10.0, gt=0, le=3600)
    # Address space of one validation child (the fork server's ~0.3 GB included; gt/labels.npz may be 1 GiB read whole).
    validation_memory_bytes: int = Field(default=2 * GIB, ge=512 * 1024**2)

    # The 2D-maps stage: the models jobs may name, and where their jobs run (docs/service.md, "2D maps").
    map_models: MapModelTable = {}  # JSON: entry name -> {"kind": masks | features, "path": absolute folder}
    maps_queue: Literal["cpu", "gpu"] | None = None  # queue of jobs that compute maps; unset or empty: job_queue

    # The app and the data lifecycle.
    session_ttl_s: int = Field(default=8 * 3600, gt=0)  # an app sign-in (HttpOnly cookie) lasts this long
    quota_bytes: int | None = Field(default=100 * GIB, gt=0)  # per tenant: uploads + scenes + results; None: none
    quota_concurrent_jobs: int | None = Field(default=4, gt=0)  # per tenant: queued + running jobs; None: none
    retention_days: float | None = Field(default=None, gt=0)  # finished jobs older than this are deleted
    min_free_disk_bytes: int = Field(default=1 * GIB, ge=0)  # an extraction leaves at least this much free

    log_level: str = "INFO"
    max_tiles_per_job: int = Field(default=64, gt=0, le=9801)  # NxM tiles one job may ask (and one per frame)
    storage_probe_timeout_s: float = Field(default=2.0, gt=0, le=30)  # /readyz: how long the object store has to answer
    storage_probe_cache_s: float = Field(default=5.0, ge=0, le=60)  # /readyz: how long one storage probe's answer holds

    @field_validator("maps_queue", mode="before")
    @classmethod
    def _empty_is_unset(cls, value: Any) -> Any:
        return None if value == "" else value  # docker compose passes an unset ${PANOGS_MAPS_QUEUE:-} as ""

    @field_validator("map_models", mode="before")
    @classmethod
    def _json_object(cls, value: Any) -> Any:
        """The environment's JSON text (empty: no entries); a dict as given in code."""
        if not isinstance(value, str):
            return value
        if not value.strip():
            return {}
        try:
            return json.loads(value)
        except ValueError as exc:
            raise ValueError(f"PANOGS_MAP_MODELS is not JSON ({exc}); expected an object of entries") from exc

    @model_validator(mode="after")
    def _check(self) -> Settings:
        if self.broker_visibility_timeout_s <= self.job_time_limit_s:
            raise ValueError(
                f"broker_visibility_timeout_s ({self.broker_visibility_timeout_s}) must exceed "
                f"job_time_limit_s "
                f"({self.job_time_limit_s}), or a running job's message is delivered twice"
            )
        if self.heartbeat_timeout_s <= self.heartbeat_interval_s:
            raise ValueError("heartbeat_timeout_s must exceed heartbeat_interval_s")
        check_map_models(self.map_models)
        if self.storage_url is not None and not self.storage_url.startswith("s3://"):
            raise ValueError(f"PANOGS_STORAGE_URL must be s3://bucket[/prefix], not {self.storage_url!r}")
        secret = self.s3_secret_access_key or ""
        if self.environment == "production" and PLACEHOLDER_SECRET in secret:
            raise ValueError(
                f"PANOGS_S3_SECRET_ACCESS_KEY still holds the placeholder {PLACEHOLDER_SECRET!r}: {_SET_YOUR_OWN}"
            )
        if self.environment == "production":
            for name in ("database_url", "broker_url"):
                value = getattr(self, name)
                if not value:
                    raise ValueError(f"PANOGS_{name.upper()} must be set in production")
                if PLACEHOLDER_SECRET in value:
                    raise ValueError(
                        f"PANOGS_{name.upper()} still holds the placeholder {PLACEHOLDER_SECRET!r}: {_SET_YOUR_OWN}"
                    )
        return self

    @property
    def database(self) -> str:
        """The database URL in force."""
        return self.database_url or f"sqlite:///{(self.data_dir / 'panogs.db').resolve()}"

    @property
    def broker(self) -> str:
        """The broker URL in force."""
        return self.broker_url or "filesystem://"

    @property
    def is_embedded_broker(self) -> bool:
        """True when the broker is the serverless filesystem transport."""
        return self.broker.startswith("filesystem://")

    @property
    def worker_thread_count(self) -> int:
        """Threads of torch, OpenMP and BLAS in each worker process: ``worker_threads``, else the cores this
        process may use divided by the jobs a worker runs at once (panogs_core/threads.py)."""
        if self.worker_threads is not None:
            return self.worker_threads
        jobs_at_once = 1 if self.worker_pool == "solo" else self.worker_concurrency  # solo ignores concurrency
        return threads_per_process(available_cores(), jobs_at_once)

    @property
    def storage(self) -> Path:
        """Root of uploads, scenes and artifacts."""
        return (self.storage_dir or self.data_dir / "storage").resolve()

    @property
    def broker_folder(self) -> Path:
        """Folder of the filesystem broker's messages."""
        return (self.data_dir / "broker").resolve()

    def broker_transport_options(self) -> dict[str, Any]:
        """kombu transport options for the broker in force."""
        if self.is_embedded_broker:
            folder = self.broker_folder
            return {
                "data_folder_in": str(folder / "queue"),
                "data_folder_out": str(folder / "queue"),
                "control_folder": str(folder / "control"),
                "processed_folder": str(folder / "processed"),
                "store_processed": False,
                "polling_interval": 0.2,  # seconds; an idle embedded worker starts a job this quickly
            }
        options: dict[str, Any] = {"visibility_timeout": self.broker_visibility_timeout_s}
        if self.broker_key_prefix:
            options["global_keyprefix"] = self.broker_key_prefix
        return options

    def map_model_names(self, kind: str) -> list[str]:
        """The entries of ``map_models`` of one kind (``masks`` or ``features``), sorted."""
        return sorted(name for name, entry in self.map_models.items() if entry.kind == kind)

    def ensure_dirs(self) -> None:
        """Create the local folders this configuration writes to."""
        self.storage.mkdir(parents=True, exist_ok=True)
        if self.database.startswith("sqlite:///"):
            Path(self.database.removeprefix("sqlite:///")).parent.mkdir(parents=True, exist_ok=True)
        if self.is_embedded_broker:
            for key in ("data_folder_in", "control_folder", "processed_folder"):
                Path(self.broker_transport_options()[key]).mkdir(parents=True, exist_ok=True)


def check_map_models(entries: dict[str, MapModelEntry]) -> None:
    """Refuse an entry whose name is not a plain word or whose path is not absolute, naming the entry.

    A relative path would resolve against whichever folder a process started in, so the API and the workers could
    read different folders under one name.
    """
    for name, entry in entries.items():
        if not MAP_MODEL_NAME.fullmatch(name):
            raise ValueError(
                f"PANOGS_MAP_MODELS: entry name {name!r}: letters, digits, '.', '_' or '-' (at most 64), "
                "starting with a letter or digit"
            )
        if not PurePosixPath(entry.path).is_absolute():
            raise ValueError(
                f"PANOGS_MAP_MODELS: entry {name!r} ({entry.kind}): path {entry.path!r} is not absolute; give the "
                "model folder's absolute path on the worker"
            )


@functools.cache
def get_settings() -> Settings:
    """The process-wide settings, read once from the environment (and ``.env``)."""
    return Settings()
