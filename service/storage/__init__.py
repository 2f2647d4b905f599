"""Files on the local or shared volume: where uploads, scenes and job artifacts live, and streamed writes.

Layout under ``Settings.storage``::

    uploads/<upload_id>/data          the bytes as they arrive (tus PATCHes append at the offset)
    scenes/<scene_id>/                the validated, extracted bundle (``open_bundle`` workdir)
    artifacts/<job_id>/               the pipeline's out_dir: outputs, stage checkpoints, report

Nothing is read or written whole in memory: writes go through a small buffer, hashes are computed in blocks.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import threading
import uuid
from collections import OrderedDict
from pathlib import Path
from typing import BinaryIO

BLOCK = 1 << 20  # read/write block, bytes
ARCHIVE_SUFFIXES = {"zip": ".zip", "tar": ".tar", "gzip": ".tar.gz"}


class Storage:
    """Paths under one root; relative paths are what the database stores."""

    def __init__(self, root: Path) -> None:
        self.root = root.resolve()

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
        """Where an upload's bytes accumulate."""
        return self.root / "uploads" / str(upload_id) / "data"

    def scene_dir(self, scene_id: uuid.UUID) -> Path:
        """Where a scene's bundle is extracted."""
        return self.root / "scenes" / str(scene_id)

    def job_dir(self, job_id: uuid.UUID) -> Path:
        """A job's pipeline output folder (artifacts and stage checkpoints)."""
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


def sha256_file(path: Path, length: int | None = None) -> hashlib._Hash:
    """SHA-256 of the first ``length`` bytes of ``path`` (all of it by default), read in blocks."""
    digest = hashlib.sha256()
    remaining = path.stat().st_size if length is None else length
    with path.open("rb") as f:
        while remaining > 0:
            block = f.read(min(BLOCK, remaining))
            if not block:
                break
            digest.update(block)
            remaining -= len(block)
    return digest


def detect_archive(path: Path) -> str | None:
    """``.zip``, ``.tar`` or ``.tar.gz`` from the file's first bytes (not its name), or None."""
    with path.open("rb") as f:
        head = f.read(512)
    if head.startswith(b"PK\x03\x04") or head.startswith(b"PK\x05\x06"):
        return ARCHIVE_SUFFIXES["zip"]
    if head.startswith(b"\x1f\x8b"):
        return ARCHIVE_SUFFIXES["gzip"]
    if len(head) >= 262 and head[257:262] == b"ustar":
        return ARCHIVE_SUFFIXES["tar"]
    return None


def dir_size(path: Path) -> int:
    """Total bytes of the regular files under ``path`` (links are not followed)."""
    total = 0
    for dirpath, _dirs, files in os.walk(path):
        for name in files:
            p = Path(dirpath) / name
            if not p.is_symlink():
                total += p.stat().st_size
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

    def take(self, upload_id: uuid.UUID, path: Path, offset: int) -> hashlib._Hash:
        """The running hash of the first ``offset`` bytes (removed from the cache until :meth:`put`)."""
        with self._lock:
            hit = self._states.pop(upload_id, None)
        if hit is not None and hit[0] == offset:
            return hit[1]
        return sha256_file(path, offset)

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


class ChunkWriter:
    """Writes one PATCH body at a known offset, hashing as it goes; used from a worker thread.

    ``write`` is fed the request's chunks; ``close`` flushes and returns the new offset. ``rollback`` cuts the
    file back to where this PATCH started (checksum mismatch).
    """

    def __init__(self, path: Path, offset: int, running: hashlib._Hash, chunk_algo: str | None) -> None:
        self.path = path
        self.start = offset
        self.offset = offset
        self.running = running
        self.chunk_hash = hashlib.new(chunk_algo) if chunk_algo else None
        self._file: BinaryIO = path.open("r+b")
        self._file.seek(offset)
        self._file.truncate(offset)  # bytes past the recorded offset are from an interrupted PATCH

    def write(self, data: bytes | bytearray) -> None:
        """Append ``data`` at the current offset."""
        self._file.write(data)
        self.running.update(data)
        if self.chunk_hash is not None:
            self.chunk_hash.update(data)
        self.offset += len(data)

    def close(self) -> int:
        """Flush to disk; returns the offset after the last byte written."""
        self._file.flush()
        os.fsync(self._file.fileno())
        self._file.close()
        return self.offset

    def rollback(self) -> None:
        """Discard everything this writer wrote."""
        if not self._file.closed:
            self._file.close()
        with self.path.open("r+b") as f:
            f.truncate(self.start)
        self.offset = self.start
