"""Engines and sessions. One sync style everywhere: the API's ``def`` routes and the worker share this
module."""

from __future__ import annotations

import functools
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

SQLITE_BUSY_TIMEOUT_MS = 30_000  # the API and the worker write to one SQLite file; wait rather than fail


def _sqlite_pragmas(dbapi_connection: Any, _record: Any) -> None:
    cursor = dbapi_connection.cursor()
    cursor.execute("PRAGMA journal_mode=WAL")  # readers do not block the writer
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.close()


@functools.cache
def get_engine(url: str) -> Engine:
    """One engine per database URL per process."""
    if url.startswith("sqlite"):
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})
        event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    # No pre-ping (a round trip per checkout): a connection broken by a database restart fails one request with
    # 503 and SQLAlchemy then invalidates the whole pool; the worker retries (worker.leased.with_db_retry).
    return create_engine(url, pool_size=10, max_overflow=20, pool_timeout=10, pool_recycle=1800)


@functools.cache
def get_read_engine(url: str) -> Engine:
    """The engine of ``url`` in autocommit mode, for single-statement reads: no BEGIN/ROLLBACK round trips."""
    return get_engine(url).execution_options(isolation_level="AUTOCOMMIT")


@functools.cache
def get_session_factory(url: str) -> sessionmaker[Session]:
    """A session factory bound to the engine of ``url``."""
    return sessionmaker(get_engine(url), expire_on_commit=False)


@contextmanager
def session_scope(factory: sessionmaker[Session]) -> Iterator[Session]:
    """A session that rolls back on error and always closes."""
    session = factory()
    try:
        yield session
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()
