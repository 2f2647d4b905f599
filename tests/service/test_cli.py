"""`panogs keys create|list|revoke`, the worker command line, and the service commands inside `panogs`."""

from __future__ import annotations

from pathlib import Path

import pytest

from service import cli
from service.settings import Settings, get_settings
from worker import cli as worker_cli


@pytest.fixture
def data_dir(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    for name in ("PANOGS_DATABASE_URL", "PANOGS_BROKER_URL", "PANOGS_STORAGE_DIR"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("PANOGS_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.chdir(tmp_path)
    get_settings.cache_clear()
    yield tmp_path / "data"
    get_settings.cache_clear()


def test_keys_lifecycle(data_dir: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["keys", "create", "--name", "alice"]) == 0
    key = capsys.readouterr().out.strip()
    assert key.startswith("pgs_")
    assert (data_dir / "panogs.db").is_file()  # a fresh data folder is migrated on first use
    assert cli.main(["keys", "list"]) == 0
    listing = capsys.readouterr().out
    prefix = key.split("_")[1]
    assert prefix in listing
    assert "alice" in listing
    assert key not in listing
    assert cli.main(["keys", "revoke", prefix]) == 0
    assert "revoked" in capsys.readouterr().out
    cli.main(["keys", "list"])
    row = next(line for line in capsys.readouterr().out.splitlines() if prefix in line)
    assert " - " not in row  # the revoked column holds a time now
    assert cli.main(["keys", "revoke", "nosuchkey"]) == 1


def test_worker_argv_follows_settings(tmp_path: Path) -> None:
    settings = Settings(_env_file=None, data_dir=tmp_path, worker_queues="gpu", worker_pool="prefork")  # type: ignore[call-arg]
    argv = worker_cli.worker_argv(settings, None, "INFO")
    assert "--queues=gpu" in argv
    assert "--pool=prefork" in argv
    assert "--prefetch-multiplier=1" in argv
    assert "--queues=cpu" in worker_cli.worker_argv(settings, "cpu", "INFO")


def test_panogs_cli_has_the_service_commands() -> None:
    core_cli = pytest.importorskip("panogs_core.cli")
    parser = core_cli.build_parser()
    args = parser.parse_args(["serve", "--no-worker", "--port", "9000"])
    assert args.func is cli.cmd_serve
    assert args.port == 9000
    assert parser.parse_args(["keys", "create", "--name", "x"]).func is cli.cmd_keys_create
    assert parser.parse_args(["worker"]).func is worker_cli.cmd_worker


def test_embedded_serve_refuses_an_install_without_the_worker(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], data_dir: Path
) -> None:
    """An API-only install (no torch) cannot run the embedded worker: serve says so at once, before migrating."""
    monkeypatch.setattr(cli, "WORKER_MODULES", ("torch", "no_such_module_for_panogs"))
    assert cli.main(["serve", "--port", "1"]) == 2
    err = capsys.readouterr().err
    assert "no_such_module_for_panogs" in err
    assert "--no-worker" in err
    assert "torch" not in err.split("needs", 1)[1].split("which")[0]  # only what is missing is named
    assert not data_dir.exists(), "nothing was migrated or created"
