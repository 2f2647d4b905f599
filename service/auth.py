"""API keys: each key is a tenant. Keys look like ``pgs_<prefix>_<secret>``; only SHA-256(key) is stored.

The secret has 256 bits of entropy, so a fast hash is enough (no password stretching needed); the prefix finds
the row and the hash is compared in constant time. Lookups are cached per process for ``api_key_cache_s``
seconds, which bounds how long a revoked key keeps working on an API process that has just seen it.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
import time
import uuid
from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

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


def revoke_api_key(session: Session, ident: str) -> ApiKey | None:
    """Revoke the key whose id or prefix is ``ident``; None when there is none."""
    try:
        row = session.get(ApiKey, uuid.UUID(ident))
    except ValueError:
        row = session.scalar(select(ApiKey).where(ApiKey.prefix == ident))
    if row is None:
        return None
    if row.revoked_at is None:
        row.revoked_at = utcnow()
        session.commit()
    return row


class KeyVerifier:
    """Checks bearer keys against the database with a short per-process cache."""

    def __init__(self, ttl_s: float) -> None:
        self._ttl_s = ttl_s
        self._cache: dict[str, tuple[float, Tenant | None]] = {}
        self._lock = threading.Lock()

    def cached(self, key: str) -> tuple[bool, Tenant | None]:
        """(True, tenant or None) when the answer for ``key`` is known without the database."""
        if KEY_PATTERN.match(key) is None:
            return True, None
        with self._lock:
            hit = self._cache.get(hash_key(key))
        if hit is not None and hit[0] > time.monotonic():
            return True, hit[1]
        return False, None

    def verify(self, session: Session, key: str) -> Tenant | None:
        """The tenant of ``key``, or None when the key is malformed, unknown or revoked."""
        known, tenant = self.cached(key)
        if known:
            return tenant
        match = KEY_PATTERN.match(key)
        assert match is not None  # cached() answers for malformed keys
        digest = hash_key(key)
        now = time.monotonic()
        row = session.scalar(select(ApiKey).where(ApiKey.prefix == match.group(1)))
        tenant = None
        if row is not None and row.revoked_at is None and hmac.compare_digest(row.key_hash, digest):
            tenant = Tenant(id=row.id, name=row.name)
        if self._ttl_s > 0:
            with self._lock:
                if len(self._cache) > 10_000:  # bounded: forget everything rather than grow
                    self._cache.clear()
                self._cache[digest] = (now + self._ttl_s, tenant)
        return tenant
