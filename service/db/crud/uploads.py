"""Upload rows: the offset moved only by the writer that read it, the state moved only from the state it was in."""

from __future__ import annotations

import uuid
from datetime import datetime
from typing import Any

from sqlalchemy import delete, select, update
from sqlalchemy.orm import Session

from service.db.base import utcnow
from service.db.leases import one_row
from service.db.models import Upload, UploadState


def advance_upload(session: Session, upload_id: uuid.UUID, old_offset: int, new_offset: int, **values: Any) -> bool:
    """Move an upload's offset forward (with ``values``: its multipart state), only if nobody else moved it
    meanwhile."""
    result = session.execute(
        update(Upload)
        .where(Upload.id == upload_id, Upload.offset == old_offset)
        .values(offset=new_offset, updated_at=utcnow(), **values)
    )
    session.commit()
    return one_row(result)


def stale_uploads(session: Session, older_than: datetime) -> list[Upload]:
    """Uploads not made into a scene and untouched since ``older_than``."""
    live = [UploadState.RECEIVING, UploadState.COMPLETE]
    stmt = select(Upload).where(Upload.state.in_(live), Upload.updated_at < older_than)
    return list(session.scalars(stmt.limit(100)))


def set_upload_state(session: Session, upload_id: uuid.UUID, old: UploadState, new: UploadState) -> bool:
    """Move an upload from ``old`` to ``new``; False when it was not in ``old`` (someone else moved it)."""
    result = session.execute(
        update(Upload).where(Upload.id == upload_id, Upload.state == old).values(state=new, updated_at=utcnow())
    )
    session.commit()
    return one_row(result)


def delete_upload(session: Session, upload_id: uuid.UUID) -> None:
    """Delete an upload's row (its bytes are the caller's to remove)."""
    session.execute(delete(Upload).where(Upload.id == upload_id))
    session.commit()
