"""Resumable uploads, tus 1.0 (core, creation, creation-with-upload, termination and checksum extensions).

The body of a PATCH (or of the creating POST) is streamed to disk at the upload's offset through a 1 MiB
buffer, hashed as it goes (SHA-256 of the whole upload, plus the chunk's own checksum when the client sends
``Upload-Checksum``). The database offset moves only after the bytes are on disk (fsync), so a server killed
mid-request resumes cleanly: bytes past the recorded offset are cut off by the next PATCH. A client that
disconnects keeps what arrived (unless it asked for a chunk checksum, which then cannot be verified).

Whole-file integrity: the client may send the expected SHA-256 (hex) as ``sha256`` in ``Upload-Metadata``;
when the last byte arrives the upload is verified and, on a mismatch, discarded.
"""

from __future__ import annotations

import base64
import binascii
import errno
import uuid
from typing import Any

import anyio.to_thread
from fastapi import Request
from sqlalchemy.orm import Session
from starlette.requests import ClientDisconnect

from service.db import crud
from service.db.base import utcnow
from service.db.models import Upload, UploadState
from service.errors import (
    ChecksumMismatch,
    Conflict,
    InsufficientStorage,
    InvalidInput,
    PayloadTooLarge,
    PreconditionFailed,
    ServiceError,
    UnsupportedMediaType,
)
from service.lifecycle import reserve_upload
from service.settings import Settings
from service.storage import BLOCK, HashStates, Storage, upload_folder
from service.storage.chunks import UploadWriter
from service.storage.objects import StorageError
from service.stored_text import printable_text

TUS_VERSION = "1.0.0"
TUS_EXTENSIONS = "creation,creation-with-upload,termination,checksum"
TUS_CHECKSUMS = "sha256"
OCTET = "application/offset+octet-stream"
DISK_FULL = (errno.ENOSPC, errno.EDQUOT)  # a write that fails for room is the volume's 507, not the server's 500


def tus_headers(**extra: Any) -> dict[str, str]:
    """Headers every tus response carries, plus ``extra`` (``Upload_Offset`` -> ``Upload-Offset``)."""
    headers = {"Tus-Resumable": TUS_VERSION, "Cache-Control": "no-store"}
    headers.update({k.replace("_", "-"): str(v) for k, v in extra.items()})
    return headers


def check_tus_version(value: str | None) -> None:
    """A client that names a tus version must name 1.0.0."""
    if value is not None and value != TUS_VERSION:
        raise PreconditionFailed(f"Tus-Resumable {value!r} is not supported; this server speaks {TUS_VERSION}")


def parse_metadata(header: str | None) -> dict[str, str]:
    """``Upload-Metadata``: comma-separated ``key base64(value)`` pairs."""
    out: dict[str, str] = {}
    if not header:
        return out
    for pair in header.split(","):
        parts = pair.strip().split(" ")
        if not parts[0] or len(parts) > 2:
            raise InvalidInput(f"Upload-Metadata: malformed pair {pair.strip()!r}; expected 'key base64value'")
        try:
            out[parts[0]] = base64.b64decode(parts[1], validate=True).decode() if len(parts) == 2 else ""
        except (binascii.Error, UnicodeDecodeError) as exc:
            raise InvalidInput(f"Upload-Metadata: value of {parts[0]!r} is not base64 of UTF-8 text") from exc
    return out


def parse_checksum(header: str | None) -> tuple[str, bytes] | None:
    """``Upload-Checksum: sha256 <base64 digest>``."""
    if header is None:
        return None
    algo, _, value = header.strip().partition(" ")
    if algo.lower() != "sha256":
        raise InvalidInput(f"Upload-Checksum: algorithm {algo!r} is not supported; use sha256")
    try:
        digest = base64.b64decode(value, validate=True)
    except binascii.Error as exc:
        raise InvalidInput("Upload-Checksum: the digest is not base64") from exc
    if len(digest) != 32:
        raise InvalidInput(f"Upload-Checksum: a sha256 digest has 32 bytes, found {len(digest)}")
    return "sha256", digest


MAX_FILENAME_CHARS = 255  # the upload's filename column, and the scene name made from it


def create_upload(
    session: Session,
    settings: Settings,
    storage: Storage,
    tenant_id: uuid.UUID,
    length: int,
    metadata: dict[str, str],
) -> Upload:
    """A new empty upload of ``length`` bytes, its bytes and disk room reserved against the tenant's quota and the
    volume under the tenant's lock (``service.lifecycle.reserve_upload``) in the transaction that adds its row."""
    if length > settings.max_upload_bytes:
        raise PayloadTooLarge(f"Upload-Length {length} exceeds the limit of {settings.max_upload_bytes} bytes")
    expected = metadata.get("sha256")
    if expected is not None:
        expected = expected.strip().lower()
        if len(expected) != 64 or any(c not in "0123456789abcdef" for c in expected):
            raise InvalidInput("Upload-Metadata: sha256 must be 64 hex digits")
    filename = check_filename(metadata.get("filename") or None)
    reserve_upload(session, settings, storage, tenant_id, length)  # refused here: nothing stored yet
    upload_id = uuid.uuid4()
    key = storage.upload_key(upload_id)
    try:
        multipart = storage.begin_upload(upload_id)
        upload = Upload(
            id=upload_id,
            api_key_id=tenant_id,
            filename=filename,
            length=length,
            offset=0,
            expected_sha256=expected,
            path=key,
            multipart=multipart,
        )
        session.add(upload)
        session.commit()
    except BaseException:
        # The row was not made (database refused or away): its empty file must not outlive it.
        session.rollback()
        storage.delete_prefix(upload_folder(key))
        raise
    return upload


def check_filename(filename: str | None) -> str | None:
    """The ``filename`` of ``Upload-Metadata``: printable, and short enough to be the scene's name (422 otherwise,
    before any byte is sent)."""
    if filename is None:
        return None
    printable_text(filename, "Upload-Metadata: filename")
    if len(filename) > MAX_FILENAME_CHARS:
        raise InvalidInput(
            f"Upload-Metadata: filename has {len(filename)} characters; at most {MAX_FILENAME_CHARS} (it names the "
            "scene)"
        )
    return filename


def has_body(request: Request) -> bool:
    """True when the request carries a body (Content-Length > 0 or chunked)."""
    length = request.headers.get("content-length")
    if length is not None:
        return length.strip() not in ("", "0")
    return "chunked" in request.headers.get("transfer-encoding", "").lower()


def check_content_type(request: Request) -> None:
    """tus bodies are ``application/offset+octet-stream``."""
    if request.headers.get("content-type", "").split(";")[0].strip().lower() != OCTET:
        raise UnsupportedMediaType(f"the body must be sent as Content-Type: {OCTET}")


class ActiveUploads:
    """Upload ids with a write in progress in this process (one writer per upload)."""

    def __init__(self) -> None:
        self._ids: set[uuid.UUID] = set()

    def acquire(self, upload_id: uuid.UUID) -> None:
        """Mark ``upload_id`` busy, or refuse."""
        if upload_id in self._ids:
            raise Conflict(f"upload {upload_id}: another request is writing to it")
        self._ids.add(upload_id)

    def release(self, upload_id: uuid.UUID) -> None:
        """Mark ``upload_id`` free."""
        self._ids.discard(upload_id)


async def receive_body(
    request: Request, upload: Upload, storage: Storage, hashes: HashStates, checksum: tuple[str, bytes] | None
) -> tuple[int, Any, dict[str, Any] | None] | None:
    """Stream the request body to the upload's file at its offset; returns (new offset, running SHA-256, the
    multipart state at the new offset for the row: None with the local backend).

    None when the client disconnected during a chunk that carried a checksum (the chunk is discarded).
    """
    declared = request.headers.get("content-length")
    if declared is not None and declared.strip().isdigit() and upload.offset + int(declared) > upload.length:
        raise PayloadTooLarge(
            f"the body ({declared} bytes at offset {upload.offset}) goes past Upload-Length {upload.length}"
        )
    algo = checksum[0] if checksum else None
    writer = await anyio.to_thread.run_sync(
        storage.upload_writer, upload.path, upload.id, upload.offset, upload.multipart, hashes, algo
    )
    buffer = bytearray()
    try:
        async for chunk in request.stream():
            if writer.offset + len(buffer) + len(chunk) > upload.length:
                raise PayloadTooLarge(f"the body goes past Upload-Length {upload.length}")
            buffer += chunk
            if len(buffer) >= BLOCK:
                data, buffer = buffer, bytearray()
                await anyio.to_thread.run_sync(writer.write, data)
        if buffer:
            await anyio.to_thread.run_sync(writer.write, buffer)
    except ClientDisconnect:
        if checksum is not None:  # a partial chunk cannot be verified: keep nothing of it
            await anyio.to_thread.run_sync(_discard, writer, hashes, upload.id)
            return None
        if buffer:
            await anyio.to_thread.run_sync(writer.write, buffer)
    except (ServiceError, OSError, StorageError) as exc:
        await anyio.to_thread.run_sync(_discard, writer, hashes, upload.id)
        if isinstance(exc, OSError) and exc.errno in DISK_FULL:
            raise InsufficientStorage(
                f"the storage volume filled up while upload {upload.id} was written; the chunk was discarded, the "
                f"upload resumes at offset {upload.offset:,}: retry later or ask the operator to free space"
            ) from None
        raise
    if checksum is not None and writer.chunk_hash is not None and writer.chunk_hash.digest() != checksum[1]:
        await anyio.to_thread.run_sync(_discard, writer, hashes, upload.id)
        raise ChecksumMismatch("Upload-Checksum does not match the bytes received; the chunk was discarded")
    offset = await anyio.to_thread.run_sync(writer.close)
    running, multipart = await anyio.to_thread.run_sync(writer.settle, upload.length)
    if running is not None:
        hashes.put(upload.id, offset, running)
    return offset, running, multipart


def _discard(writer: UploadWriter, hashes: HashStates, upload_id: uuid.UUID) -> None:
    writer.rollback()
    hashes.drop(upload_id)


def record_bytes(
    session: Session,
    storage: Storage,
    hashes: HashStates,
    upload: Upload,
    new_offset: int,
    running: Any,
    multipart: dict[str, Any] | None = None,
) -> Upload:
    """Move the offset in the database (and the multipart state with it); complete (and verify) the upload when the
    last byte is in."""
    moved = {} if multipart is None else {"multipart": multipart}
    if new_offset != upload.offset and not crud.advance_upload(session, upload.id, upload.offset, new_offset, **moved):
        raise Conflict(f"upload {upload.id}: the offset moved while this request was writing; HEAD and retry")
    session.refresh(upload)
    if upload.offset < upload.length or upload.state != UploadState.RECEIVING:
        return upload
    digest = running.hexdigest()
    hashes.drop(upload.id)
    if upload.expected_sha256 is not None and upload.expected_sha256 != digest:
        discard_upload(session, storage, upload)
        raise ChecksumMismatch(
            f"the upload's SHA-256 is {digest}, Upload-Metadata said {upload.expected_sha256}; it was discarded"
        )
    upload.sha256 = digest
    upload.state = UploadState.COMPLETE
    upload.completed_at = utcnow()
    session.commit()
    storage.upload_complete(upload.path)
    return upload


def discard_upload(session: Session, storage: Storage, upload: Upload) -> None:
    """Delete an upload's bytes (and its unfinished multipart parts) and row."""
    storage.delete_prefix(upload_folder(upload.path))
    crud.delete_upload(session, upload.id)
