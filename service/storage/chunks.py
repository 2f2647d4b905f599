"""The writers of a tus upload's bytes, one per backend, behind :class:`UploadWriter`.

With the local backend a PATCH body is appended to the upload's file (:class:`ChunkWriter`); with an object storage
it becomes parts of a multipart upload (:class:`service.storage.parts.PartWriter`). ``Storage.upload_writer``
picks the one its backend needs, so the upload code never asks which it has.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, BinaryIO, Protocol


class UploadWriter(Protocol):
    """Writes one PATCH body at the upload's offset, hashing as it goes; used from a worker thread."""

    offset: int
    running: Any  # the upload's running SHA-256, or None where none was kept (rebuilt from the object at the end)
    chunk_hash: Any  # the chunk's own hash (``Upload-Checksum``), or None

    def write(self, data: bytes | bytearray) -> None: ...

    def close(self) -> int: ...

    def rollback(self) -> None: ...

    def settle(self, length: int) -> tuple[Any, dict[str, Any] | None]:
        """After :meth:`close`: the upload's running hash (joined and complete once ``offset == length``) and the
        state its row records (None where the bytes themselves are the state)."""
        ...


class ChunkWriter:
    """Writes one PATCH body at a known offset of the upload's file, hashing as it goes.

    ``write`` is fed the request's chunks; ``close`` flushes and returns the new offset. ``rollback`` cuts the
    file back to where this PATCH started (checksum mismatch).
    """

    def __init__(self, path: Path, offset: int, running: Any, chunk_algo: str | None) -> None:
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

    def settle(self, length: int) -> tuple[Any, dict[str, Any] | None]:
        """The running hash; the file is the upload's whole state."""
        return self.running, None
