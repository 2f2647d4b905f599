"""Scene bundles kept on a worker's disk between its jobs (object storage only), so that a scene's re-run does not
fetch its whole bundle again: at ScanNet size that fetch was most of a re-run's time (docs/benchmarks.md,
"Re-runs from a scene's checkpoints").

- **Immutable, so safe to keep.** A scene's bundle never changes once stored; an entry is named by the scene's id
  (``<work>/bundles/<scene id>/``) and used read-only by the pipeline (which extracts into the job's folder).
- **Whole or absent.** A bundle is fetched into a temporary folder and renamed into place, then marked complete
  with its size; a fetch that died leaves a temporary folder that the next sweep removes.
- **Shared by the processes of one host.** Each use holds a shared ``flock`` on the entry's lock file (the fetch an
  exclusive one), so that a sweep in another worker process never removes a bundle a job is reading.
- **Bounded, and gone with the scene.** After each job the entries beyond ``max_bytes`` (least recently used
  first) and those whose scene no longer exists are removed, unless in use; ``max_bytes`` 0 keeps nothing.
- **The scene's checkpoints beside its bundle.** ``<scene id>.stages/`` holds this worker's copies of the scene's
  stage checkpoints (``worker/shared_checkpoints.py``); it counts in the entry's size and goes with the bundle.
"""

from __future__ import annotations

import fcntl
import logging
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO

from service.storage import Storage, dir_size

logger = logging.getLogger(__name__)

COMPLETE = ".complete"  # inside an entry: its size in bytes; written last
STAGES_SUFFIX = ".stages"  # <scene id>.stages/: the worker's copies of the scene's checkpoints


class BundleCache:
    """Bundles under ``folder`` (at most ``max_bytes`` kept after a job); ``live`` tells which scene ids exist."""

    def __init__(
        self, storage: Storage, folder: Path, max_bytes: int, live: Callable[[Iterable[uuid.UUID]], set[uuid.UUID]]
    ) -> None:
        self.storage = storage
        self.folder = folder
        self.max_bytes = max_bytes
        self.live = live

    def _entry(self, scene_id: uuid.UUID) -> Path:
        return self.folder / str(scene_id)

    def stages_folder(self, scene_id: uuid.UUID) -> Path:
        """Where this worker keeps its copies of the scene's stage checkpoints (used while the bundle is)."""
        return self.folder / f"{scene_id}{STAGES_SUFFIX}"

    @contextmanager
    def _locked(self, scene_id: uuid.UUID, mode: int) -> Iterator[IO[bytes]]:
        self.folder.mkdir(parents=True, exist_ok=True)
        with (self.folder / f"{scene_id}.lock").open("ab") as lock:
            fcntl.flock(lock, mode)
            try:
                yield lock
            finally:
                fcntl.flock(lock, fcntl.LOCK_UN)

    @contextmanager
    def use(self, scene_id: uuid.UUID, bundle_prefix: str) -> Iterator[Path]:
        """The scene's bundle on this disk (fetched first when missing), kept from removal while the body runs."""
        entry = self._entry(scene_id)
        with self._locked(scene_id, fcntl.LOCK_EX) as lock:
            if not (entry / COMPLETE).is_file():
                self._fetch(entry, bundle_prefix)
            os.utime(entry)  # most recently used
            fcntl.flock(lock, fcntl.LOCK_SH)  # others may read it too now; a sweep may not remove it
            yield entry

    def _fetch(self, entry: Path, bundle_prefix: str) -> None:
        shutil.rmtree(entry, ignore_errors=True)  # an entry without its mark is a fetch that did not end
        tmp = entry.with_name(f".{entry.name}.{uuid.uuid4().hex[:8]}")
        try:
            self.storage.fetch_tree(bundle_prefix.rstrip("/") + "/", tmp)
            tmp.mkdir(exist_ok=True)  # an empty bundle has no object to make the folder
            (tmp / COMPLETE).write_text(str(dir_size(tmp)))
            tmp.rename(entry)
        finally:
            shutil.rmtree(tmp, ignore_errors=True)

    def sweep(self) -> None:
        """Remove what a job no longer needs: bundles of deleted scenes, the least recently used beyond
        ``max_bytes``, and the leftovers of fetches that died. An entry in use is left for a later sweep."""
        if not self.folder.is_dir():
            return
        entries: list[tuple[float, uuid.UUID, int]] = []
        for path in self.folder.iterdir():
            if path.name.startswith(".") and path.is_dir():
                self._remove_unless_fetching(path)
                continue
            if not path.is_dir():
                continue
            if path.name.endswith(STAGES_SUFFIX):
                self._remove_orphan_stages(path)
                continue
            try:
                scene_id = uuid.UUID(path.name)
                size = int((path / COMPLETE).read_text())
            except (ValueError, OSError):
                continue  # being fetched (no mark yet), or not ours
            stages = self.stages_folder(scene_id)
            size += dir_size(stages) if stages.is_dir() else 0
            entries.append((path.stat().st_mtime, scene_id, size))
        existing = self.live([scene_id for _, scene_id, _ in entries])
        kept = 0
        for _, scene_id, size in sorted(entries, reverse=True):  # newest first: the oldest go over the bound
            if scene_id in existing and kept + size <= self.max_bytes:
                kept += size
                continue
            if not self._remove(scene_id):
                kept += size  # in use: it stays, and counts

    def _remove(self, scene_id: uuid.UUID) -> bool:
        try:
            with self._locked(scene_id, fcntl.LOCK_EX | fcntl.LOCK_NB):
                shutil.rmtree(self._entry(scene_id), ignore_errors=True)
                shutil.rmtree(self.stages_folder(scene_id), ignore_errors=True)
        except BlockingIOError:
            return False
        # The lock file stays (empty): removing it could let two processes lock two files of one name.
        logger.info("bundle of scene %s removed from this worker's cache", scene_id)
        return True

    def _remove_orphan_stages(self, stages: Path) -> None:
        """Checkpoint copies whose bundle is no longer here (removed by hand, or a fetch that failed) go."""
        try:
            scene_id = uuid.UUID(stages.name[: -len(STAGES_SUFFIX)])
        except ValueError:
            return
        try:
            with self._locked(scene_id, fcntl.LOCK_EX | fcntl.LOCK_NB):
                if not (self._entry(scene_id) / COMPLETE).is_file():
                    shutil.rmtree(stages, ignore_errors=True)
        except BlockingIOError:
            return  # in use

    def _remove_unless_fetching(self, tmp: Path) -> None:
        try:
            scene_id = uuid.UUID(tmp.name[1:].split(".", 1)[0])
        except ValueError:
            return
        try:
            with self._locked(scene_id, fcntl.LOCK_EX | fcntl.LOCK_NB):
                shutil.rmtree(tmp, ignore_errors=True)
        except BlockingIOError:
            return  # its fetch is running
