"""The API's background sweep: finds lost jobs, publishes jobs the broker missed, deletes abandoned uploads.

Runs in a thread of every API process; every change is a guarded UPDATE, so several API processes sweeping at
once do each thing once.

- A ``running`` job whose worker sent no heartbeat for ``heartbeat_timeout_s`` (killed, machine gone) goes
  back to ``queued`` and is published again, to be resumed by another worker from its last finished stage,
  or is ``failed`` with ``WorkerLost`` once it has been started ``max_attempts`` times.
- A ``queued`` job whose message never reached the broker (the broker was away) is published.
- The tiles and merge of a tiled job follow the same rules on their own rows: a lost one is re-queued and
  published again (or fails the job with ``WorkerLost`` after ``max_attempts``), an unpublished one is published.
- An upload untouched for ``upload_ttl_s`` is deleted with its bytes.
- Finished jobs past ``retention_days`` are deleted with their results; job and scene folders without rows (an
  interrupted delete) are removed.
"""

from __future__ import annotations

import logging
import socket
import threading
import uuid
from datetime import datetime

from sqlalchemy.exc import DBAPIError
from sqlalchemy.orm import Session, sessionmaker

from service.db import crud
from service.db.leases import JOBS, TILES
from service.db.models import JobState, TileKind
from service.db.session import session_scope
from service.lifecycle import sweep_orphans, sweep_retention
from service.queue import Sender, dispatch, dispatch_tile
from service.settings import Settings
from service.storage import Storage, upload_folder

logger = logging.getLogger(__name__)

DISPATCH_GRACE_S = 2.0  # a new job's own request publishes it; the reaper steps in after this


HOUSEKEEPING_EVERY = 12  # retention and orphan folders: every 12th pass (a minute by default), not every 5 s


def sweep(
    settings: Settings, factory: sessionmaker[Session], sender: Sender, storage: Storage, *, housekeeping: bool = True
) -> dict[str, int]:
    """One pass; returns how many jobs were re-queued, failed and published, uploads deleted, and (with
    ``housekeeping``) jobs past their retention and orphan folders removed."""
    counts = {"requeued": 0, "failed": 0, "published": 0, "uploads_deleted": 0, "expired": 0, "orphans": 0}
    silent_since = crud.stale_cutoff(settings.heartbeat_timeout_s)
    with session_scope(factory) as session:
        for job in JOBS.silent(session, silent_since):
            if job.attempts >= settings.max_attempts:
                message = (
                    f"the worker running this job stopped responding (no heartbeat for "
                    f"{settings.heartbeat_timeout_s:g} s), {job.attempts} time(s); giving up"
                )
                counts["failed"] += crud.fail_lost(session, job, silent_since, "WorkerLost", message)
            elif JOBS.requeue_silent(session, job.id, silent_since):
                logger.warning("job %s: worker %s lost (attempt %d); re-queued", job.id, job.worker, job.attempts)
                counts["requeued"] += 1
        requeued_tiles = _reap_tiles(session, settings, silent_since, counts)
        pending = [(job.id, job.queue) for job in crud.undispatched_jobs(session, crud.stale_cutoff(DISPATCH_GRACE_S))]
        pending_tiles = crud.undispatched_tiles(session, crud.stale_cutoff(DISPATCH_GRACE_S))
        pending_tiles += [t for t in requeued_tiles if t not in pending_tiles]
        stale = [(u.id, u.path) for u in crud.stale_uploads(session, crud.stale_cutoff(settings.upload_ttl_s))]
        for upload_id, rel in stale:
            storage.delete_prefix(upload_folder(rel))
            crud.delete_upload(session, upload_id)
            counts["uploads_deleted"] += 1
    if housekeeping:
        with session_scope(factory) as session:
            counts["expired"] = sweep_retention(session, settings, storage)
            counts["orphans"] = sweep_orphans(session, storage)
    for job_id, queue in pending:
        counts["published"] += dispatch(factory, sender, job_id, queue)
    for tile_id, kind, queue in pending_tiles:
        counts["published"] += dispatch_tile(factory, sender, tile_id, kind, queue)
    return counts


def _reap_tiles(
    session: Session, settings: Settings, silent_since: datetime, counts: dict[str, int]
) -> list[tuple[uuid.UUID, TileKind, str]]:
    """Lost tiles and merges: re-queued, or their job failed for good. Returns the re-queued ones (id, kind, queue),
    which this pass publishes at once (nothing else will; the outbox's grace is for the fan-out's own publish)."""
    requeued = []
    for tile in TILES.silent(session, silent_since):
        if tile.attempts >= settings.max_attempts:
            message = (
                f"the worker running {tile.kind} {tile.name} stopped responding (no heartbeat for "
                f"{settings.heartbeat_timeout_s:g} s), {tile.attempts} time(s); giving up"
            )
            failed = crud.end_tiled_job(
                session, tile.job_id, JobState.FAILED, tile_id=tile.id, error_type="WorkerLost", message=message
            )
            counts["failed"] += failed
        elif TILES.requeue_silent(session, tile.id, silent_since):
            logger.warning("job %s: %s %s lost (worker %s, attempt %d); re-queued", tile.job_id, tile.kind,
                           tile.name, tile.worker, tile.attempts)  # fmt: skip
            counts["requeued"] += 1
            requeued.append((tile.id, tile.kind, crud.job_queue(session, tile.job_id)))
    return requeued


def embedded_worker_name(pid: int) -> str:
    """The prefix of the ``worker`` column of jobs run by the embedded worker process ``pid`` (``panogs worker``
    names itself ``panogs-<pid>@<host>``; its solo pool runs jobs in that same process)."""
    return f"panogs-{pid}@{socket.gethostname()}/"


def requeue_dead_worker(factory: sessionmaker[Session], pid: int) -> int:
    """Put the running jobs and tiles of a worker process that is known dead back in the queue at once (the
    supervisor saw it exit), instead of waiting out the heartbeat timeout; the sweep publishes them.
    Returns how many."""
    with session_scope(factory) as session:
        count = JOBS.requeue_worker(session, embedded_worker_name(pid))
        count += TILES.requeue_worker(session, embedded_worker_name(pid))
    if count:
        logger.warning("worker %d died; re-queued its %d running job(s) at once", pid, count)
    return count


class Reaper:
    """Runs :func:`sweep` every ``reaper_interval_s`` in a daemon thread until stopped."""

    def __init__(self, settings: Settings, factory: sessionmaker[Session], sender: Sender, storage: Storage) -> None:
        self._args = (settings, factory, sender, storage)
        self._interval = settings.reaper_interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="panogs-reaper", daemon=True)

    def start(self) -> None:
        """Start sweeping."""
        self._thread.start()

    def stop(self) -> None:
        """Stop after the current pass."""
        self._stop.set()
        self._thread.join(timeout=10)

    def _loop(self) -> None:
        passes = 0
        while not self._stop.wait(self._interval):
            passes += 1
            try:
                counts = sweep(*self._args, housekeeping=passes % HOUSEKEEPING_EVERY == 1)
            except DBAPIError as exc:
                logger.warning("reaper: database unavailable (%r)", exc.orig)
                continue
            except Exception:  # the sweep must keep running; the next pass may succeed
                logger.exception("reaper: sweep failed")
                continue
            if any(counts.values()):
                logger.info("reaper: %s", counts)
