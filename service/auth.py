"""API keys: each key is a tenant. Keys look like ``pgs_<prefix>_<secret>``; only SHA-256(key) is stored.

The secret has 256 bits of entropy, so a fast hash is enough (no password stretching needed); the prefix finds
the row and the hash is compared in constant time. Answers are cached per process for
``api_key_cache_s`` seconds, which bounds how long a revoked key keeps working on an API process that has just
seen it.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import uuid
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from service.cache import TTLCache
from service.db.base import utcnow
from service.db.models import ApiKey

KEY_PATTERN = re.compile(r"^pgs_([0-9a-f]{12})_([A-Za-z0-9_-]{43})$")


@dataclass(frozen=True)
class Tenant:
    """The caller, as the routes see it."""

    id: uuid.UUID
    name: str


def hash_key(key: str) -> str:
    """Hex SHA-256 of the full key text."""
    return hashlib.sha256(key.encode()).hexdigest()


def generate_key() -> tuple[str, str]:
    """A new key and its prefix."""
    prefix = secrets.token_hex(6)
    return f"pgs_{prefix}_{secrets.token_urlsafe(32)}", prefix


def create_api_key(session: Session, name: str) -> tuple[ApiKey, str]:
    """Store a new key; returns the row and the plaintext key, which is shown once and never stored."""
    key, prefix = generate_key()
    row = ApiKey(name=name, prefix=prefix, key_hash=hash_key(key))
    session.add(row)
    session.commit()
    return row, key


def list_api_keys(session: Session) -> list[ApiKey]:
    """Every key, oldest first."""
    return list(session.scalars(select(ApiKey).order_by(ApiKey.created_at)))


def key_prefix(ident: str) -> str:
    """The listed prefix of ``ident``: itself, or the hex part of ``pgs_<prefix>`` and of a whole key."""
    match = re.match(r"^pgs_([0-9a-f]{12})(?:_|$)", ident.strip())
    return match.group(1) if match else ident.strip()


def revoke_api_key(session: Session, ident: str) -> ApiKey | None:
    """Revoke the key whose id or prefix is ``ident``; None when there is none.

    The prefix may be given as listed (``0123abcd4567``), as it starts the key (``pgs_0123abcd4567``), or as the
    whole key: a person copies whichever they have at hand.
    """
    try:
        row = session.get(ApiKey, uuid.UUID(ident))
    except ValueError:
        row = session.scalar(select(ApiKey).where(ApiKey.prefix == key_prefix(ident)))
    if row is None:
        return None
    if row.revoked_at is None:
        row.revoked_at = utcnow()
        session.commit()
    return row


class KeyVerifier:
    """Checks bearer keys against the database, remembering answers for ``ttl_s`` seconds."""

    def __init__(self, ttl_s: float) -> None:
        self._cache: TTLCache[str, Tenant | None] = TTLCache(ttl_s)

    def cached(self, key: str) -> tuple[bool, Tenant | None]:
        """(True, tenant or None) when the answer for ``key`` is known without the database."""
        if KEY_PATTERN.match(key) is None:
            return True, None
        return self._cache.get(hash_key(key))

    def verify(self, session: Session, key: str) -> Tenant | None:
        """The tenant of ``key``, or None when the key is malformed, unknown or revoked."""
        known, tenant = self.cached(key)
        if known:
            return tenant
        match = KEY_PATTERN.match(key)
        assert match is not None  # cached() answers for malformed keys
        digest = hash_key(key)
        row = session.scalar(select(ApiKey).where(ApiKey.prefix == match.group(1)))
        if row is not None and row.revoked_at is None and hmac.compare_digest(row.key_hash, digest):
            tenant = Tenant(id=row.id, name=row.name)
        self._cache.put(digest, tenant)
        return tenant
