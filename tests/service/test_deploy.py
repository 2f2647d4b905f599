"""Deployment files: docker-compose.yml parses, names every service, volume and setting, and runs the commands
the end-to-end tests run; the Dockerfile builds a slim API image (no torch) and a worker image (CPU, or CUDA by a
build argument), both from constraints.txt; .env.example lists every setting. (Docker itself cannot run on these
machines: the files are checked by reading.)"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.cli import add_service_commands
from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
FIELDS = {f"PANOGS_{name.upper()}" for name in Settings.model_fields}


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return dict(yaml.safe_load((REPO / "docker-compose.yml").read_text()))


def test_services(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert {"api", "worker", "redis", "postgres"} <= set(services)
    for name in ("api", "worker", "redis", "postgres"):
        assert "healthcheck" in services[name], f"{name} has no health check"
    assert services["worker"]["depends_on"]["api"]["condition"] == "service_healthy"
    assert services["api"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert "replicas" not in services["worker"].get("deploy", {})  # --scale worker=N decides
    assert "ports" not in services["worker"]  # so that it can be scaled
    assert "/readyz" in " ".join(services["api"]["healthcheck"]["test"])


def test_shared_volume(compose: dict[str, Any]) -> None:
    services = compose["services"]
    for name in ("api", "worker", "worker-gpu"):
        assert "data:/data" in services[name]["volumes"]
        assert services[name]["environment"]["PANOGS_STORAGE_DIR"].startswith("/data")
    assert {"data", "pgdata", "redisdata"} <= set(compose["volumes"])


def test_environment_names_real_settings(compose: dict[str, Any]) -> None:
    for name in ("api", "worker", "worker-gpu"):
        env = compose["services"][name]["environment"]
        panogs = {k for k in env if k.startswith("PANOGS_")}
        assert panogs <= FIELDS, f"{name}: unknown settings {panogs - FIELDS}"
        assert {"PANOGS_DATABASE_URL", "PANOGS_BROKER_URL", "PANOGS_STORAGE_DIR"} <= panogs
        assert env["PANOGS_ENVIRONMENT"] == "production"
        assert env["PANOGS_DATABASE_URL"].startswith("postgresql+psycopg://")
        assert env["PANOGS_BROKER_URL"].startswith("redis://redis:")
    assert compose["services"]["worker-gpu"]["environment"]["PANOGS_WORKER_QUEUES"] == "gpu"


def test_commands_are_the_tested_ones(compose: dict[str, Any]) -> None:
    import argparse

    parser = argparse.ArgumentParser(prog="panogs")
    add_service_commands(parser.add_subparsers(dest="command", required=True))
    api = compose["services"]["api"]["command"]
    assert api[:3] == ["panogs", "serve", "--no-worker"]
    assert parser.parse_args(api[1:]).port == 8000
    assert compose["services"]["worker"]["command"] == ["panogs", "worker"]
    from procs import compose_command  # what test_e2e and test_faults start

    assert compose_command("api")[3:] == api[1:]
    assert compose_command("worker")[3:] == ["worker"]


def dockerfile_stages() -> dict[str, str]:
    """The Dockerfile's stages by name: the text from each ``FROM ... AS name`` to the next."""
    text = (REPO / "Dockerfile").read_text()
    parts = re.split(r"^FROM \S+ AS (\w+)$", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def test_dockerfile_api_image_is_slim() -> None:
    api = dockerfile_stages()["api"]
    assert re.search(r"^ARG API_EXTRAS=service$", api, re.M)
    assert "[${API_EXTRAS}]" in api
    assert "torch" not in api
    assert "apt-get" not in api  # open3d's system libraries belong to the worker
    assert re.search(r'^CMD \["panogs", "serve", "--no-worker"', api, re.M)
    assert re.search(r"^USER panogs$", api, re.M)


def test_dockerfile_worker_image() -> None:
    worker = dockerfile_stages()["worker"]
    assert re.search(r"^ARG TORCH_VARIANT=cpu$", worker, re.M)
    assert "download.pytorch.org/whl/${TORCH_VARIANT}" in worker
    assert "torch==2.13.0" in worker
    assert "[worker,text]" in worker
    assert "libusb-1.0-0" in worker
    assert re.search(r'^CMD \["panogs", "worker"\]', worker, re.M)
    assert re.search(r"^USER panogs$", worker, re.M)


def test_every_install_follows_the_constraints() -> None:
    stages = dockerfile_stages()
    assert "COPY constraints.txt" in stages["base"]
    for name in ("api", "worker"):
        installs = [line for line in stages[name].splitlines() if "pip install" in line]
        assert installs
        assert all("-c constraints.txt" in line for line in installs), f"{name}: {installs}"


def test_compose_builds_each_service_from_its_target(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert services["api"]["build"]["target"] == "api"
    for name in ("worker", "worker-gpu"):
        assert services[name]["build"]["target"] == "worker"
    assert services["api"]["image"] != services["worker"]["image"]


def test_env_example_lists_every_setting() -> None:
    text = (REPO / ".env.example").read_text()
    named = set(re.findall(r"\bPANOGS_[A-Z_]+(?==)", text))
    assert FIELDS <= named, f"missing from .env.example: {sorted(FIELDS - named)}"
    assert "POSTGRES_PASSWORD=changethis" in text


def test_production_refuses_placeholders(tmp_path: Path) -> None:
    from pydantic import ValidationError

    common = {
        "_env_file": None,
        "data_dir": tmp_path,
        "environment": "production",
        "broker_url": "redis://r:6379/0",
    }
    with pytest.raises(ValidationError, match="placeholder"):
        Settings(database_url="postgresql+psycopg://panogs:changethis@db/panogs", **common)  # type: ignore[arg-type]
    with pytest.raises(ValidationError, match="must be set in production"):
        Settings(**common)  # type: ignore[arg-type]
    assert Settings(database_url="postgresql+psycopg://panogs:s3cret@db/panogs", **common).environment == "production"  # type: ignore[arg-type]
