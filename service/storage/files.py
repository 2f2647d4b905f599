"""Helpers over stored bytes that any module of the storage package may use: hashes read in blocks, what an archive
is by its first bytes, a folder's size, an upload's prefix. They know no backend and import nothing of the package
but the object protocol."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

from service.storage.objects import ObjectStorage

BLOCK = 1 << 20  # read/write block, bytes
ARCHIVE_SUFFIXES = {"zip": ".zip", "tar": ".tar", "gzip": ".tar.gz"}


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


def upload_folder(key: str) -> str:
    """The prefix of an upload's objects (``uploads/<id>/``), from the key of its bytes."""
    return key.rsplit("/", 1)[0] + "/"


def sha256_object(objects: ObjectStorage, key: str) -> hashlib._Hash:
    """SHA-256 of a stored object, read in blocks."""
    digest = hashlib.sha256()
    for block in objects.read_range(key, 0, None, block=BLOCK):
        digest.update(block)
    return digest


def detect_archive(path: Path) -> str | None:
    """``.zip``, ``.tar`` or ``.tar.gz`` from the file's first bytes (not its name), or None."""
    with path.open("rb") as f:
        return archive_suffix(f.read(512))


def archive_suffix(head: bytes) -> str | None:
    """:func:`detect_archive` from a file's first 512 bytes."""
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
