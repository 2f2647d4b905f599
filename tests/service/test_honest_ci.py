"""Under CI (``CI=true``) a PostgreSQL or Redis that does not answer fails the tests that need it, naming the
service and the command that starts it; on a developer's machine those tests are skipped."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from service_harness import REPO, START_POSTGRES, free_port, require_service

CLOSED_PG = f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/postgres"
PG_TEST = "tests/migrations/test_migrations.py::test_upgrade_check_downgrade_roundtrip[postgres]"


def test_unreachable_fails_under_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CI", "true")
    with pytest.raises(pytest.fail.Exception, match=r"Redis is not reachable at redis://x:1/0; start it with: go"):
        require_service("Redis", "redis://x:1/0", reachable=False, start="go")


def test_unreachable_skips_off_ci(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("CI", raising=False)
    with pytest.raises(pytest.skip.Exception, match="Redis is not reachable"):
        require_service("Redis", "redis://x:1/0", reachable=False, start="go")


def test_reachable_goes_on(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CI", "true")
    assert require_service("Redis", "redis://x:1/0", reachable=True, start="go") is None  # no skip, no fail


def _run_pg_test(ci: str | None) -> subprocess.CompletedProcess[str]:
    env = {k: v for k, v in os.environ.items() if k != "CI"}
    env["PANOGS_TEST_PG_ADMIN_URL"] = CLOSED_PG
    # The child needs none of the installed pytest plugins (hypothesis, schemathesis, dash...): loading them and
    # rewriting their modules' asserts was 2 of its 3 s.
    env["PYTEST_DISABLE_PLUGIN_AUTOLOAD"] = "1"
    if ci is not None:
        env["CI"] = ci
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", PG_TEST]
    return subprocess.run(argv, cwd=REPO, env=env, capture_output=True, text=True, timeout=300)


def test_a_ci_run_without_postgres_fails_and_says_how_to_start_it() -> None:
    done = _run_pg_test("true")
    assert done.returncode == 1, done.stdout[-3000:]
    assert "PostgreSQL is not reachable" in done.stdout
    assert START_POSTGRES in done.stdout
    assert "1 error" in done.stdout


def test_a_local_run_without_postgres_skips() -> None:
    done = _run_pg_test(None)
    assert done.returncode == 0, done.stdout[-3000:]
    assert "1 skipped" in done.stdout
