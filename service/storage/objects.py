"""What the service and the workers store, as objects under keys: the one protocol of both storage backends.

A key is a relative, ``/``-separated path (``uploads/<id>/data``, ``scenes/<id>/bundle/scene.json``,
``artifacts/<job id>/panoptic.ply``). Two backends implement :class:`ObjectStorage` with the same behaviour, which
``tests/service/test_storage_contract.py`` runs against both:

- :class:`service.storage.local.LocalStorage`: files under one folder (the embedded default, ``./panogs-data``);
- :class:`service.storage.s3.S3Storage`: an S3 bucket and prefix through boto3 (``PANOGS_STORAGE_URL=s3://...``).

Both write an object whole or not at all (a reader never sees half of one), both refuse a multipart part under
:data:`MIN_PART_BYTES` unless it is the last, and both answer a range that starts past the end with
:class:`RangeNotSatisfiable`. Every call blocks: the API calls them from a worker thread.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Protocol

# S3's smallest part of a multipart upload, every part but the last (SeaweedFS enforces it as AWS does).
MIN_PART_BYTES = 5 * 1024 * 1024
MAX_PARTS = 10_000  # S3's most parts in one multipart upload
_KEY_PART = re.compile(r"^[A-Za-z0-9._+=@,-]+$")


class StorageError(Exception):
    """A storage operation failed for a reason that waiting cannot fix (refused, malformed, too small)."""


class StorageUnavailable(StorageError):
    """The storage did not answer or answered that it is busy: the same call may succeed later."""


class ObjectNotFound(StorageError, KeyError):
    """No object under that key (or no multipart upload under that id)."""

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else "object not found"


class AlreadyExists(StorageError):
    """A conditional create found an object under the key already."""


class RangeNotSatisfiable(StorageError):
    """A byte range that starts at or past the object's end; ``size`` is the object's length."""

    def __init__(self, key: str, start: int, size: int) -> None:
        super().__init__(f"{key}: range start {start} is past the object's {size} bytes")
        self.size = size


@dataclass(frozen=True)
class ObjectInfo:
    """One stored object: its key, size in bytes, an opaque version tag (changes when the bytes do) and, where the
    listing gives it, when it was last written (seconds since the epoch; 0 when unknown)."""

    key: str
    size: int
    etag: str
    modified: float = 0.0


@dataclass(frozen=True)
class Part:
    """One uploaded part of a multipart upload (numbered from 1)."""

    number: int
    size: int
    etag: str


def check_key(key: str, *, prefix: bool = False) -> str:
    """``key`` when it is a relative path of plain parts; a prefix (``prefix=True``) must end with ``/``.

    Refuses ``..``, ``.``, empty parts, absolute paths and characters outside ``[A-Za-z0-9._+=@,-]``: a key
    comes from the service's own ids and the run folder's declared names, never from a user's text.
    """
    body = key
    if prefix:
        if not key.endswith("/"):
            raise ValueError(f"storage prefix {key!r} must end with '/'")
        body = key[:-1]
    parts = body.split("/")
    if not body or any(p in ("", ".", "..") or not _KEY_PART.match(p) for p in parts):
        raise ValueError(f"storage key {key!r} is not a relative path of plain names")
    return key


class ObjectStorage(Protocol):
    """Objects under keys; uploads in parts; ranges; prefix deletes; signed download links."""

    @property
    def url(self) -> str:
        """Where the objects are (``file:///...`` or ``s3://bucket/prefix``), for logs and messages."""
        ...

    def put_bytes(self, key: str, data: bytes, *, if_absent: bool = False) -> ObjectInfo:
        """Store ``data`` under ``key``; with ``if_absent``, raise :class:`AlreadyExists` when it exists."""
        ...

    def put_file(self, key: str, path: Path) -> ObjectInfo:
        """Store a local file under ``key``, streamed (never whole in memory)."""
        ...

    def put_stream(self, key: str, stream: BinaryIO) -> ObjectInfo:
        """Store what ``stream`` yields under ``key``, streamed."""
        ...

    def get_bytes(self, key: str) -> bytes:
        """The whole object (for small ones: JSON, markers)."""
        ...

    def get_file(self, key: str, path: Path) -> ObjectInfo:
        """Copy the object to a local file, streamed; ``path`` appears whole (written aside, then renamed)."""
        ...

    def read_range(self, key: str, start: int = 0, end: int | None = None, *, block: int = 1 << 20) -> Iterator[bytes]:
        """Bytes ``[start, end)`` (``end`` clipped to the size; None: to the end) in blocks of at most ``block``.

        Raises :class:`RangeNotSatisfiable` when ``start`` is at or past the end of a non-empty object, before
        yielding anything.
        """
        ...

    def stat(self, key: str) -> ObjectInfo | None:
        """The object's size and tag, or None when there is none."""
        ...

    def list_objects(self, prefix: str) -> Iterator[ObjectInfo]:
        """Every object whose key starts with ``prefix`` (a folder: ends with ``/``), in key order."""
        ...

    def delete(self, key: str) -> None:
        """Delete one object (nothing when it is absent)."""
        ...

    def delete_prefix(self, prefix: str) -> int:
        """Delete every object under ``prefix`` and abort its multipart uploads; returns the objects deleted."""
        ...

    def signed_url(self, key: str, expires_s: int) -> str:
        """A link that downloads the object without other credentials until ``expires_s`` from now."""
        ...

    def start_multipart(self, key: str) -> str:
        """Begin a multipart upload to ``key``; returns its id."""
        ...

    def put_part(self, key: str, upload_id: str, number: int, data: bytes) -> Part:
        """Store part ``number`` (1 to :data:`MAX_PARTS`) of an upload; the same number again replaces it."""
        ...

    def list_parts(self, key: str, upload_id: str) -> list[Part]:
        """The parts stored so far, by number (raises :class:`ObjectNotFound` for an unknown upload).

        A part sent twice within one second may be listed in either version by SeaweedFS (its times are whole
        seconds): complete an upload with the parts :meth:`put_part` returned, kept by the caller.
        """
        ...

    def complete_multipart(self, key: str, upload_id: str, parts: Iterable[Part]) -> ObjectInfo:
        """Join ``parts`` (in number order) into the object; every part but the last has :data:`MIN_PART_BYTES`."""
        ...

    def abort_multipart(self, key: str, upload_id: str) -> None:
        """Drop an upload and its parts (nothing when it is gone)."""
        ...

    def list_multipart(self, prefix: str) -> list[tuple[str, str]]:
        """``(key, upload id)`` of the unfinished multipart uploads under ``prefix``."""
        ...


def check_parts(key: str, parts: list[Part]) -> list[Part]:
    """``parts`` in number order, refused as S3 refuses them: none, repeated numbers, a small part before the last."""
    ordered = sorted(parts, key=lambda p: p.number)
    if not ordered:
        raise StorageError(f"{key}: a multipart upload needs at least one part")
    numbers = [p.number for p in ordered]
    if len(set(numbers)) != len(numbers):
        raise StorageError(f"{key}: part numbers repeat: {numbers}")
    small = [p.number for p in ordered[:-1] if p.size < MIN_PART_BYTES]
    if small:
        raise StorageError(f"{key}: parts {small} are under {MIN_PART_BYTES} bytes and not the last (EntityTooSmall)")
    return ordered


def check_part_number(number: int) -> None:
    """Part numbers are 1 to :data:`MAX_PARTS`."""
    if not 1 <= number <= MAX_PARTS:
        raise StorageError(f"part number {number} is outside 1..{MAX_PARTS}")
