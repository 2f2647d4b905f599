"""``/v1/uploads``: resumable bundle uploads (tus 1.0; see :mod:`service.uploads`)."""

from __future__ import annotations

import hashlib
import uuid
from typing import Annotated, Any

from fastapi import APIRouter, Header, Request, Response, status
from fastapi.concurrency import run_in_threadpool
from sqlalchemy.orm import Session, sessionmaker

from service import uploads as up
from service.api.deps import FactoryDep, SessionDep, SettingsDep, StorageDep, TenantDep, UploadDep
from service.auth import Tenant
from service.db import crud
from service.db.models import Upload, UploadState
from service.db.session import session_scope
from service.errors import Conflict, NotFound, PayloadTooLarge, ServiceError
from service.lifecycle import check_upload_room
from service.schemas import UploadPublic, error_responses
from service.settings import Settings
from service.storage import Storage

router = APIRouter(prefix="/uploads", tags=["uploads"])

_BODY = {
    "requestBody": {
        "required": False,
        "content": {up.OCTET: {"schema": {"type": "string", "format": "binary"}}},
    }
}
_ERRORS = error_responses(404, 409, 412, 413, 415, 460, 507)
TusVersion = Annotated[
    str | None, Header(alias="Tus-Resumable", description="1.0.0", json_schema_extra={"enum": ["1.0.0"]})
]
# sha256 and the base64 of 32 bytes; the digest itself is compared with the bytes received (460 when it differs).
CHECKSUM_SCHEMA = {"pattern": r"^sha256 [A-Za-z0-9+/]{43}=$"}


@router.options("", include_in_schema=False)
def discover(settings: SettingsDep) -> Response:
    """tus discovery: version, extensions, size limit and checksum algorithms."""
    headers = up.tus_headers(
        Tus_Version=up.TUS_VERSION,
        Tus_Extension=up.TUS_EXTENSIONS,
        Tus_Max_Size=settings.max_upload_bytes,
        Tus_Checksum_Algorithm=up.TUS_CHECKSUMS,
    )
    return Response(status_code=status.HTTP_204_NO_CONTENT, headers=headers)


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=UploadPublic,
    openapi_extra=_BODY,
    responses=_ERRORS,
)
async def create_upload(
    request: Request,
    tenant: TenantDep,
    settings: SettingsDep,
    storage: StorageDep,
    factory: FactoryDep,
    upload_length: Annotated[int, Header(alias="Upload-Length", ge=0, description="total bytes")],
    upload_metadata: Annotated[str | None, Header(alias="Upload-Metadata")] = None,
    upload_checksum: Annotated[
        str | None, Header(alias="Upload-Checksum", description="sha256 <base64>", json_schema_extra=CHECKSUM_SCHEMA)
    ] = None,
    tus_resumable: TusVersion = None,
) -> Response:
    """Start an upload of ``Upload-Length`` bytes; the body may carry the first bytes (or all of them).

    ``Upload-Metadata`` may hold ``filename`` and ``sha256`` (hex SHA-256 of the whole file, verified at the
    end), each base64-encoded as tus requires.
    """
    up.check_tus_version(tus_resumable)
    metadata = up.parse_metadata(upload_metadata)
    checksum = up.parse_checksum(upload_checksum)
    with_body = up.has_body(request)
    if with_body:
        up.check_content_type(request)
        declared = request.headers.get("content-length", "").strip()
        if declared.isdigit() and int(declared) > upload_length:
            # Refused before anything is stored: no upload without an id in the answer is left behind.
            raise PayloadTooLarge(f"the body ({declared} bytes) goes past Upload-Length {upload_length}")
    upload = await run_in_threadpool(
        _in_session, factory, _create_within_quota, settings, storage, tenant.id, upload_length, metadata
    )
    if with_body:
        try:
            upload = await _write(request, factory, storage, upload, checksum)
        except ServiceError:
            # The client never learns this upload's id from an error: delete it rather than leave it on disk.
            await run_in_threadpool(_in_session, factory, _discard_by_id, storage, upload.id)
            raise
    elif upload.length == 0:
        upload = await run_in_threadpool(_record, factory, request, storage, upload, 0, hashlib.sha256(), None)
    body = UploadPublic.model_validate(upload).model_dump_json()
    headers = up.tus_headers(Location=f"/v1/uploads/{upload.id}", Upload_Offset=upload.offset)
    return Response(body, status_code=201, headers=headers, media_type="application/json")


@router.head("/{upload_id}", responses=_ERRORS)
def upload_offset(upload: UploadDep) -> Response:
    """How many bytes arrived (``Upload-Offset``) of ``Upload-Length``: where to resume."""
    headers = up.tus_headers(Upload_Offset=upload.offset, Upload_Length=upload.length)
    return Response(status_code=200, headers=headers)


@router.get("/{upload_id}", response_model=UploadPublic, responses=_ERRORS)
def get_upload(upload: UploadDep) -> Upload:
    """An upload's progress, state and checksum."""
    return upload


@router.patch("/{upload_id}", status_code=status.HTTP_204_NO_CONTENT, openapi_extra=_BODY, responses=_ERRORS)
async def append(
    upload_id: uuid.UUID,
    request: Request,
    tenant: TenantDep,
    settings: SettingsDep,
    storage: StorageDep,
    factory: FactoryDep,
    upload_offset: Annotated[int, Header(alias="Upload-Offset", ge=0, description="must equal the current offset")],
    upload_checksum: Annotated[
        str | None, Header(alias="Upload-Checksum", description="sha256 <base64>", json_schema_extra=CHECKSUM_SCHEMA)
    ] = None,
    tus_resumable: TusVersion = None,
) -> Response:
    """Append the body at ``Upload-Offset`` (which must be the offset the server has).

    The bytes the upload still needs (Upload-Length less what arrived) must fit on the disk (507) and the tenant
    must still be within its storage quota (413), checked before a byte is written.
    """
    up.check_tus_version(tus_resumable)
    checksum = up.parse_checksum(upload_checksum)
    up.check_content_type(request)
    upload = await run_in_threadpool(_owned_upload, factory, upload_id, tenant)
    if upload.offset != upload_offset:
        raise Conflict(f"Upload-Offset {upload_offset} does not match the server's offset {upload.offset}")
    if upload.state != UploadState.RECEIVING:
        raise Conflict(f"upload {upload.id} is {upload.state.value}; it takes no more bytes")
    await run_in_threadpool(_in_session, factory, check_upload_room, settings, storage, upload)
    upload = await _write(request, factory, storage, upload, checksum)
    return Response(status_code=204, headers=up.tus_headers(Upload_Offset=upload.offset))


@router.delete("/{upload_id}", status_code=status.HTTP_204_NO_CONTENT, responses=_ERRORS)
def delete_upload(upload: UploadDep, session: SessionDep, storage: StorageDep) -> Response:
    """Abandon an upload and delete its bytes (tus termination)."""
    up.discard_upload(session, storage, upload)
    return Response(status_code=204, headers=up.tus_headers())


def _create_within_quota(
    session: Session,
    settings: Settings,
    storage: Storage,
    tenant_id: uuid.UUID,
    length: int,
    metadata: dict[str, str],
) -> Upload:
    # The size limit first (it is what the client must change), then the quota and the disk under the tenant's lock.
    return up.create_upload(session, settings, storage, tenant_id, length, metadata)


def _discard_by_id(session: Session, storage: Storage, upload_id: uuid.UUID) -> None:
    upload = session.get(Upload, upload_id)
    if upload is not None:
        up.discard_upload(session, storage, upload)


def _in_session(factory: sessionmaker[Session], fn: Any, *args: Any) -> Any:
    with session_scope(factory) as session:
        return fn(session, *args)


def _owned_upload(factory: sessionmaker[Session], upload_id: uuid.UUID, tenant: Tenant) -> Upload:
    with session_scope(factory) as session:
        upload = crud.get_owned(session, Upload, upload_id, tenant.id)
    if upload is None:
        raise NotFound("upload", upload_id)
    return upload


def _record(
    factory: sessionmaker[Session],
    request: Request,
    storage: Storage,
    upload: Upload,
    offset: int,
    running: Any,
    multipart: dict[str, Any] | None,
) -> Upload:
    with session_scope(factory) as session:
        upload = session.merge(upload)
        return up.record_bytes(session, storage, request.app.state.hashes, upload, offset, running, multipart)


async def _write(
    request: Request,
    factory: sessionmaker[Session],
    storage: Storage,
    upload: Upload,
    checksum: tuple[str, bytes] | None,
) -> Upload:
    active: up.ActiveUploads = request.app.state.active_uploads
    active.acquire(upload.id)
    try:
        received = await up.receive_body(request, upload, storage, request.app.state.hashes, checksum)
        if received is None:  # the client went away mid-chunk; nothing of it was kept
            return upload
        return await run_in_threadpool(_record, factory, request, storage, upload, *received)
    finally:
        active.release(upload.id)
