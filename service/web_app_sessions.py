"""The web app's sign-in: an API key is exchanged once for a random session token, kept by the browser in an HttpOnly,
SameSite=Strict cookie. The long-lived key never travels again (not in URLs, not in logs, not in page storage).

Only SHA-256(token) is stored (``app_session``); a session ends at its expiry, at sign-out, or when its key is
revoked. A cookie-authenticated request that changes something must carry ``X-Panogs-App`` (a header a cross-site
form cannot set), on top of SameSite.
"""

from __future__ import annotations

import hashlib
import secrets
import uuid
from datetime import timedelta

from sqlalchemy import delete, select
from sqlalchemy.orm import Session

from service.auth import Tenant
from service.db.base import utcnow
from service.db.models import ApiKey, AppSession

COOKIE_NAME = "panogs_session"
APP_HEADER = "X-Panogs-App"
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})


def _hash(token: str) -> str:
    return hashlib.sha256(token.encode()).hexdigest()


def open_session(session: Session, api_key_id: uuid.UUID, ttl_s: int) -> tuple[str, AppSession]:
    """A new session of ``api_key_id``; returns the token (for the cookie; never stored) and the row."""
    token = secrets.token_urlsafe(32)
    now = utcnow()
    row = AppSession(api_key_id=api_key_id, token_hash=_hash(token), expires_at=now + timedelta(seconds=ttl_s))
    session.add(row)
    # Expired sessions of this key go now: sign-ins never pile up rows.
    session.execute(delete(AppSession).where(AppSession.api_key_id == api_key_id, AppSession.expires_at < now))
    session.commit()
    return token, row


def session_tenant(session: Session, token: str) -> tuple[Tenant, AppSession] | None:
    """The tenant and session of a live ``token``; None when unknown, expired or its key revoked."""
    row = session.execute(
        select(AppSession, ApiKey)
        .join(ApiKey, ApiKey.id == AppSession.api_key_id)
        .where(AppSession.token_hash == _hash(token))
    ).first()
    if row is None:
        return None
    app_session, key = row
    if key.revoked_at is not None or app_session.expires_at <= utcnow():
        return None
    return Tenant(id=key.id, name=key.name), app_session


def close_session(session: Session, token: str) -> None:
    """Sign out: delete the session (nothing to do when it is already gone)."""
    session.execute(delete(AppSession).where(AppSession.token_hash == _hash(token)))
    session.commit()
