"""Run one job: claim it, run the pipeline with progress, heartbeats and cancellation, record the outcome.

``execute_job`` knows nothing of Celery: tests call it with a scripted pipeline and a SQLite database.

- **Claim**: a job is run by the task holding its ``lease``; every write is guarded by it (``crud``).
- **Progress**: ``on_progress(stage, done, total)`` writes stage, overall progress and per-stage timings at
  most every ``progress_interval_s``, and checks for a cancel request and the time limit at the same
  moments. A database that is briefly away only skips progress writes; the run goes on.
- **Heartbeat**: a thread refreshes ``heartbeat_at`` every ``heartbeat_interval_s``, also inside long
  stages; the API's reaper re-queues (or fails) a running job whose heartbeat stops.
- **Cancellation** is cooperative: the callback raises :class:`panogs_core.errors.Cancelled`, which stages let
  through, between and inside stages.
- **Resume**: the pipeline runs with ``resume=True`` in the job's own folder, so a job claimed again after its
  worker died reuses the checkpoints of the stages that finished.
- **Vocabulary**: the pipeline gets a built-in label-set name or the job's inline classes, parsed here; never a
  string that could name a file (:func:`job_vocabulary`, docs/service.md "Which request fields reach the host").
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, TypeVar

from sqlalchemy import func, select, update
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from panogs_core.errors import Cancelled, PanoGSError
from panogs_core.io.run_folder import DOWNLOADABLE, GAUSSIANS_PLY
from panogs_core.types import Vocabulary
from service import jobs
from service.db import crud
from service.db.base import utcnow
from service.db.faults import DatabaseFault, classify
from service.db.models import Artifact, FitState, Job, JobState, Scene
from service.db.session import session_scope
from service.settings import Settings
from service.storage import Storage, TreePush, sha256_file
from service.storage.objects import StorageError, StorageUnavailable
from worker.bundle_cache import BundleCache
from worker.shared_checkpoints import SceneCheckpoints

logger = logging.getLogger(__name__)
T = TypeVar("T")

# The pipeline's outputs that become downloadable artifacts, with their media types (the run folder's declaration).
ARTIFACTS = {name: spec.media_type for name, spec in DOWNLOADABLE.items()}
# The stage that runs after the results are written, and the file it finishes (served once the fit is done).
FIT_STAGE = "appearance"
FITTED_FILES = frozenset({GAUSSIANS_PLY.name})


class PipelineFn(Protocol):
    """``panogs_core.pipeline.run.run_pipeline``'s signature, as the runner uses it."""

    def __call__(
        self,
        bundle: Path,
        out_dir: Path,
        config: Any,
        *,
        vocabulary: str | Vocabulary | None,
        on_progress: Callable[[str, int, int], None],
        resume: bool,
        on_results: Callable[[Any], None],
        shared: Any,
    ) -> Any: ...


class TransientError(Exception):
    """The database or broker was away for longer than the runner waits; the task is retried later."""


class CancelRequested(Cancelled):
    """The job's owner asked to cancel it."""


class LeaseLost(Cancelled):
    """Another task now holds the job (this worker was presumed dead); stop without writing anything."""

    save_partial_work = False


class TimeLimitExceeded(Cancelled):
    """The job ran past ``job_time_limit_s``."""


class Interrupted(Cancelled):
    """The worker is shutting down; the job goes back to the queue and resumes later."""


class StorageStop(Cancelled):
    """The object storage failed a call the pipeline made (a stage's progress, which stores the stage before it, or
    a shared checkpoint's fetch or store). Raised as a cancel so that it passes through the appearance fit, which
    would otherwise record any error as the fit's own failure and let the results stand: the worker then treats
    ``error`` as it treats a storage error anywhere else (an outage retries the job with backoff, a refusal fails
    it with its message)."""

    def __init__(self, error: StorageError) -> None:
        super().__init__(str(error))
        self.error = error


def stopping_on_storage_errors(fn: Callable[..., T]) -> Callable[..., T]:
    """``fn``, its storage errors raised as :class:`StorageStop`."""

    def call(*args: Any, **kwargs: Any) -> T:
        try:
            return fn(*args, **kwargs)
        except StorageError as exc:
            raise StorageStop(exc) from exc

    return call


class _CheckpointsThroughStops:
    """The scene's checkpoints as the pipeline sees them: their storage errors are :class:`StorageStop`."""

    def __init__(self, shared: SceneCheckpoints) -> None:
        self.fetch = stopping_on_storage_errors(shared.fetch)
        self.store = stopping_on_storage_errors(shared.store)
        self.known_input_hash = stopping_on_storage_errors(shared.known_input_hash)
        self.keep_input_hash = stopping_on_storage_errors(shared.keep_input_hash)


@dataclass(frozen=True)
class JobEnv:
    """Everything a job run needs besides its id; built once per worker process."""

    settings: Settings
    session_factory: sessionmaker[Session]
    storage: Storage
    pipeline: PipelineFn
    make_config: Callable[[dict[str, Any]], Any]
    stages: tuple[str, ...] = ()
    shutdown: threading.Event = field(default_factory=threading.Event)  # set when the worker is stopping
    # Publishes a tiled job's tile and merge tasks; None: a Celery app for ``settings`` (tests pass a recorder).
    sender: Any = None


def load_pipeline() -> tuple[PipelineFn, tuple[str, ...], Callable[[dict[str, Any]], Any]]:
    """The core's pipeline, its stage names and the config factory the API checks a job's overrides with.

    Imports the pipeline, torch with it: a task calls this, never a prefork parent. Tests put a stand-in pipeline
    here (tests/support/pipeline_stand_in.py); no setting can.
    """
    from panogs_core.pipeline.run import STAGES, run_pipeline

    return run_pipeline, tuple(STAGES), jobs.pipeline_config


def with_db_retry(fn: Callable[[], T], *, deadline_s: float, what: str) -> T:
    """Call ``fn``; while the database is unreachable, retry with backoff until ``deadline_s`` has passed.

    Only an outage is waited out: any other database error (an integrity error, a bug) cannot pass by waiting and
    is raised at once.
    """
    start = time.monotonic()
    delay = 0.25
    while True:
        try:
            return fn()
        except DBAPIError as exc:
            if classify(exc) is not DatabaseFault.OUTAGE:
                raise
            if time.monotonic() - start + delay > deadline_s:
                raise TransientError(f"database unavailable while trying to {what}: {exc.orig!r}") from exc
            logger.warning("database unavailable (%s); retrying in %.1f s", what, delay)
            time.sleep(delay)
            delay = min(delay * 2, 5.0)


@dataclass
class Tracker:
    """Progress state of one run, shared by the callback and the heartbeat thread."""

    job_id: uuid.UUID
    lease: str
    env: JobEnv
    timings: dict[str, float]
    cached: list[str] = field(default_factory=list)  # stages taken from another job's checkpoint, earlier attempts'
    computed_before: frozenset[str] = frozenset()  # stages an earlier attempt of this job computed (and stored)
    started: float = field(default_factory=time.monotonic)
    stage: str | None = None
    stage_started: float = 0.0
    last_write: float = 0.0
    stop: threading.Event = field(default_factory=threading.Event)
    lost: bool = False
    results_ready: bool = False  # the results are recorded; what runs now is the appearance fit
    fit_progress: float = 0.0
    push: TreePush | None = None  # stores the output folder (object storage), after each stage and at the end
    shared: SceneCheckpoints | None = None  # the scene's checkpoints; its leases are renewed with the heartbeat

    def push_outputs(self, *, best_effort: bool = False) -> None:
        """Store what changed in the output folder (nothing with the local backend, which writes in place)."""
        if self.push is None:
            return
        try:
            self.push.push()
        except StorageError:
            if not best_effort:
                raise
            logger.warning("job %s: could not store its partial work", self.job_id, exc_info=True)

    def stage_values(self) -> dict[str, Any]:
        """The per-stage columns as they stand: the stage times and the stages taken from the scene's checkpoints
        (by an earlier attempt or by this one)."""
        # A stage an earlier attempt computed comes back from the scene's store on a retry: not another job's.
        reused = [s for s in (self.shared.reused if self.shared else []) if s not in self.computed_before]
        return {"stage_timings": dict(self.timings), "cached_stages": list(dict.fromkeys([*self.cached, *reused]))}

    def fraction(self, stage: str, done: int, total: int) -> float:
        if stage not in self.env.stages:
            return 0.0
        within = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
        return (self.env.stages.index(stage) + within) / len(self.env.stages)

    def close_stage(self, now: float) -> None:
        # A stage that a previous attempt finished keeps that attempt's time (a resumed stage takes ~0 s).
        if self.stage is not None and self.stage not in self.timings:
            self.timings[self.stage] = round(now - self.stage_started, 3)

    def on_progress(self, stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        changed = stage != self.stage
        if changed:
            self.close_stage(now)
            self.stage, self.stage_started = stage, now
            self.push_outputs()  # the stage before this one has its checkpoint: store it
        if self.lost:
            raise LeaseLost(f"job {self.job_id}: another worker holds it now")
        if self.env.shutdown.is_set():
            raise Interrupted("the worker is shutting down")
        if not changed and now - self.last_write < self.env.settings.progress_interval_s:
            return
        self.last_write = now
        if now - self.started > self.env.settings.job_time_limit_s:
            raise TimeLimitExceeded(f"the job ran longer than {self.env.settings.job_time_limit_s:g} s")
        values: dict[str, Any] = {}
        if self.results_ready and stage == FIT_STAGE:
            self.fit_progress = min(max(done / total, 0.0), 1.0) if total > 0 else 0.0
            values["fit_progress"] = self.fit_progress
        self.write(stage=stage, progress=self.fraction(stage, done, total), **self.stage_values(), **values)

    def write(self, **values: Any) -> None:
        """Progress and heartbeat write; a database that is away is skipped, a lost lease or a cancel
        stops."""
        try:
            with session_scope(self.env.session_factory) as session:
                held = crud.update_running(session, self.job_id, self.lease, **values)
                cancel = crud.cancel_requested(session, self.job_id)
        except DBAPIError as exc:
            logger.warning("job %s: progress not recorded, database unavailable (%r)", self.job_id, exc.orig)
            return
        if not held:
            self.lost = True
            raise LeaseLost(f"job {self.job_id}: another worker holds it now, or it was finished")
        if cancel:
            raise CancelRequested("canceled at the owner's request")

    @contextmanager
    def beating(self) -> Iterator[None]:
        """Heartbeats from a thread while the body runs; stopped before the outcome is written. May be entered again
        (a job that asked for tiles beats while it plans, then, left whole, while it runs)."""
        self.stop.clear()
        beat = threading.Thread(target=self.heartbeat_loop, name=f"heartbeat-{self.job_id}", daemon=True)
        beat.start()
        try:
            yield
        finally:
            self.stop.set()
            beat.join(timeout=5)

    def heartbeat_loop(self) -> None:
        while not self.stop.wait(self.env.settings.heartbeat_interval_s):
            if self.shared is not None:
                self.shared.refresh()
            try:
                self.write()
            except CancelRequested:
                pass  # the progress callback raises it in the pipeline's thread
            except LeaseLost:
                logger.warning("job %s: lease lost; the pipeline stops at its next progress step", self.job_id)
                return


def execute_job(job_id: uuid.UUID, *, lease: str, worker: str, env: JobEnv) -> JobState | None:
    """Run job ``job_id`` under ``lease``; returns the state it ended in, or None when it was not ours to run.

    Raises:
        TransientError: the database stayed away longer than ``transient_retry_s``; retry the task later.
    """
    deadline = env.settings.transient_retry_s
    job = with_db_retry(lambda: _claim(job_id, lease, worker, env), deadline_s=deadline, what="claim the job")
    if job is None:
        return None
    if job.attempts > env.settings.max_attempts:
        message = f"the job was started {job.attempts - 1} times and its worker was lost each time"
        _finish(job_id, lease, env, JobState.FAILED, error_type="WorkerLost", error_message=message)
        return JobState.FAILED
    logger.info("job %s: running (attempt %d, worker %s)", job_id, job.attempts, worker)
    timings, cached = dict(job.stage_timings or {}), list(job.cached_stages or [])
    tracker = Tracker(
        job_id=job_id,
        lease=lease,
        env=env,
        timings=timings,
        cached=cached,
        computed_before=frozenset(timings) - set(cached),
    )
    return _run(job, tracker, env)


def _claim(job_id: uuid.UUID, lease: str, worker: str, env: JobEnv) -> Job | None:
    with session_scope(env.session_factory) as session:
        stale = crud.stale_cutoff(env.settings.heartbeat_timeout_s)
        job = crud.claim_job(session, job_id, lease, worker, stale)
        if job is None:
            current = session.get(Job, job_id)
            if current is not None and current.cancel_requested and not current.state.is_terminal:
                crud.cancel_unclaimed(session, job_id)
            logger.info("job %s: not claimed (%s)", job_id, current.state if current else "no such job")
        return job


def job_vocabulary(session: Session, job: Job) -> str | Vocabulary | None:
    """What the pipeline gets as the job's label set: a built-in name (the pipeline resolves names only), the
    job's inline classes and embeddings as a :class:`Vocabulary`, or None for the bundle's own.

    Raises:
        InputError: the stored value is not a built-in name (a row from before inline vocabularies that named a
            file: refused without repeating it), or the inline classes do not parse.
    """
    from panogs_core.language.label_sets import builtin_vocabulary, inline_vocabulary, is_builtin_name

    if job.vocabulary_classes is not None:
        embeddings = session.scalar(select(Job.vocabulary_embeddings).where(Job.id == job.id))
        return inline_vocabulary(job.vocabulary_classes, embeddings, source=f"job {job.id} vocabulary")
    if job.vocabulary is not None and not is_builtin_name(job.vocabulary):
        builtin_vocabulary(job.vocabulary)  # raises, with a message that names no path
    return job.vocabulary


def _run(job: Job, tracker: Tracker, env: JobEnv) -> JobState | None:
    try:
        with session_scope(env.session_factory) as session:
            scene = crud.get_scene(session, job.scene_id)
            vocabulary = job_vocabulary(session, job)
    except PanoGSError as exc:
        return _finish(
            job.id, tracker.lease, env, JobState.FAILED, error_type=type(exc).__name__, error_message=str(exc)
        )
    if scene is None:
        return _finish(
            job.id,
            tracker.lease,
            env,
            JobState.FAILED,
            error_type="SceneMissing",
            error_message=f"scene {job.scene_id} no longer exists",
        )
    try:
        with _workspace(env, job, scene.bundle_path) as (bundle_dir, out_dir, push):
            tracker.push = push
            try:
                return _run_in(job, tracker, env, vocabulary, bundle_dir, out_dir)
            finally:
                if tracker.shared is not None:
                    tracker.shared.release_all()  # a stage that never stored its key: the next taker computes it
    except StorageUnavailable as exc:
        # The object storage is away: hand the job back and retry the task with backoff (Celery's); the next
        # attempt resumes from the checkpoints it stored.
        with_db_retry(lambda: _release(job.id, tracker), deadline_s=env.settings.transient_retry_s, what="hand back")
        logger.warning("job %s: object storage unavailable, handed back: %s", job.id, exc)
        raise TransientError(f"object storage unavailable: {exc}") from exc
    except StorageError as exc:  # refused keys, a missing bucket: waiting cannot help
        return _fail(job.id, tracker, "StorageError", without_host_paths(str(exc), env)[:10_000])


@contextmanager
def _workspace(env: JobEnv, job: Job, bundle_path: str) -> Iterator[tuple[Path, Path, TreePush | None]]:
    """The job's bundle and output folder: in place with the local backend; else a scratch folder of this task
    with the scene's bundle and what earlier attempts stored of the job (its checkpoints) fetched into it, and a
    :class:`TreePush` that stores the output folder back. The scratch folder is removed after the task."""
    storage = env.storage
    if storage.is_local:
        out_dir = storage.job_dir(job.id)
        out_dir.mkdir(parents=True, exist_ok=True)
        yield storage.path(bundle_path), out_dir, None
        return
    with ExitStack() as stack:
        scratch = stack.enter_context(storage.scratch(f"job-{job.id}"))
        out_dir = scratch / "out"
        out_dir.mkdir()
        bundle_dir = bundle_in(stack, env, job, bundle_path, scratch)
        storage.fetch_tree(storage.job_prefix(job.id), out_dir)
        push = TreePush(storage, out_dir, storage.job_prefix(job.id))
        push.mark_present()
        yield bundle_dir, out_dir, push


def bundle_in(stack: ExitStack, env: JobEnv, job: Job, bundle_path: str, scratch: Path) -> Path:
    """The scene's bundle on this host for a task of ``job`` (object storage): from the worker's bundle cache, held
    until ``stack`` closes (then the cache is swept), or fetched into ``scratch`` when the cache is off."""
    storage = env.storage
    bundles = _bundle_cache(env)
    if bundles is None:
        bundle_dir = scratch / "bundle"
        storage.fetch_tree(bundle_path.rstrip("/") + "/", bundle_dir)
        return bundle_dir
    stack.callback(_sweep_quietly, bundles)  # after the task: within the bound, no deleted scene's bundle
    return stack.enter_context(bundles.use(job.scene_id, bundle_path))


def _bundle_cache(env: JobEnv) -> BundleCache | None:
    """This worker's cache of bundles (and of their scenes' checkpoints), or None when it keeps none."""
    if env.storage.is_local or env.settings.bundle_cache_bytes <= 0:
        return None
    return BundleCache(
        env.storage,
        env.storage.root / "work" / "bundles",
        env.settings.bundle_cache_bytes,
        lambda ids: _scenes_alive(env, ids),
    )


def _run_in(
    job: Job, tracker: Tracker, env: JobEnv, vocabulary: str | Vocabulary | None, bundle_dir: Path, out_dir: Path
) -> JobState | None:
    bundles = _bundle_cache(env)
    shared = SceneCheckpoints(
        env.storage,
        job.scene_id,
        owner=f"job {job.id} lease {tracker.lease}",
        lease_s=env.settings.heartbeat_timeout_s,
        on_wait=lambda stage: tracker.on_progress(stage, 0, 1),
        on_stored=lambda size: _count_scene_bytes(env, job.scene_id, size),
        local_copies=None if bundles is None else bundles.stages_folder(job.scene_id),
    )
    tracker.shared = shared
    if tracker.push is not None:
        tracker.push.skip = shared.kept  # a checkpoint the scene's store keeps is not stored again with the job
    try:
        config = env.make_config(job.config or {})
        if job.tiling is not None and _fanned_out(job, tracker, env, bundle_dir, out_dir, config):
            return JobState.RUNNING  # its tiles' tasks run it now, and its merge ends it
        with tracker.beating():
            result = env.pipeline(
                bundle_dir,
                out_dir,
                config,
                vocabulary=vocabulary,
                on_progress=stopping_on_storage_errors(tracker.on_progress),
                resume=True,
                on_results=stopping_on_storage_errors(lambda _result: _record_results(job.id, tracker, out_dir)),
                shared=_CheckpointsThroughStops(shared),
            )
        tracker.push_outputs()
    except StorageError:
        raise  # handled by _run, around the workspace
    except StorageStop as exc:
        raise exc.error from exc  # likewise
    except LeaseLost:
        logger.warning("job %s: stopped, another worker holds it", job.id)
        return None
    except Interrupted:
        tracker.push_outputs(best_effort=True)  # what it did so far resumes on another host
        with_db_retry(
            lambda: _release(job.id, tracker),
            deadline_s=env.settings.transient_retry_s,
            what="hand the job back",
        )
        logger.info("job %s: handed back to the queue (worker shutting down)", job.id)
        return JobState.QUEUED
    except CancelRequested as exc:
        tracker.close_stage(time.monotonic())
        fit = {"fit_state": FitState.CANCELED, "fit_error": str(exc)} if tracker.results_ready else {}
        return _finish(job.id, tracker.lease, env, JobState.CANCELED, **tracker.stage_values(), **fit)
    except (TimeLimitExceeded, PanoGSError) as exc:
        # Domain errors: the input or the configuration is at fault, retrying cannot help.
        logger.info("job %s: failed: %s: %s", job.id, type(exc).__name__, exc)
        message = without_host_paths(str(exc), env, bundle_dir, out_dir)[:10_000]
        fit = {"fit_state": FitState.FAILED, "fit_error": f"{type(exc).__name__}: {message}"}
        return _fail(job.id, tracker, type(exc).__name__, message, **(fit if tracker.results_ready else {}))
    tracker.close_stage(time.monotonic())
    timings = merge_timings(tracker.timings, getattr(result, "timings", None))
    fit_state, fit_error = fit_outcome(result)
    if fit_error is not None:
        fit_error = without_host_paths(fit_error, env, bundle_dir, out_dir)[:10_000]
        logger.info("job %s: results ready, the Gaussian fit %s: %s", job.id, fit_state, fit_error)
    exclude = frozenset() if fit_state.scene_ready else FITTED_FILES  # an unfitted scene is not served
    artifacts = collect_artifacts(job.id, out_dir, env.storage, exclude=exclude)
    return _finish(
        job.id,
        tracker.lease,
        env,
        JobState.SUCCEEDED,
        artifacts=artifacts,
        progress=1.0,
        stage=None,
        **{**tracker.stage_values(), "stage_timings": timings},
        results_at=func.coalesce(Job.results_at, utcnow()),  # a pipeline without on_results: now
        fit_state=fit_state,
        fit_progress=1.0 if fit_state.scene_ready else tracker.fit_progress,
        fit_error=fit_error,
    )


def _fanned_out(job: Job, tracker: Tracker, env: JobEnv, bundle_dir: Path, out_dir: Path, config: Any) -> bool:
    """Plan a job that asks for tiles; True when it was tiled and its tiles are published (worker/tiles.py)."""
    from worker import tiles

    if tiles.tiles_asked(job) == tiles.TILES_OFF:
        return False
    return tiles.plan_and_fan_out(job, tracker, env, bundle_dir, out_dir, config)


def _fail(job_id: uuid.UUID, tracker: Tracker, error_type: str, message: str, **values: Any) -> JobState | None:
    """Record the job failed with ``error_type: message`` and the stage times so far."""
    tracker.close_stage(time.monotonic())
    return _finish(
        job_id,
        tracker.lease,
        tracker.env,
        JobState.FAILED,
        **tracker.stage_values(),
        error_type=error_type,
        error_message=message,
        **values,
    )


def _sweep_quietly(bundles: BundleCache) -> None:
    """The bundle cache's sweep, whose failure (the database away) must not replace how the job ended."""
    try:
        bundles.sweep()
    except (DBAPIError, OSError):
        logger.warning("the bundle cache was not swept; the next job's sweep does it", exc_info=True)


def _scenes_alive(env: JobEnv, scene_ids: Iterable[uuid.UUID]) -> set[uuid.UUID]:
    """Which of ``scene_ids`` still exist (a deleted scene's bundle leaves the worker's disk too)."""
    wanted = list(scene_ids)
    if not wanted:
        return set()
    with session_scope(env.session_factory) as session:
        return set(session.scalars(select(Scene.id).where(Scene.id.in_(wanted))))


def _count_scene_bytes(env: JobEnv, scene_id: uuid.UUID, size: int) -> None:
    """A checkpoint stored under the scene counts in its size (the tenant's storage quota)."""

    def write() -> None:
        with session_scope(env.session_factory) as session:
            session.execute(update(Scene).where(Scene.id == scene_id).values(size_bytes=Scene.size_bytes + size))
            session.commit()

    with_db_retry(write, deadline_s=env.settings.transient_retry_s, what="count a shared checkpoint")


def fit_outcome(result: Any) -> tuple[FitState, str | None]:
    """How the pipeline's appearance fit ended (``PipelineResult.appearance``: ``state``, ``error``).

    A pipeline that says nothing of a fit (one without it) counts as fitted: its outputs are final when it returns.
    """
    appearance = getattr(result, "appearance", None)
    if not isinstance(appearance, Mapping):
        return FitState.SUCCEEDED, None
    try:
        state = FitState(str(appearance.get("state", FitState.SUCCEEDED.value)))
    except ValueError:
        state = FitState.SUCCEEDED
    if state in (FitState.RUNNING, FitState.CANCELED):  # returned, so it did not stop; a running one never ended
        state = FitState.FAILED
    error = appearance.get("error")
    return state, (str(error) if error is not None else None)


def _record_results(job_id: uuid.UUID, tracker: Tracker, out_dir: Path) -> None:
    """The pipeline wrote its results (before the fit): record their artifacts and ``results_at``; the
    instances, queries and viewer scene answer from here on. Called in the pipeline's thread.

    Raises:
        LeaseLost: another task holds the job now.
    """
    env = tracker.env
    tracker.push_outputs()
    artifacts = collect_artifacts(job_id, out_dir, env.storage, exclude=FITTED_FILES)

    def write() -> bool:
        with session_scope(env.session_factory) as session:
            return crud.record_results(session, job_id, tracker.lease, artifacts, **tracker.stage_values())

    if not with_db_retry(write, deadline_s=env.settings.transient_retry_s, what="record the job's results"):
        tracker.lost = True
        raise LeaseLost(f"job {job_id}: another worker holds it now, or it was finished")
    tracker.results_ready = True
    logger.info("job %s: results ready (%d artifacts); the Gaussian fit goes on", job_id, len(artifacts))


def without_host_paths(message: str, env: JobEnv, *folders: Path) -> str:
    """``message`` as the job's owner may read it: a path inside one of ``folders`` (the job's bundle, its output
    folder) is named relative to that folder, anything else under the storage or data folder relative to it,
    so that no error of a job tells where the host keeps its files (docs/service.md)."""
    roots = [*folders, env.storage.root, env.settings.data_dir.resolve()]
    for root in roots:
        for form in dict.fromkeys((str(root), str(root.resolve()))):  # as given and resolved (symlinked mounts)
            message = message.replace(form + "/", "").replace(form, ".")
    return message


def _release(job_id: uuid.UUID, tracker: Tracker) -> None:
    tracker.close_stage(time.monotonic())
    with session_scope(tracker.env.session_factory) as session:
        crud.release_job(session, job_id, tracker.lease, **tracker.stage_values())


def merge_timings(measured: dict[str, float], reported: Any) -> dict[str, float]:
    """The pipeline's own stage times over the runner's, except for stages it reused from a checkpoint.

    ``reported`` is ``PipelineResult.timings``: records with ``name``, ``wall_s`` and ``cached``, or a
    mapping of stage to seconds. A cached stage keeps the time of the attempt that computed it.
    """
    out = dict(measured)
    items = (
        reported.items() if isinstance(reported, Mapping) else [(getattr(r, "name", None), r) for r in (reported or [])]
    )
    for stage, value in items:
        seconds = getattr(value, "wall_s", value)
        if stage is None or not isinstance(seconds, int | float):
            continue
        if getattr(value, "cached", False) and stage in out:
            continue
        out[str(stage)] = round(float(seconds), 3)
    return out


def collect_artifacts(
    job_id: uuid.UUID, out_dir: Path, storage: Storage, *, exclude: frozenset[str] = frozenset()
) -> list[Artifact]:
    """Artifact rows for the pipeline outputs present in ``out_dir``, but those named in ``exclude``."""
    rows = []
    for name, media_type in ARTIFACTS.items():
        path = out_dir / name
        if path.is_file() and name not in exclude:
            rows.append(
                Artifact(
                    job_id=job_id,
                    name=name,
                    path=storage.job_prefix(job_id) + name,
                    size_bytes=path.stat().st_size,
                    sha256=sha256_file(path).hexdigest(),
                    media_type=media_type,
                )
            )
    return rows


def _finish(job_id: uuid.UUID, lease: str, env: JobEnv, state: JobState, **values: Any) -> JobState | None:
    def write() -> bool:
        with session_scope(env.session_factory) as session:
            return crud.finish_job(session, job_id, lease, state, **values)

    if not with_db_retry(write, deadline_s=env.settings.transient_retry_s, what=f"record the job as {state}"):
        logger.warning("job %s: could not record %s, the job moved on without this worker", job_id, state)
        return None
    logger.info("job %s: %s", job_id, state)
    return state


def record_crash(job_id: uuid.UUID, lease: str, exc: BaseException, env: JobEnv) -> None:
    """Fail a job after an unexpected error at the task boundary (best effort; the error is re-raised
    there)."""
    message = without_host_paths(f"{type(exc).__name__}: {exc}", env)[:10_000]
    try:
        _finish(job_id, lease, env, JobState.FAILED, error_type="InternalError", error_message=message)
    except Exception:  # the original error matters more than this one
        logger.exception("job %s: could not record the crash", job_id)
