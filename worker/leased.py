"""What a leased task is, for the job runner (``worker/runner.py``) and the tile runner (``worker/tiles.py``) alike.

A task runs one row (a job, or a tiled job's tile or merge) under the row's ``lease``, the id of the Celery task
that claimed it; every write is guarded by it (``service.db.leases``). This module holds what every such task
shares, so that each runner keeps only what is its own:

- **Errors**: the stops a task raises through the pipeline as :class:`panogs_core.errors.Cancelled` (a cancel, a
  lost lease, the time limit, a worker shutdown, a storage failure), and :class:`TransientError` for Celery's retry.
- **Environment**: :class:`JobEnv`, built once per worker process.
- **Database retries**: :func:`with_db_retry` waits out an outage, nothing else.
- **Progress and heartbeat**: :class:`Tracker` writes progress at most every ``progress_interval_s`` to the row
  it runs (:class:`LeasedRow`: the job's or the tile's), checks for a cancel, the time limit and a shutdown at
  the same moments, and beats from a thread while the body runs; the reaper re-queues a row whose heartbeat stops.
- **Workspace**: the folders a task works in (:func:`workspace_plan`, ``service.storage.workspace``), with the
  worker's bundle cache when it keeps one.
- **Endings**: :func:`run_leased` turns how a task's body stopped into the row's outcome, the same way for both.
"""

from __future__ import annotations

import logging
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

from sqlalchemy import select
from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from panogs_core.errors import Cancelled, PanoGSError
from panogs_core.types import Vocabulary
from service.db import crud
from service.db.faults import DatabaseFault, classify
from service.db.models import Scene
from service.db.session import session_scope
from service.settings import Settings
from service.storage import Storage
from service.storage.objects import StorageError, StorageUnavailable
from service.storage.workspace import Pusher, WorkPlan, Workspace
from worker.bundle_cache import BundleCache
from worker.shared_checkpoints import SceneCheckpoints

logger = logging.getLogger(__name__)
T = TypeVar("T")
R = TypeVar("R")
R_co = TypeVar("R_co", covariant=True)

# The stage that runs after the results are written (its progress is the job's fit progress).
FIT_STAGE = "appearance"


# Errors ------------------------------------------------------------------------------------------------------------


class TransientError(Exception):
    """The database or broker was away for longer than the runner waits; the task is retried later."""


class CancelRequested(Cancelled):
    """The job's owner asked to cancel it."""


class LeaseLost(Cancelled):
    """Another task now holds the row (this worker was presumed dead); stop without writing anything."""

    save_partial_work = False


class TimeLimitExceeded(Cancelled):
    """The job ran past ``job_time_limit_s``."""


class Interrupted(Cancelled):
    """The worker is shutting down; the row goes back to the queue and resumes later."""


class StorageStop(Cancelled):
    """The object storage failed a call the pipeline made (a stage's progress, which stores the stage before it, or
    a shared checkpoint's fetch or store). Raised as a cancel so that it passes through the appearance fit, which
    would otherwise record any error as the fit's own failure and let the results stand: the worker then treats
    ``error`` as it treats a storage error anywhere else (an outage retries the task with backoff, a refusal fails
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


# Environment and database retries ----------------------------------------------------------------------------------


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


@dataclass(frozen=True)
class JobEnv:
    """Everything a task needs besides its row's id; built once per worker process."""

    settings: Settings
    session_factory: sessionmaker[Session]
    storage: Storage
    pipeline: PipelineFn
    make_config: Callable[[dict[str, Any]], Any]
    stages: tuple[str, ...] = ()
    shutdown: threading.Event = field(default_factory=threading.Event)  # set when the worker is stopping
    # Publishes a tiled job's tile and merge tasks; None: a Celery app for ``settings`` (tests pass a recorder).
    sender: Any = None


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


def claim_retried(
    env: JobEnv, what: str, claim: Callable[[], T | None], attempts: Callable[[T], tuple[int, str]]
) -> Claim[T]:
    """The row ``claim`` takes for this task (database outages waited out), and why it is not run again when its
    workers kept dying: claimed more than ``max_attempts`` times (``attempts``: the count and the row's name)."""
    row = with_db_retry(claim, deadline_s=env.settings.transient_retry_s, what=f"claim {what}")
    if row is None:
        return Claim(None, None)
    count, name = attempts(row)
    if count <= env.settings.max_attempts:
        return Claim(row, None)
    return Claim(row, f"{name} was started {count - 1} times and its worker was lost each time")


@dataclass(frozen=True)
class Claim(Generic[T]):
    """A claimed row (None: not ours to run) and, when it has been lost too often, why it ends now."""

    row: T | None
    worn_out: str | None


def write_retried(env: JobEnv, what: str, write: Callable[[Session], T]) -> T:
    """``write`` in one session, its database outages waited out (:func:`with_db_retry`)."""

    def attempt() -> T:
        with session_scope(env.session_factory) as session:
            return write(session)

    return with_db_retry(attempt, deadline_s=env.settings.transient_retry_s, what=what)


# Progress and heartbeat ------------------------------------------------------------------------------------------


class LeasedRow(Protocol):
    """The row a task runs, as its tracker writes it."""

    @property
    def job_id(self) -> uuid.UUID:
        """The job it belongs to (or is)."""
        ...

    @property
    def label(self) -> str:
        """Names it in logs and messages: ``job <id>``, ``tile <id>``."""
        ...

    @property
    def ended(self) -> str:
        """How a lost lease is worded: ``it was finished``, ``its job ended``."""
        ...

    def fraction(self, stages: tuple[str, ...], stage: str, done: int, total: int) -> float:
        """The row's progress at ``done`` of ``total`` in ``stage``."""
        ...

    def write(self, session: Session, lease: str, values: dict[str, Any]) -> bool:
        """Write ``values`` and the heartbeat under ``lease``; False once the lease is lost."""
        ...


def stage_fraction(stages: tuple[str, ...], stage: str, done: int, total: int) -> float:
    """Overall progress at ``done`` of ``total`` in ``stage`` of the pipeline's ``stages`` (0 for another stage)."""
    if stage not in stages:
        return 0.0
    return (stages.index(stage) + within(done, total)) / len(stages)


def within(done: int, total: int) -> float:
    """``done / total`` clamped to [0, 1] (0 without a total)."""
    return min(max(done / total, 0.0), 1.0) if total > 0 else 0.0


@dataclass
class Tracker:
    """Progress state of one task, shared by the progress callback and the heartbeat thread."""

    row: LeasedRow
    lease: str
    env: JobEnv
    timings: dict[str, float] = field(default_factory=dict)
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
    push: Pusher | None = None  # stores the output folder back (object storage), after each stage and at the end
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
            logger.warning("%s: could not store its partial work", self.row.label, exc_info=True)

    def stage_values(self) -> dict[str, Any]:
        """The per-stage columns as they stand: the stage times and the stages taken from the scene's checkpoints
        (by an earlier attempt or by this one)."""
        # A stage an earlier attempt computed comes back from the scene's store on a retry: not another job's.
        reused = [s for s in (self.shared.reused if self.shared else []) if s not in self.computed_before]
        return {"stage_timings": dict(self.timings), "cached_stages": list(dict.fromkeys([*self.cached, *reused]))}

    def raise_stops(self) -> None:
        """Raise what ends the job now without a write (a lost lease, the worker's shutdown); the job's stage stays."""
        if self.lost:
            raise LeaseLost(f"{self.row.label}: another worker holds it now")
        if self.env.shutdown.is_set():
            raise Interrupted("the worker is shutting down")

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
        self.raise_stops()
        if not changed and now - self.last_write < self.env.settings.progress_interval_s:
            return
        self.last_write = now
        if now - self.started > self.env.settings.job_time_limit_s:
            raise TimeLimitExceeded(f"the job ran longer than {self.env.settings.job_time_limit_s:g} s")
        values: dict[str, Any] = {}
        if self.results_ready and stage == FIT_STAGE:
            self.fit_progress = within(done, total)
            values["fit_progress"] = self.fit_progress
        progress = self.row.fraction(self.env.stages, stage, done, total)
        self.write(stage=stage, progress=progress, **self.stage_values(), **values)

    def write(self, **values: Any) -> None:
        """Progress and heartbeat write; a database that is away is skipped, a lost lease or a cancel stops."""
        try:
            with session_scope(self.env.session_factory) as session:
                held = self.row.write(session, self.lease, values)
                cancel = held and crud.cancel_requested(session, self.row.job_id)
        except DBAPIError as exc:
            logger.warning("%s: progress not recorded, database unavailable (%r)", self.row.label, exc.orig)
            return
        if not held:
            self.lost = True
            raise LeaseLost(f"{self.row.label}: another worker holds it now, or {self.row.ended}")
        if cancel:
            raise CancelRequested("canceled at the owner's request")

    @contextmanager
    def beating(self) -> Iterator[None]:
        """Heartbeats from a thread while the body runs; stopped before the outcome is written. May be entered again
        (a job that asked for tiles beats while it plans, then, left whole, while it runs)."""
        self.stop.clear()
        beat = threading.Thread(target=self.heartbeat_loop, name=f"heartbeat-{self.row.label}", daemon=True)
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
                logger.warning("%s: lease lost; the pipeline stops at its next progress step", self.row.label)
                return


# Workspace -------------------------------------------------------------------------------------------------------


def workspace_plan(env: JobEnv, name: str, scene_id: uuid.UUID, bundle_path: str, **paths: Any) -> WorkPlan:
    """What a task of a job on scene ``scene_id`` reads and writes (``fetch``, ``push``: parts of the job's folder),
    its bundle from this worker's bundle cache when it keeps one."""
    bundles = bundle_cache(env)
    cached = None if bundles is None else (lambda: _cached_bundle(bundles, scene_id, bundle_path))
    return WorkPlan(name=name, bundle_path=bundle_path, cached_bundle=cached, **paths)


@contextmanager
def _cached_bundle(bundles: BundleCache, scene_id: uuid.UUID, bundle_path: str) -> Iterator[Path]:
    """The scene's bundle from the cache, held while the task runs; then the cache is swept (within its bound, no
    deleted scene's bundle)."""
    try:
        with bundles.use(scene_id, bundle_path) as here:
            yield here
    finally:
        _sweep_quietly(bundles)


def bundle_cache(env: JobEnv) -> BundleCache | None:
    """This worker's cache of bundles (and of their scenes' checkpoints), or None when it keeps none (the objects
    are this host's files, or ``bundle_cache_bytes`` is 0)."""
    folder = env.storage.work_folder("bundles")
    if folder is None or env.settings.bundle_cache_bytes <= 0:
        return None
    return BundleCache(env.storage, folder, env.settings.bundle_cache_bytes, lambda ids: _scenes_alive(env, ids))


def _sweep_quietly(bundles: BundleCache) -> None:
    """The bundle cache's sweep, whose failure (the database away) must not replace how the task ended."""
    try:
        bundles.sweep()
    except (DBAPIError, OSError):
        logger.warning("the bundle cache was not swept; the next task's sweep does it", exc_info=True)


def _scenes_alive(env: JobEnv, scene_ids: Iterable[uuid.UUID]) -> set[uuid.UUID]:
    """Which of ``scene_ids`` still exist (a deleted scene's bundle leaves the worker's disk too)."""
    wanted = list(scene_ids)
    if not wanted:
        return set()
    with session_scope(env.session_factory) as session:
        return set(session.scalars(select(Scene.id).where(Scene.id.in_(wanted))))


# Endings ---------------------------------------------------------------------------------------------------------


class Ending(Protocol[R_co]):
    """How a task's row ends otherwise than by its own success; each runner writes its rows its way."""

    def hand_back(self) -> None:
        """Put the row back in the queue (this claim does not count as an attempt)."""
        ...

    def handed_back(self) -> R_co:
        """The state a handed-back task returns."""
        ...

    def canceled(self, exc: CancelRequested) -> R_co | None: ...

    def failed(self, error_type: str, message: str, *, in_run: bool) -> R_co | None:
        """Record the row failed (``in_run``: the body raised it, not the storage around it)."""
        ...


def in_workspace(
    tracker: Tracker, ending: Ending[R], plan: WorkPlan, body: Callable[[Workspace], R | None]
) -> R | None:
    """``body`` in the task's workspace; an object storage that is away hands the row back and retries the task
    (Celery's backoff; the next attempt resumes from what was stored), one that refuses fails it.

    Raises:
        TransientError: the object storage was unavailable.
    """
    env = tracker.env
    sweep_scratch_once(env)
    try:
        with env.storage.workspace(tracker.row.job_id, plan) as work:
            tracker.push = work.push
            return body(work)
    except StorageUnavailable as exc:
        write_hand_back(tracker, ending)
        logger.warning("%s: object storage unavailable, handed back: %s", tracker.row.label, exc)
        raise TransientError(f"object storage unavailable: {exc}") from exc
    except StorageError as exc:  # refused keys, a missing bucket: waiting cannot help
        return ending.failed("StorageError", without_host_paths(str(exc), env)[:10_000], in_run=False)


_SWEPT: set[int] = set()  # the processes (by pid: a forked child is another) that swept the scratch folders
_SWEEP_LOCK = threading.Lock()


def sweep_scratch_once(env: JobEnv) -> None:
    """At this process's first task: remove the scratch folders a killed worker left on this data folder (their
    owner process is gone; a live sibling's stay)."""
    with _SWEEP_LOCK:
        if os.getpid() in _SWEPT:
            return
        _SWEPT.add(os.getpid())
    try:
        removed = env.storage.sweep_scratch()
    except OSError:
        logger.warning("the stale scratch folders were not swept", exc_info=True)
        return
    if removed:
        logger.info("removed %d scratch folder(s) of a worker that is gone: %s", len(removed), ", ".join(removed))


def write_hand_back(tracker: Tracker, ending: Ending[Any]) -> None:
    """Hand the row back, the database's outages waited out."""
    deadline = tracker.env.settings.transient_retry_s
    with_db_retry(ending.hand_back, deadline_s=deadline, what=f"hand {tracker.row.label} back")


def run_leased(tracker: Tracker, ending: Ending[R], work: Workspace, body: Callable[[], R | None]) -> R | None:
    """``body``'s result, or the row's outcome from how it stopped: a lost lease writes nothing, a shutdown hands
    the row back with its partial work stored, a cancel and a domain error (the input or the settings at fault:
    retrying cannot help) end it. Storage errors go to :func:`in_workspace`, around the workspace."""
    try:
        return body()
    except StorageError:
        raise
    except StorageStop as exc:
        raise exc.error from exc
    except LeaseLost:
        logger.warning("%s: stopped, another worker holds it or its job ended", tracker.row.label)
        return None
    except Interrupted:
        tracker.push_outputs(best_effort=True)  # what it did so far resumes on another host
        write_hand_back(tracker, ending)
        logger.info("%s: handed back to the queue (worker shutting down)", tracker.row.label)
        return ending.handed_back()
    except CancelRequested as exc:
        return ending.canceled(exc)
    except (TimeLimitExceeded, PanoGSError) as exc:
        logger.info("%s: failed: %s: %s", tracker.row.label, type(exc).__name__, exc)
        message = without_host_paths(str(exc), tracker.env, work.bundle, work.out)[:10_000]
        return ending.failed(type(exc).__name__, message, in_run=True)


def without_host_paths(message: str, env: JobEnv, *folders: Path) -> str:
    """``message`` as the job's owner may read it: a path inside one of ``folders`` (the job's bundle, its output
    folder) is named relative to that folder, anything else under the storage or data folder relative to it,
    so that no error of a job tells where the host keeps its files (docs/service.md)."""
    roots = [*folders, env.storage.root, env.settings.data_dir.resolve()]
    for root in roots:
        for form in dict.fromkeys((str(root), str(root.resolve()))):  # as given and resolved (symlinked mounts)
            message = message.replace(form + "/", "").replace(form, ".")
    return message
