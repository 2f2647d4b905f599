"""Where uploads, scenes and job artifacts live: an object storage (:mod:`service.storage.objects`) behind the
paths and keys the service uses, and streamed writes.

Keys (the same layout on disk for the local backend, under ``Settings.storage``)::

    uploads/<upload_id>/data          the bytes as they arrive (tus PATCHes: appended on disk, S3 multipart parts)
    scenes/<scene_id>/                the validated, extracted bundle (``open_bundle`` workdir)
    artifacts/<job_id>/               the pipeline's out_dir: outputs, stage checkpoints, report

With the local backend (the embedded default) the service works on those files in place, as it always did. With
S3 (``PANOGS_STORAGE_URL``) nothing is shared between hosts but the bucket: each process keeps only a work folder
of its own (``<data_dir>/work``): scratch folders for an extraction or a job, removed after it, and a cache of
finished jobs' result files that the API reads.

Every difference between the two lives in this package, behind :class:`Storage`: the folders a leased task works
in (:mod:`service.storage.workspace`), an archive's way into a scene (:mod:`service.storage.extraction`), the
writer of an upload's bytes (:mod:`service.storage.chunks`), a download (:mod:`service.storage.download`), the
checkpoints kept as links or copies, and the free space there is to ask about. No module outside it asks which
backend it has.

Nothing is read or written whole in memory: writes go through a small buffer, hashes are computed in blocks.
"""

from __future__ import annotations

import hashlib
import shutil
import threading
import uuid
from collections import OrderedDict
from collections.abc import Iterator
from contextlib import AbstractContextManager, ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from service.storage.extraction import Extraction, open_extraction
from service.storage.files import (
    BLOCK,
    archive_suffix,
    detect_archive,
    dir_size,
    sha256_file,
    sha256_object,
    upload_folder,
)
from service.storage.local import LocalStorage
from service.storage.objects import ObjectInfo, ObjectStorage
from service.storage.scratch import owner_tag, sweep_stale
from service.storage.workspace import InPlace, WorkPlan, Workspace

if TYPE_CHECKING:
    from service.storage.chunks import UploadWriter

__all__ = [
    "BLOCK",
    "HashStates",
    "Storage",
    "TreePush",
    "archive_suffix",
    "detect_archive",
    "dir_size",
    "sha256_file",
    "sha256_object",
    "upload_folder",
]

STAGES_PREFIX = "stages/"  # a job's checkpoints: never in the API's cache of result files


class Storage:
    """The object storage with the service's keys; with the local backend, also the files themselves."""

    def __init__(self, root: Path, objects: ObjectStorage | None = None) -> None:
        """``root``: the local backend's folder, or (with ``objects`` another backend) this process's work folder."""
        self.root = root.resolve()
        self.objects: ObjectStorage = objects if objects is not None else LocalStorage(self.root)
        # The objects are this folder's own files: the service works on them in place (no scratch, no cache).
        self._in_place = isinstance(self.objects, LocalStorage) and self.objects.root == self.root

    # Keys ------------------------------------------------------------------------------------------------------

    @staticmethod
    def upload_key(upload_id: uuid.UUID) -> str:
        return f"uploads/{upload_id}/data"

    @staticmethod
    def scene_prefix(scene_id: uuid.UUID) -> str:
        return f"scenes/{scene_id}/"

    @staticmethod
    def job_prefix(job_id: uuid.UUID) -> str:
        return f"artifacts/{job_id}/"

    def delete_prefix(self, prefix: str) -> int:
        """Delete every object under ``prefix`` (and unfinished multipart uploads there)."""
        return self.objects.delete_prefix(prefix)

    # Local files (the local backend's own, or this process's work folder) --------------------------------------

    def path(self, rel: str) -> Path:
        """Absolute path of a stored relative path; refuses anything that leaves the root."""
        full = (self.root / rel).resolve()
        if not full.is_relative_to(self.root):
            raise ValueError(f"path {rel!r} leaves the storage root")
        return full

    def rel(self, path: Path) -> str:
        """The relative path the database stores for ``path``."""
        return path.resolve().relative_to(self.root).as_posix()

    def upload_file(self, upload_id: uuid.UUID) -> Path:
        """Where an upload's bytes accumulate (local backend)."""
        return self.root / self.upload_key(upload_id)

    def scene_dir(self, scene_id: uuid.UUID) -> Path:
        """Where a scene's bundle is extracted (local backend)."""
        return self.root / "scenes" / str(scene_id)

    def job_dir(self, job_id: uuid.UUID) -> Path:
        """A job's pipeline output folder (artifacts and stage checkpoints; local backend)."""
        return self.root / "artifacts" / str(job_id)

    def remove_tree(self, path: Path) -> None:
        """Delete a folder (or file) under the root, if present."""
        path = path.resolve()
        if not path.is_relative_to(self.root) or path == self.root:
            raise ValueError(f"refusing to delete {path}: not inside the storage root")
        if path.is_dir():
            shutil.rmtree(path, ignore_errors=True)
        elif path.exists():
            path.unlink()

    @contextmanager
    def scratch(self, what: str) -> Iterator[Path]:
        """A fresh local folder for one task (an extraction, a job), removed after it whatever happens (and, if this
        process is killed, by the next one that sweeps: :meth:`sweep_scratch`)."""
        folder = self.root / "work" / "scratch" / f"{what}-{owner_tag()}-{uuid.uuid4().hex[:12]}"
        folder.mkdir(parents=True)
        try:
            yield folder
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def sweep_scratch(self) -> list[str]:
        """Remove the scratch folders of processes that are gone (killed mid-task); returns their names."""
        return sweep_stale(self.root / "work" / "scratch")

    def run_folder(self, job_id: uuid.UUID) -> Path:
        """A local folder with a job's result files: the job's own folder with the local backend; else a cache of
        them in the work folder, brought up to date from the storage (a file that changed or is new is fetched;
        the stage checkpoints are not)."""
        if self._in_place:
            return self.job_dir(job_id)
        folder = self.root / "work" / "cache" / "artifacts" / str(job_id)
        prefix = self.job_prefix(job_id)
        for info in self.objects.list_objects(prefix):
            rel = info.key[len(prefix) :]
            if rel.startswith(STAGES_PREFIX):
                continue
            local = folder / rel
            if not local.is_file() or local.stat().st_size != info.size:
                self.objects.get_file(info.key, local)
        folder.mkdir(parents=True, exist_ok=True)
        return folder

    def drop_cached(self, job_id: uuid.UUID) -> None:
        """Forget the cached result files of a deleted job (S3 backend)."""
        if not self._in_place:
            shutil.rmtree(self.root / "work" / "cache" / "artifacts" / str(job_id), ignore_errors=True)

    def fetch_tree(self, prefix: str, folder: Path) -> int:
        """Copy every object under ``prefix`` into ``folder`` (keys below the prefix as paths); returns how many."""
        count = 0
        for info in self.objects.list_objects(prefix):
            self.objects.get_file(info.key, folder / info.key[len(prefix) :])
            count += 1
        return count

    def store_tree(self, folder: Path, prefix: str) -> int:
        """Store every file under ``folder`` as an object under ``prefix``; returns the bytes stored."""
        return TreePush(self, folder, prefix).push()

    # What the backends do differently -------------------------------------------------------------------------

    def begin_upload(self, upload_id: uuid.UUID) -> dict[str, Any] | None:
        """Make room for a new upload's bytes: an empty file in place, or a multipart upload (whose state the row
        records, returned here)."""
        if self._in_place:
            path = self.upload_file(upload_id)
            path.parent.mkdir(parents=True, exist_ok=True)
            path.touch()
            return None
        from service.storage import parts

        return parts.begin(self.objects, self.upload_key(upload_id))

    def upload_writer(
        self,
        key: str,
        upload_id: uuid.UUID,
        offset: int,
        multipart: dict[str, Any] | None,
        hashes: HashStates,
        chunk_algo: str | None,
    ) -> UploadWriter:
        """The writer of one PATCH body at ``offset`` of the upload stored at ``key`` (blocking: call from a
        thread): appended to the file in place, or parts of the multipart upload (a running hash this process
        does not keep is made from the joined object at the end)."""
        from service.storage.chunks import ChunkWriter
        from service.storage.parts import PartWriter

        if self._in_place:
            path = self.path(key)
            running = hashes.take(upload_id, path, offset)
            assert running is not None  # rebuilt from the file when not kept
            return ChunkWriter(path, offset, running, chunk_algo)
        cached = hashes.take(upload_id, None, offset)
        return PartWriter(self.objects, key, offset, multipart, cached, chunk_algo)

    def upload_complete(self, key: str) -> None:
        """The upload at ``key`` is recorded complete: the states of its parts are done with (object storage)."""
        if not self._in_place:
            from service.storage import parts

            parts.forget_other_states(self.objects, key, -1)

    def download_link(self, key: str, expires_s: int) -> str | None:
        """A link of the store that downloads ``key`` for ``expires_s``, or None where there is none a client could
        follow: the local backend (the API is the store), or a store reachable only from the service's network."""
        public_url = getattr(self.objects, "public_url", None)
        if self._in_place or public_url is None:
            return None
        url: str | None = public_url(key, expires_s)
        return url

    def served_file(self, key: str) -> Path | None:
        """The object ``key`` as a file a response may send itself (the local backend's own file), or None: the
        object is streamed from the store (:mod:`service.storage.download`)."""
        return self.path(key) if self._in_place else None

    def volume_free_bytes(self) -> int | None:
        """Free bytes of the volume the objects are written to, or None where there is none to ask (an object
        store: only an extraction's scratch folder is bounded, through the work folder's volume)."""
        return shutil.disk_usage(self.root).free if self._in_place else None

    def work_folder(self, name: str) -> Path | None:
        """A folder of this process's work folder for copies of stored objects kept between tasks (a worker's
        bundles and checkpoints), or None where the objects are files of this host already (a copy would be a
        second one)."""
        return None if isinstance(self.objects, LocalStorage) else self.root / "work" / name

    def get_linked(self, key: str, dest: Path) -> ObjectInfo:
        """The object ``key`` at ``dest``: a second name of the same file where the objects are files of this host,
        else a download. For objects only ever replaced by a rename (the checkpoints)."""
        if isinstance(self.objects, LocalStorage):
            return self.objects.link_out(key, dest)
        return self.objects.get_file(key, dest)

    def put_linked(self, key: str, path: Path) -> ObjectInfo:
        """Keep the file at ``path`` as the object ``key``: a second name of it where the objects are files of this
        host, else an upload. For files only ever replaced by a rename (the checkpoints)."""
        if isinstance(self.objects, LocalStorage):
            return self.objects.link_in(key, path)
        return self.objects.put_file(key, path)

    @contextmanager
    def workspace(self, job_id: uuid.UUID, plan: WorkPlan) -> Iterator[Workspace]:
        """The folders of one leased task of job ``job_id`` (:mod:`service.storage.workspace`): in place with the
        local backend; else a scratch folder of the task, removed when it ends, with the scene's bundle (the
        worker's cached one, or fetched), what the task reads of the job's folder fetched, and a push of what it
        writes."""
        if self._in_place:
            out = self.job_dir(job_id)
            out.mkdir(parents=True, exist_ok=True)
            yield Workspace(self.path(plan.bundle_path), out, InPlace())
            return
        prefix = self.job_prefix(job_id)
        with ExitStack() as stack:
            scratch = stack.enter_context(self.scratch(f"{plan.name}-{job_id}"))
            out = scratch / "out"
            out.mkdir()
            if plan.cached_bundle is not None:
                bundle = stack.enter_context(plan.cached_bundle())
            else:
                bundle = scratch / "bundle"
                self.fetch_tree(plan.bundle_path.rstrip("/") + "/", bundle)
            for rel in plan.fetch:
                if rel == "" or rel.endswith("/"):
                    self.fetch_tree(prefix + rel, out / rel)
                else:
                    self.objects.get_file(prefix + rel, out / rel)
            own = out / plan.push
            own.mkdir(parents=True, exist_ok=True)
            push = TreePush(self, own, prefix + plan.push)
            push.mark_present()
            yield Workspace(bundle, out, push)

    def extraction(self, upload_key: str, scene_id: uuid.UUID) -> AbstractContextManager[Extraction | None]:
        """An archive's way into scene ``scene_id`` (:func:`service.storage.extraction.open_extraction`)."""
        return open_extraction(self, self._in_place, upload_key, scene_id)


class TreePush:
    """Stores what changed in a local folder since the last :meth:`push` (new files, or a size or time that moved)
    as objects under a prefix: a job's scratch output folder, pushed after each stage and at the end. A file that
    was stored (or fetched) and is gone from the folder is deleted under the prefix too: a finished tile drops its
    bulky checkpoints, which must not stay behind in the bucket.

    Temporary files of the pipeline (``*.tmp``, ``*.tmp.npz``) are never pushed: a checkpoint is stored once it
    has its name, so a half-written one never reaches the storage; nor the files in :attr:`skip` (kept under
    another key already: a job's checkpoints that the scene's shared store holds).
    """

    def __init__(self, storage: Storage, folder: Path, prefix: str) -> None:
        self.storage = storage
        self.folder = folder
        self.prefix = prefix
        self._seen: dict[str, tuple[int, int]] = {}
        self.skip: set[Path] = set()

    def mark_present(self) -> None:
        """Take the folder's current files as stored already (they were just fetched from the prefix)."""
        for path, rel in self._files():
            st = path.stat()
            self._seen[rel] = (st.st_size, st.st_mtime_ns)

    def _files(self) -> Iterator[tuple[Path, str]]:
        for path in sorted(self.folder.rglob("*")):
            if path.is_file() and not path.is_symlink() and ".tmp" not in path.name and path not in self.skip:
                yield path, path.relative_to(self.folder).as_posix()

    def push(self) -> int:
        """Store the files that changed and delete the objects of those removed; returns the bytes stored."""
        total = 0
        present = set()
        for path, rel in self._files():
            present.add(rel)
            st = path.stat()
            mark = (st.st_size, st.st_mtime_ns)
            if self._seen.get(rel) != mark:
                total += self.storage.objects.put_file(self.prefix + rel, path).size
                self._seen[rel] = mark
        for rel in sorted(set(self._seen) - present):
            if not (self.folder / rel).exists():  # removed, not merely skipped
                self.storage.objects.delete(self.prefix + rel)
            del self._seen[rel]
        return total


class HashStates:
    """Running SHA-256 of in-progress uploads, so that each byte is hashed once when PATCHes arrive in order.

    Keyed by upload id with the offset the state covers. A state that is missing (another API process took the
    previous PATCH, or this one restarted) is rebuilt from the bytes already on disk.
    """

    def __init__(self, capacity: int = 64) -> None:
        self._states: OrderedDict[uuid.UUID, tuple[int, hashlib._Hash]] = OrderedDict()
        self._capacity = capacity
        self._lock = threading.Lock()

    def take(self, upload_id: uuid.UUID, path: Path | None, offset: int) -> hashlib._Hash | None:
        """The running hash of the first ``offset`` bytes (removed from the cache until :meth:`put`); rebuilt from
        ``path`` when this process has none, or None without a path (the parts of an S3 upload cannot be read)."""
        with self._lock:
            hit = self._states.pop(upload_id, None)
        if hit is not None and hit[0] == offset:
            return hit[1]
        return sha256_file(path, offset) if path is not None else None

    def put(self, upload_id: uuid.UUID, offset: int, digest: hashlib._Hash) -> None:
        """Keep the running hash that covers ``offset`` bytes."""
        with self._lock:
            self._states[upload_id] = (offset, digest)
            while len(self._states) > self._capacity:
                self._states.popitem(last=False)

    def drop(self, upload_id: uuid.UUID) -> None:
        """Forget an upload's state."""
        with self._lock:
            self._states.pop(upload_id, None)
