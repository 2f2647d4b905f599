"""The data lifecycle: deleting scenes and jobs with their files, per-tenant quotas, retention, orphan sweeping.

- **Delete** removes the rows first, then the files: a failure between the two leaves only files without rows,
  which :func:`sweep_orphans` removes later; a retry of a DELETE whose rows are gone answers 204 again (safe to
  retry). A running job is asked to cancel first; its worker finds the row gone at its next progress step (a lost
  lease) and stops, and any file it wrote after the delete is an orphan for the sweep.
- **Quotas** per tenant: stored bytes (unconsumed uploads + scenes + job results) and concurrent job slots (queued
  or running jobs; a tiled job holds one per tile, up to the whole limit), as ``service.db.crud.keys`` counts them.
  A request that would pass one is refused with 413 / 429 and a message naming the limit and its setting. The
  check and the insert it guards run in one transaction under the tenant's lock (:func:`reserve_upload`,
  :func:`reserve_job_slots`), so N requests at once accept exactly what fits. Each stored byte counts once: an
  upload being made into a scene stops counting as its scene is measured.
- **Free disk**: an upload is created, and each PATCH accepted, only when the bytes it still needs fit on the
  storage volume with ``min_free_disk_bytes`` left free, less what every other open upload has reserved and not
  yet written (507 otherwise); an extraction is bounded the same way.
- **Retention**: finished jobs older than ``retention_days`` are deleted with their results.
"""

from __future__ import annotations

import logging
import shutil
import uuid
from datetime import timedelta

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from service.db import crud
from service.db.base import utcnow
from service.db.models import Artifact, Job, JobState, Scene, Upload
from service.errors import InsufficientStorage, QuotaExceeded
from service.settings import Settings
from service.storage import Storage

logger = logging.getLogger(__name__)
ORPHAN_GRACE = timedelta(minutes=10)  # a folder younger than this may belong to a row not yet committed
LIVE_STATES = (JobState.QUEUED, JobState.RUNNING)


def check_storage_quota(session: Session, settings: Settings, tenant_id: uuid.UUID, more: int) -> None:
    """Refuse (413) when ``more`` bytes would take the tenant past ``quota_bytes``."""
    if settings.quota_bytes is None:
        return
    used = crud.stored_bytes(session, tenant_id)
    if used + more > settings.quota_bytes:
        needs = f"this needs {more:,} more" if more else "its uploads are counted at their Upload-Length"
        raise QuotaExceeded(
            f"storage quota exceeded: this tenant stores {used:,} bytes and {needs}; the limit is "
            f"{settings.quota_bytes:,} bytes (PANOGS_QUOTA_BYTES); delete scenes or jobs to make room",
            status_code=413,
        )


def room_left(session: Session, settings: Settings, tenant_id: uuid.UUID, releasing: int = 0) -> int | None:
    """Bytes the tenant may still store, once ``releasing`` stored bytes are gone; None when there is no quota."""
    if settings.quota_bytes is None:
        return None
    return max(0, settings.quota_bytes - crud.stored_bytes(session, tenant_id) + releasing)


def disk_room(settings: Settings, storage: Storage) -> int:
    """Bytes the storage volume may still take, keeping ``min_free_disk_bytes`` free."""
    return max(0, shutil.disk_usage(storage.root).free - settings.min_free_disk_bytes)


def check_disk_room(settings: Settings, storage: Storage, needed: int, what: str, reserved: int = 0) -> None:
    """Refuse (507) when ``needed`` bytes do not fit on the storage volume with ``min_free_disk_bytes`` left free,
    once ``reserved`` bytes (promised to other open uploads, not yet written) are set aside.

    An object storage (S3) has no free space to ask: only the local backend is checked (an extraction's scratch
    folder is, through :func:`extraction_limit`).
    """
    free = storage.volume_free_bytes()
    if free is None:
        return
    room = max(0, free - settings.min_free_disk_bytes - reserved)
    if needed > room:
        others = f", {reserved:,} of them promised to open uploads," if reserved else ""
        raise InsufficientStorage(
            f"not enough free disk: {what} needs {needed:,} more bytes, the storage volume can take {room:,} "
            f"while keeping {settings.min_free_disk_bytes:,} bytes free (PANOGS_MIN_FREE_DISK_BYTES){others}; "
            "retry later or ask the operator to free space"
        )


def reserve_upload(session: Session, settings: Settings, storage: Storage, tenant_id: uuid.UUID, length: int) -> None:
    """Check the tenant's quota and the volume's room for a new upload of ``length`` bytes under the tenant's lock
    (and the volume's), which the caller's transaction holds until it commits the upload's row."""
    crud.lock_tenant(session, tenant_id, volume=storage.volume_free_bytes() is not None)
    check_storage_quota(session, settings, tenant_id, length)
    reserved = crud.reserved_upload_bytes(session)
    check_disk_room(settings, storage, length, f"an upload of Upload-Length {length:,}", reserved)


def check_upload_room(session: Session, settings: Settings, storage: Storage, upload: Upload) -> None:
    """Before a PATCH: the tenant within its quota (this upload counts at its full length already), and the bytes
    the upload still needs on the volume, beside what the other open uploads have reserved."""
    check_storage_quota(session, settings, upload.api_key_id, 0)
    remaining = upload.length - upload.offset
    reserved = crud.reserved_upload_bytes(session, excluding=upload.id) if storage.volume_free_bytes() else 0
    what = f"upload {upload.id} ({upload.offset:,} of {upload.length:,} bytes)"
    check_disk_room(settings, storage, remaining, what, reserved)


def extraction_limit(
    session: Session, settings: Settings, storage: Storage, tenant_id: uuid.UUID, releasing: int = 0
) -> tuple[int, str]:
    """The most bytes an archive may expand to, and what sets it: the bundle limit, the tenant's quota room, or the
    free disk (less ``min_free_disk_bytes``). Never above what the core allows by default.

    ``releasing``: stored bytes that stop counting when the extraction succeeds (the upload being extracted is
    deleted then), so that a scene may use the room of the upload it comes from.
    """
    from panogs_core.io.bundle.archive import DEFAULT_MAX_BYTES as DEFAULT_MAX_EXTRACTED_BYTES

    candidates = [(settings.bundle_max_bytes or DEFAULT_MAX_EXTRACTED_BYTES, "the bundle size limit")]
    room = room_left(session, settings, tenant_id, releasing)
    if room is not None:
        candidates.append((room, f"this tenant's storage quota ({settings.quota_bytes:,} bytes, PANOGS_QUOTA_BYTES)"))
    candidates.append((disk_room(settings, storage), "the free disk space of the storage volume"))
    return min(candidates, key=lambda c: c[0])


def check_job_quota(session: Session, settings: Settings, tenant_id: uuid.UUID, slots: int = 1) -> None:
    """Refuse (429) a new job of ``slots`` slots when it would take the tenant's queued and running jobs past
    ``quota_concurrent_jobs`` slots (a tiled job holds one per tile, up to the whole limit)."""
    limit = settings.quota_concurrent_jobs
    if limit is None:
        return
    live = crud.live_job_slots(session, tenant_id, limit)
    if live + min(slots, limit) > limit:
        asks = f"; this job asks {slots} (one per tile)" if slots > 1 else ""
        raise QuotaExceeded(
            f"concurrent job quota reached: the queued and running jobs hold {live} slot(s){asks}; the limit is "
            f"{limit} (PANOGS_QUOTA_CONCURRENT_JOBS; a tiled job holds one per tile); wait for one to finish or "
            "cancel one",
            status_code=429,
        )


def reserve_job_slots(session: Session, settings: Settings, tenant_id: uuid.UUID, slots: int) -> None:
    """:func:`check_job_quota` under the tenant's lock, which the caller's transaction holds until it commits the
    job's row: concurrent creations take the slots one after another."""
    if settings.quota_concurrent_jobs is None:
        return
    crud.lock_tenant(session, tenant_id)
    check_job_quota(session, settings, tenant_id, slots)


def delete_job(session: Session, storage: Storage, job: Job) -> None:
    """Cancel (if live), delete the row (artifacts cascade) and the job's folder."""
    if job.state in LIVE_STATES:
        crud.request_cancel(session, job)
    job_id = job.id
    session.execute(delete(Artifact).where(Artifact.job_id == job_id))
    session.execute(delete(Job).where(Job.id == job_id))
    session.commit()
    storage.delete_prefix(storage.job_prefix(job_id))
    storage.drop_cached(job_id)


def delete_scene(session: Session, storage: Storage, scene: Scene) -> list[uuid.UUID]:
    """Delete a scene with every job on it (each as :func:`delete_job`) and its bundle; returns the jobs' ids."""
    jobs = list(session.scalars(select(Job).where(Job.scene_id == scene.id)))
    for job in jobs:
        delete_job(session, storage, job)
    scene_id = scene.id
    session.execute(delete(Scene).where(Scene.id == scene_id))
    session.commit()
    storage.delete_prefix(storage.scene_prefix(scene_id))
    return [job.id for job in jobs]


def sweep_retention(session: Session, settings: Settings, storage: Storage) -> int:
    """Delete finished jobs older than ``retention_days``; returns how many."""
    if settings.retention_days is None:
        return 0
    cutoff = utcnow() - timedelta(days=settings.retention_days)
    old = list(
        session.scalars(
            select(Job)
            .where(Job.state.in_(tuple(s for s in JobState if s.is_terminal)), Job.finished_at < cutoff)
            .limit(100)
        )
    )
    for job in old:
        delete_job(session, storage, job)
    return len(old)


def sweep_orphans(session: Session, storage: Storage) -> int:
    """Remove job and scene folders whose rows are gone (a delete interrupted between rows and files, or a worker
    that wrote after its job was deleted) once nothing was written in them for ``ORPHAN_GRACE``; returns how many."""
    removed = 0
    cutoff = (utcnow() - ORPHAN_GRACE).timestamp()
    for top, model in (("artifacts/", Job), ("scenes/", Scene)):
        newest: dict[str, float] = {}
        for info in storage.objects.list_objects(top):
            folder = info.key[len(top) :].split("/", 1)[0]
            newest[folder] = max(newest.get(folder, 0.0), info.modified)
        for name, modified in newest.items():
            try:
                ident = uuid.UUID(name)
            except ValueError:
                continue
            if modified < cutoff and session.get(model, ident) is None:
                storage.delete_prefix(f"{top}{name}/")
                removed += 1
    return removed
