"""Database errors are answered by what they mean, with real driver errors on SQLite and PostgreSQL: integrity
errors are the client's 409 or 422, an outage is a 503 with Retry-After, anything else is a 500 whose traceback is
in the server log (never a retryable 503 that hides a bug)."""

from __future__ import annotations

import logging
import secrets
import sqlite3
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from service_harness import free_port
from sqlalchemy import Engine, create_engine, text

from service.db.session import get_engine
from service.errors import install_error_handlers

ERRORS_LOGGER = "service.errors"


def answer(engine: Engine, *statements: str) -> httpx.Response:
    """The response of a route that runs ``statements`` in one transaction on ``engine``."""
    app = FastAPI()
    install_error_handlers(app)

    @app.post("/run")
    def run() -> dict[str, str]:
        with engine.begin() as conn:
            for statement in statements:
                conn.execute(text(statement))
        return {"status": "ok"}

    with TestClient(app, raise_server_exceptions=False) as client:
        return client.post("/run")


class Tables:
    """A parent table with a unique name, a NOT NULL and a CHECK rule, and a child that refers to it."""

    def __init__(self, engine: Engine) -> None:
        self.engine = engine
        suffix = secrets.token_hex(3)
        self.parent, self.child = f"errtest_parent_{suffix}", f"errtest_child_{suffix}"

    def create(self) -> None:
        with self.engine.begin() as conn:
            conn.execute(text(f"CREATE TABLE {self.parent} (id INTEGER PRIMARY KEY, name TEXT NOT NULL UNIQUE, "
                              f"size INTEGER CHECK (size >= 0))"))  # fmt: skip
            conn.execute(text(f"CREATE TABLE {self.child} (id INTEGER PRIMARY KEY, "
                              f"parent_id INTEGER NOT NULL REFERENCES {self.parent}(id))"))  # fmt: skip
            conn.execute(text(f"INSERT INTO {self.parent} (id, name, size) VALUES (1, 'a', 1)"))

    def drop(self) -> None:
        with self.engine.begin() as conn:
            conn.execute(text(f"DROP TABLE {self.child}"))
            conn.execute(text(f"DROP TABLE {self.parent}"))


@pytest.fixture(params=["sqlite", "postgres"])
def tables(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[Tables]:
    url = f"sqlite:///{tmp_path / 'errors.db'}" if request.param == "sqlite" else request.getfixturevalue("pg_url")
    made = Tables(get_engine(url))  # the service's engine: SQLite enforces foreign keys there
    made.create()
    yield made
    made.drop()


def test_duplicate_is_a_conflict(tables: Tables) -> None:
    response = answer(tables.engine, f"INSERT INTO {tables.parent} (id, name) VALUES (2, 'a')")
    assert response.status_code == 409
    assert response.json()["type"] == "conflict"
    assert "already exists" in response.json()["message"]
    assert "Retry-After" not in response.headers


def test_missing_reference_is_a_conflict(tables: Tables) -> None:
    response = answer(tables.engine, f"INSERT INTO {tables.child} (id, parent_id) VALUES (1, 999)")
    assert response.status_code == 409
    assert "no longer exists" in response.json()["message"]


@pytest.mark.parametrize(
    "values", ["(2, NULL, 1)", "(2, 'b', -1)"], ids=["not-null", "check"]
)  # fmt: skip
def test_refused_value_is_invalid_input(tables: Tables, values: str) -> None:
    response = answer(tables.engine, f"INSERT INTO {tables.parent} (id, name, size) VALUES {values}")
    assert response.status_code == 422
    assert response.json()["type"] == "invalid_input"


def test_a_bug_is_a_500_with_its_traceback_in_the_log(tables: Tables, caplog: pytest.LogCaptureFixture) -> None:
    # A missing table: SQLite reports it as an OperationalError, like an outage; it must not be answered as one.
    with caplog.at_level(logging.ERROR, logger=ERRORS_LOGGER):
        response = answer(tables.engine, "SELECT * FROM no_such_table_anywhere")
    assert response.status_code == 500
    body = response.json()
    assert body["type"] == "internal_error"
    assert "no_such_table" not in body["message"], "no SQL leaves the server"
    logged = [r for r in caplog.records if r.name == ERRORS_LOGGER and r.exc_info]
    assert logged, "the error was logged with its traceback"
    assert "no_such_table_anywhere" in caplog.text


def test_unreachable_postgres_is_an_outage(caplog: pytest.LogCaptureFixture) -> None:
    closed = f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/postgres"
    engine = create_engine(closed, connect_args={"connect_timeout": 2})
    with caplog.at_level(logging.WARNING, logger=ERRORS_LOGGER):
        response = answer(engine, "SELECT 1")
    assert response.status_code == 503
    assert response.json()["type"] == "service_unavailable"
    assert response.headers["Retry-After"] == "2"
    assert not [r for r in caplog.records if r.exc_info], "an outage is expected: one line, no traceback"


def test_locked_sqlite_is_an_outage(tmp_path: Path) -> None:
    path = tmp_path / "locked.db"
    holder = sqlite3.connect(path, isolation_level=None)
    holder.execute("CREATE TABLE t (x INTEGER)")
    holder.execute("BEGIN EXCLUSIVE")  # another writer holds the file
    try:
        impatient = create_engine(f"sqlite:///{path}", connect_args={"timeout": 0})
        response = answer(impatient, "INSERT INTO t VALUES (1)")
    finally:
        holder.execute("ROLLBACK")
        holder.close()
    assert response.status_code == 503
    assert response.headers["Retry-After"] == "2"


def test_exhausted_pool_is_an_outage(tmp_path: Path) -> None:
    engine = create_engine(f"sqlite:///{tmp_path / 'pool.db'}", pool_size=1, max_overflow=0, pool_timeout=0.1)
    with engine.connect():  # the pool's only connection is busy
        response = answer(engine, "SELECT 1")
    assert response.status_code == 503


def test_a_value_the_database_cannot_hold_is_invalid_input(tables: Tables) -> None:
    # PostgreSQL refuses an integer out of its column's range with a DataError (SQLSTATE 22003); SQLite stores it.
    if tables.engine.dialect.name != "postgresql":
        pytest.skip("SQLite holds any integer")
    response = answer(tables.engine, f"INSERT INTO {tables.parent} (id, name, size) VALUES (2, 'b', 99999999999)")
    assert response.status_code == 422
    assert response.json()["type"] == "invalid_input"
