"""Helpers for tests and benchmarks of the service: throwaway PostgreSQL databases and Redis key prefixes.

Each test session gets its own database (``panogs_test_<random>``) and its own Redis key prefix, so that it
never touches anyone else's data on a shared server, and removes them when it ends.
"""

from __future__ import annotations

import secrets
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import create_engine, make_url, text

DEFAULT_PG_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"
DEFAULT_REDIS_URL = "redis://127.0.0.1:6379/0"


@contextmanager
def temp_postgres(admin_url: str = DEFAULT_PG_ADMIN_URL) -> Iterator[str]:
    """Create an empty database next to ``admin_url``'s, yield its URL, drop it afterwards."""
    name = f"panogs_test_{secrets.token_hex(4)}"
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    with admin.connect() as conn:
        conn.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield make_url(admin_url).set(database=name).render_as_string(hide_password=False)
    finally:
        from service.db.session import get_engine

        get_engine.cache_clear()
        with admin.connect() as conn:
            conn.execute(text(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)'))
        admin.dispose()


def postgres_reachable(admin_url: str = DEFAULT_PG_ADMIN_URL) -> bool:
    """True when PostgreSQL answers at ``admin_url``."""
    engine = create_engine(admin_url, connect_args={"connect_timeout": 2})
    try:
        with engine.connect() as conn:
            conn.execute(text("SELECT 1"))
        return True
    except Exception:  # any failure means not reachable
        return False
    finally:
        engine.dispose()


def new_redis_prefix() -> str:
    """A Redis key prefix of our own (kombu ``global_keyprefix``)."""
    return f"panogs_test_{secrets.token_hex(4)}:"


def drop_redis_prefix(url: str, prefix: str) -> int:
    """Delete every key under ``prefix``; returns how many."""
    import redis

    client = redis.Redis.from_url(url)
    try:
        keys = list(client.scan_iter(match=f"{prefix}*", count=500))
        if keys:
            client.delete(*keys)
        return len(keys)
    finally:
        client.close()


def redis_reachable(url: str = DEFAULT_REDIS_URL) -> bool:
    """True when Redis answers at ``url``."""
    import redis

    client = redis.Redis.from_url(url, socket_connect_timeout=2)
    try:
        return bool(client.ping())
    except Exception:  # any failure means not reachable
        return False
    finally:
        client.close()
