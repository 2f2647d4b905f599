"""Fixtures of the service tests: a real PostgreSQL database (and the embedded SQLite), the app, API keys,
bundles.

URLs come from the environment with local defaults: ``PANOGS_TEST_PG_ADMIN_URL`` (a database this user may
create databases from) and ``PANOGS_TEST_REDIS_URL``. Each session creates its own database and Redis key
prefix and removes them at the end. An unreachable PostgreSQL or Redis skips the tests that need it, except
under CI (``CI=true``), where it fails them with the command that starts it.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient
from pipeline_stand_in import use
from seaweedfs import SeaweedFS, seaweedfs
from service_harness import (
    PG_ADMIN_URL,
    REDIS_URL,
    SCRIPTED_PIPELINE,
    drop_redis_prefix,
    new_redis_prefix,
    require_postgres,
    require_redis,
    temp_postgres,
)
from sqlalchemy import text
from svc_helpers import RecordingSender, new_key, pack, write_tiny_bundle

from service.api_app import create_app
from service.db.migrate import upgrade
from service.db.models import Base
from service.db.session import get_engine
from service.settings import Settings

# Children first: a DELETE per table, which on the few rows a test leaves takes under 1 ms where TRUNCATE took
# 18 (it rewrites every table's files), before each of the ~160 PostgreSQL tests.
TABLES = ("artifact", "job_tile", "job", "scene", "upload", "app_session", "api_key")


@pytest.fixture(scope="session")
def pg_url() -> Iterator[str]:
    """A migrated PostgreSQL database of this session."""
    assert set(TABLES) == set(Base.metadata.tables), "TABLES must name every table, children first"
    require_postgres(PG_ADMIN_URL)
    with temp_postgres(PG_ADMIN_URL) as url:
        upgrade(url)
        yield url


@pytest.fixture(scope="session")
def redis_prefix() -> Iterator[str]:
    """A Redis key prefix of this session (its keys are deleted at the end)."""
    require_redis(REDIS_URL)
    prefix = new_redis_prefix()
    yield prefix
    drop_redis_prefix(REDIS_URL, prefix)


@pytest.fixture(scope="session")
def seaweedfs_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SeaweedFS]:
    """A SeaweedFS S3 server of this session (``weed mini`` on free ports, data under tmp), stopped at the end."""
    with seaweedfs(tmp_path_factory.mktemp("seaweedfs")) as server:
        yield server


@pytest.fixture(scope="session")
def sqlite_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A migrated SQLite file, copied for each test that uses the embedded database."""
    path = tmp_path_factory.mktemp("template") / "panogs.db"
    upgrade(f"sqlite:///{path}")
    get_engine.cache_clear()
    return path


def _clean_postgres(url: str) -> None:
    with get_engine(url).begin() as conn:
        for table in TABLES:
            conn.execute(text(f"DELETE FROM {table}"))


@pytest.fixture
def make_settings(
    tmp_path: Path, sqlite_template: Path, request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch
) -> Callable[..., Settings]:
    """Settings for a backend, with everything on disk under this test's tmp_path; jobs' configs are those of the
    scripted pipeline (API tests run no pipeline) unless ``stand_in=None`` keeps the core's."""

    def make(backend: str = "postgres", *, stand_in: str | None = SCRIPTED_PIPELINE, **overrides: Any) -> Settings:
        if stand_in is not None:
            use(monkeypatch, stand_in)
        values: dict[str, Any] = {
            "data_dir": tmp_path / "data",
            "heartbeat_timeout_s": 30,
            "api_key_cache_s": 0,
            "status_cache_s": 0,
        }
        if backend == "postgres":
            url = request.getfixturevalue("pg_url")
            _clean_postgres(url)
            values["database_url"] = url
        else:
            (tmp_path / "data").mkdir(exist_ok=True)
            shutil.copy(sqlite_template, tmp_path / "data" / "panogs.db")
        values.update(overrides)
        return Settings(_env_file=None, **values)  # type: ignore[call-arg]

    return make


@pytest.fixture
def settings(make_settings: Callable[..., Settings], request: pytest.FixtureRequest) -> Settings:
    """PostgreSQL settings by default; ``BOTH_BACKENDS`` runs a test on the embedded SQLite as well."""
    return make_settings(getattr(request, "param", "postgres"))


@pytest.fixture
def sender() -> RecordingSender:
    return RecordingSender()


@pytest.fixture
def client(settings: Settings, sender: RecordingSender) -> Iterator[TestClient]:
    app = create_app(settings, sender=sender, run_reaper=False)
    with TestClient(app) as c:
        yield c


@pytest.fixture
def auth(settings: Settings) -> dict[str, str]:
    return new_key(settings, "alice")


@pytest.fixture
def other_auth(settings: Settings) -> dict[str, str]:
    return new_key(settings, "mallory")


@pytest.fixture
def tiny_zip(tmp_path: Path) -> bytes:
    return pack(write_tiny_bundle(tmp_path / "bundle"))
