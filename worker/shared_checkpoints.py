"""Stage checkpoints shared by the jobs of one scene, by stage key, with a lease so that one job computes each.

The pipeline's stage keys hash a stage's inputs and the settings it reads (``panogs_core.pipeline.stages``), so a
job whose early stages have the key of an earlier job's (a re-run that changes only the clustering thresholds)
fetches those checkpoints instead of computing them: ``scenes/<scene id>/stages/<stage>/<key>.ckpt``.

- **Whole or absent.** A checkpoint is stored once it is complete (the pipeline renames it into place first, and
  an object is written whole by both backends), so a worker that crashes mid-write leaves nothing to read.
- **One computes, the others wait.** A job that misses a checkpoint takes the key's lease (a conditional create
  of ``<key>.lease``); a second job that needs the same key meanwhile waits for the checkpoint, going through the
  job's progress callback each poll (a cancel or a lost lease stops it). The holder refreshes its leases with its
  heartbeat; a lease older than ``lease_s`` belongs to a dead worker and is taken over. Two takers of one stale
  lease may both compute the stage: the result is the same and each write is whole.
- **One copy.** A checkpoint is kept once: with the local backend the job's file and the scene's object are two
  names of the same bytes (hard links; both sides only ever replace a checkpoint by a rename), and with object
  storage the job's own folder does not store the checkpoints kept here (:attr:`SceneCheckpoints.kept`: the
  output folder's push skips them; a retry fetches them from here again). A checkpoint this job will compute is
  in ``kept`` from the moment its lease is taken, before the file exists: the pipeline renames it into place and
  stores it from its writer thread while the next stage's progress pushes the output folder, and a path added
  only once its upload ended was pushed under the job's prefix in between (every job wrote a copy of its last
  stored checkpoint). Should the job end without storing it, the path leaves ``kept`` and the folder's last push
  stores it with the job.
- **Counted and deleted with the scene.** Each stored checkpoint's bytes are added to the scene's ``size_bytes``
  (the tenant's quota); deleting the scene deletes its prefix, checkpoints included.
- **No job hashes an uploaded bundle.** The keys start from a hash of the bundle. A scene made from an upload has
  its archive's SHA-256, computed while the bytes arrived (``service/uploads.py``), and the archive's bytes decide
  every file extracted from it: the keys start from a hash of that (:func:`archive_input_hash`), so no job, the
  scene's first included, reads the 2 GB bundle (ScanNet size) to hash it before its first stage. A scene without
  one (made otherwise) has its first job hash the bundle and keep the hash under the scene (``input.json``, with
  the hashing rule it was made by); the scene's later jobs read it instead of hashing the bundle again (a scene's
  bundle never changes). A kept hash comes first: the scene's stored checkpoints were filed under it.
- **A copy on the worker's disk** (object storage only, :attr:`SceneCheckpoints.local_copies`): what a worker
  fetched or stored stays beside its cached bundle of the scene (``worker/bundle_cache.py``), so that a re-run on
  the same worker reads no checkpoint from the store: at ScanNet size those reads were a third of a re-run's time
  (docs/benchmarks.md, "Re-runs from a scene's checkpoints"). A key names immutable bytes, so a copy is never
  stale; copies are written whole (a rename into place) and go with the cached bundle.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import shutil
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path

from panogs_core.pipeline.input_hash import HASH_RULE
from service.storage import Storage
from service.storage.objects import AlreadyExists, ObjectNotFound, StorageError

logger = logging.getLogger(__name__)

# The rule of :func:`archive_input_hash`, in the hash's own bytes, so that no other rule's input can make it.
ARCHIVE_HASH_RULE = "sha256:upload-archive-sha256:v1"


def archive_input_hash(archive_sha256: str) -> str:
    """The input hash of a bundle extracted from an archive whose SHA-256 is ``archive_sha256`` (64 hex digits)."""
    return hashlib.sha256(f"{ARCHIVE_HASH_RULE}\n{archive_sha256}".encode()).hexdigest()


def _is_sha256(value: object) -> bool:
    return isinstance(value, str) and len(value) == 64 and all(c in "0123456789abcdef" for c in value)


class SceneCheckpoints:
    """``panogs_core.pipeline.run.SharedCheckpoints`` over the storage, under one scene."""

    def __init__(
        self,
        storage: Storage,
        scene_id: uuid.UUID,
        owner: str,
        *,
        lease_s: float,
        poll_s: float = 0.5,
        on_wait: Callable[[str], None] | None = None,
        on_stored: Callable[[int], None] | None = None,
        local_copies: Path | None = None,
        archive_sha256: str | None = None,
    ) -> None:
        self.storage = storage
        # The SHA-256 of the archive the scene's bundle was extracted from (the scene's ``bundle_sha256``), if any.
        self.archive_sha256 = archive_sha256 if _is_sha256(archive_sha256) else None
        self.prefix = f"{storage.scene_prefix(scene_id)}stages/"
        self.owner = owner
        self.lease_s = lease_s
        self.poll_s = poll_s
        self.on_wait = on_wait
        self.on_stored = on_stored
        # The worker's copies of this scene's checkpoints (object storage with a bundle cache), else None.
        self.local_copies = local_copies
        self.reused: list[str] = []  # the stages fetched from another job's checkpoint
        self.kept: set[Path] = set()  # the run folder's files that are checkpoints of this store (fetched, stored)
        self._held: set[tuple[str, str]] = set()
        self._computing: dict[tuple[str, str], Path] = {}  # leased keys not stored yet, and where their file goes
        self._lock = threading.Lock()

    def _object(self, stage: str, key: str) -> str:
        return f"{self.prefix}{stage}/{key}.ckpt"

    def _lease(self, stage: str, key: str) -> str:
        return f"{self.prefix}{stage}/{key}.lease"

    def _lease_body(self) -> bytes:
        return json.dumps({"owner": self.owner, "at": time.time()}).encode()

    def _copy(self, stage: str, key: str) -> Path | None:
        return None if self.local_copies is None else self.local_copies / stage / f"{key}.ckpt"

    def fetch(self, stage: str, key: str, dest: Path) -> bool:
        objects = self.storage.objects
        copy = self._copy(stage, key)
        if copy is not None and copy.is_file():
            _link_or_copy(copy, dest)
            return self._reused(stage, key, dest, "this worker's copy of ")
        while True:
            if objects.stat(self._object(stage, key)) is not None:
                try:
                    self.storage.get_linked(self._object(stage, key), dest)
                except ObjectNotFound:  # deleted between the two calls (the scene is going): compute it
                    return False
                if copy is not None:
                    _keep_copy(dest, copy)
                return self._reused(stage, key, dest, "")
            try:
                objects.put_bytes(self._lease(stage, key), self._lease_body(), if_absent=True)
            except AlreadyExists:
                if self._stale(stage, key):
                    objects.delete(self._lease(stage, key))  # its holder is gone: take it over
                    continue
                if self.on_wait is not None:
                    self.on_wait(stage)  # may raise Cancelled (a cancel, a lost lease, the time limit)
                time.sleep(self.poll_s)
                continue
            if objects.stat(self._object(stage, key)) is not None:
                objects.delete(self._lease(stage, key))  # stored between our look and our lease: fetch it
                continue
            with self._lock:
                self._held.add((stage, key))
                self._computing[(stage, key)] = dest
                self.kept.add(dest)  # before the file exists: see "One copy" above
            return False

    def _reused(self, stage: str, key: str, dest: Path, where: str) -> bool:
        self.kept.add(dest)
        self.reused.append(stage)
        logger.info("stage %s: %scheckpoint %s of this scene reused", stage, where, key)
        return True

    def known_input_hash(self) -> str | None:
        """The scene's bundle hash as a job of the scene kept it (``<prefix>input.json``), else the one its upload's
        archive gives (:func:`archive_input_hash`), else None (the job hashes the bundle)."""
        kept = self._kept_input_hash()
        if kept is not None:
            return kept
        return None if self.archive_sha256 is None else archive_input_hash(self.archive_sha256)

    def _kept_input_hash(self) -> str | None:
        """The hash in ``<prefix>input.json``, or None (none kept, kept by code that hashed otherwise, or not a
        hash)."""
        try:
            kept = json.loads(self.storage.objects.get_bytes(self._input_hash_key()))
        except (ObjectNotFound, ValueError):
            return None
        if not isinstance(kept, dict) or kept.get("rule") != HASH_RULE or not _is_sha256(kept.get("sha256")):
            return None
        return str(kept["sha256"])

    def keep_input_hash(self, sha256: str) -> None:
        """Keep the bundle's hash for the scene's later jobs (the first writer's stays: every job computes the same)."""
        body = json.dumps({"rule": HASH_RULE, "sha256": sha256}).encode()
        try:
            self.storage.objects.put_bytes(self._input_hash_key(), body, if_absent=True)
        except AlreadyExists:
            pass

    def _input_hash_key(self) -> str:
        return f"{self.prefix}input.json"

    def _stale(self, stage: str, key: str) -> bool:
        try:
            holder = json.loads(self.storage.objects.get_bytes(self._lease(stage, key)))
        except ObjectNotFound:
            return False  # released meanwhile: look again
        except ValueError:
            return True
        return bool(time.time() - float(holder.get("at", 0)) > self.lease_s)

    def store(self, stage: str, key: str, path: Path) -> None:
        self.kept.add(path)  # before the upload, which the folder's push must not race (see "One copy" above)
        info = self.storage.put_linked(self._object(stage, key), path)
        with self._lock:
            self._computing.pop((stage, key), None)
        copy = self._copy(stage, key)
        if copy is not None:
            _keep_copy(path, copy)
        if self.on_stored is not None:
            self.on_stored(info.size)
        self._release(stage, key)

    def _release(self, stage: str, key: str) -> None:
        with self._lock:  # not while the heartbeat renews it, which would put it back
            self._held.discard((stage, key))
            self.storage.objects.delete(self._lease(stage, key))

    def refresh(self) -> None:
        """Renew the leases this job holds (from its heartbeat)."""
        with self._lock:
            for stage, key in list(self._held):
                try:
                    self.storage.objects.put_bytes(self._lease(stage, key), self._lease_body())
                except StorageError:
                    logger.warning("stage %s: could not renew the lease of key %s", stage, key)

    def release_all(self) -> None:
        """Give up every lease still held (the job ended, failed or stopped before storing); a checkpoint it did
        not store goes back to the job's own folder's push."""
        with self._lock:
            held = list(self._held)
            for path in self._computing.values():
                self.kept.discard(path)
            self._computing.clear()
        for stage, key in held:
            try:
                self._release(stage, key)
            except StorageError:
                logger.warning("stage %s: lease of key %s not released; it expires", stage, key)


def _link_or_copy(src: Path, dest: Path) -> None:
    """``dest`` made a name of ``src``'s bytes (a hard link; a copy across file systems), replacing it whole."""
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_name(f".{dest.name}.{uuid.uuid4().hex[:8]}")
    try:
        try:
            os.link(src, tmp)
        except OSError:  # another file system (or no hard links there)
            shutil.copyfile(src, tmp)
        os.replace(tmp, dest)
    finally:
        tmp.unlink(missing_ok=True)


def _keep_copy(path: Path, copy: Path) -> None:
    """Keep the checkpoint at ``path`` as this worker's copy; a copy that cannot be made is only logged (the
    store has the checkpoint: a later job fetches it)."""
    try:
        _link_or_copy(path, copy)
    except OSError as exc:
        logger.warning("checkpoint %s: no local copy kept (%s)", copy.name, exc)
