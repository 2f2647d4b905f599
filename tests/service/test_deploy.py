"""Deployment files: docker-compose.yml parses, names every service, volume and setting, and runs the commands
the end-to-end tests run; the Dockerfile builds an API image (slim by default: no torch) and worker images (CPU, or
a CUDA build of torch that exists), both from constraints.txt, each image named for what it holds and checking
itself at build time; .env.example lists every setting; .dockerignore keeps .env out of the build context. The files
are checked by reading here and the image scripts by running them; `make deploy-check` (tools/deploy-check) builds
and runs the images themselves."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from service.cli import add_service_commands
from service.settings import Settings

REPO = Path(__file__).resolve().parents[2]
FIELDS = {f"PANOGS_{name.upper()}" for name in Settings.model_fields}
IMAGE_SCRIPTS = REPO / "tools" / "docker" / "image"
# The builds of the pinned torch 2.13.0 (PyTorch's release compatibility matrix: CUDA 12.6 and 13.0 stable, 13.2
# experimental; PyPI's own 2.13.0 is the CUDA 13.0 one). cu124 and cu128 are not among them.
CUDA_VARIANTS = {"cu126", "cu130", "cu132"}
DEPLOYMENT_FILES = ("Dockerfile", "docker-compose.yml", ".env.example", "docs/service.md")


@pytest.fixture(scope="module")
def compose() -> dict[str, Any]:
    return dict(yaml.safe_load((REPO / "docker-compose.yml").read_text()))


def test_services(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert {"api", "worker", "redis", "postgres"} <= set(services)
    for name in ("api", "worker", "worker-gpu", "redis", "postgres"):
        assert "healthcheck" in services[name], f"{name} has no health check"
    assert services["worker"]["depends_on"]["api"]["condition"] == "service_healthy"
    assert services["api"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    assert "replicas" not in services["worker"].get("deploy", {})  # --scale worker=N decides
    assert "ports" not in services["worker"]  # so that it can be scaled
    assert "/readyz" in " ".join(services["api"]["healthcheck"]["test"])


def test_no_shared_volume_objects_in_seaweedfs(compose: dict[str, Any]) -> None:
    services = compose["services"]
    for name in ("api", "worker", "worker-gpu"):
        assert "volumes" not in services[name], f"{name} mounts a volume: nothing is shared between hosts"
        env = services[name]["environment"]
        assert "PANOGS_STORAGE_DIR" not in env
        assert env["PANOGS_STORAGE_URL"].startswith("${PANOGS_STORAGE_URL:-s3://")
        assert "seaweedfs:8333" in env["PANOGS_S3_ENDPOINT_URL"]
    assert services["api"]["depends_on"]["seaweedfs"]["condition"] == "service_healthy"
    seaweed = services["seaweedfs"]
    assert seaweed["build"]["target"] == "seaweedfs"
    assert seaweed["volumes"] == ["s3data:/data"]
    assert "healthcheck" in seaweed
    assert set(compose["volumes"]) == {"s3data", "pgdata", "redisdata"}


def test_environment_names_real_settings(compose: dict[str, Any]) -> None:
    for name in ("api", "worker", "worker-gpu"):
        env = compose["services"][name]["environment"]
        panogs = {k for k in env if k.startswith("PANOGS_")}
        assert panogs <= FIELDS, f"{name}: unknown settings {panogs - FIELDS}"
        assert {"PANOGS_DATABASE_URL", "PANOGS_BROKER_URL", "PANOGS_STORAGE_URL", "PANOGS_S3_ENDPOINT_URL"} <= panogs
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
    """The Dockerfile's stages by name: the instructions from each ``FROM ... AS name`` to the next (no comments)."""
    text = "\n".join(line for line in (REPO / "Dockerfile").read_text().splitlines() if not line.startswith("#"))
    parts = re.split(r"^FROM \S+ AS ([\w-]+)$", text, flags=re.M)
    return dict(zip(parts[1::2], parts[2::2], strict=True))


def dockerfile_global_args() -> dict[str, str]:
    """The ``ARG NAME=default`` lines before the first ``FROM`` (the ones a ``FROM`` line may use)."""
    head = (REPO / "Dockerfile").read_text().split("\nFROM ", 1)[0]
    return {m[1]: m[2].strip('"') for m in re.finditer(r"^ARG (\w+)=(.*)$", head, re.M)}


def test_dockerfile_api_image_is_slim_by_default() -> None:
    stages = dockerfile_stages()
    assert dockerfile_global_args()["API_KIND"] == "slim"
    assert re.search(r"^FROM api-\$\{API_KIND\} AS api$", (REPO / "Dockerfile").read_text(), re.M)
    slim = stages["api-slim"]
    assert '"$(ls /wheels/panogs-*.whl)[service]"' in slim
    assert "torch" not in slim
    assert "apt-get" not in slim  # open3d's system libraries belong to the pipeline
    assert re.search(r"^RUN panogs-image-check service$", slim, re.M)
    assert stages["api-full"].strip() == ""  # the full API is the pipeline's environment, layer for layer
    api = stages["api"]
    assert re.search(r'^CMD \["panogs", "serve", "--no-worker"', api, re.M)
    assert re.search(r"^USER panogs$", api, re.M)
    # the classic builder builds every stage above the target: the API comes last so that a worker build skips it
    assert list(stages)[-1] == "api"


def test_dockerfile_worker_image() -> None:
    stages = dockerfile_stages()
    pipeline, torch = stages["pipeline"], stages["torch"]
    for stage in (pipeline, torch):
        assert re.search(r"^ARG TORCH_VARIANT=cpu$", stage, re.M)
    assert re.search(r"^ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/\$\{TORCH_VARIANT\}$", torch, re.M)
    assert 'RUN panogs-install-torch "${TORCH_VARIANT}"' in torch
    assert "COPY --from=torch /opt/panogs /opt/panogs" in pipeline
    assert "[worker,text]" in pipeline
    assert "${OPEN3D_LIBS}" in pipeline
    assert 'RUN panogs-image-check worker,text && panogs-check-torch "${TORCH_VARIANT}"' in pipeline
    assert re.search(r"^FROM pipeline AS worker$", (REPO / "Dockerfile").read_text(), re.M)
    worker = stages["worker"]
    assert re.search(r'^CMD \["panogs", "worker"\]', worker, re.M)
    assert re.search(r"^USER panogs$", worker, re.M)


def test_dockerfile_installs_open3ds_system_libraries() -> None:
    # open3d-cpu links libEGL, libGL and libX11 at import; without them every job failed at its first stage
    assert set(dockerfile_global_args()["OPEN3D_LIBS"].split()) == {
        "libegl1",
        "libgl1",
        "libx11-6",
        "libusb-1.0-0",
        "libgomp1",
    }


def test_base_images_are_build_arguments(compose: dict[str, Any]) -> None:
    args = dockerfile_global_args()
    stages = (REPO / "Dockerfile").read_text()
    assert re.search(r"^FROM \$\{PYTHON_IMAGE\} AS base$", stages, re.M)
    assert re.search(r"^FROM \$\{NODE_IMAGE\} AS web$", stages, re.M)
    assert len(re.findall(r"^FROM \$\{", stages, re.M)) == 2  # every other stage derives from base
    for name in ("api", "worker", "worker-gpu"):
        build_args = compose["services"][name]["build"]["args"]
        for arg in ("PYTHON_IMAGE", "NODE_IMAGE"):
            # compose's default is the Dockerfile's, and a site overrides both with one variable
            assert build_args[arg] == f"${{{arg}:-{args[arg]}}}", f"{name}: {arg}"
    services = compose["services"]
    assert services["postgres"]["image"] == "${POSTGRES_IMAGE:-postgres:16-alpine}"
    assert services["redis"]["image"] == "${REDIS_IMAGE:-redis:7-alpine}"


def test_each_image_is_named_for_what_it_holds(compose: dict[str, Any]) -> None:
    services = compose["services"]
    images = {name: services[name]["image"] for name in ("api", "worker", "worker-gpu")}
    assert len(set(images.values())) == 3, images
    assert images["worker"].startswith("panogs-worker-cpu:")
    assert services["worker"]["build"]["args"]["TORCH_VARIANT"] == "cpu"
    gpu_variant = services["worker-gpu"]["build"]["args"]["TORCH_VARIANT"]
    assert gpu_variant == "${PANOGS_CUDA_VARIANT:-cu130}"
    assert images["worker-gpu"].startswith(f"panogs-worker-{gpu_variant}:")
    # the compose API renders and answers free text (the README's session), on the CPU worker's layers
    assert services["api"]["build"]["args"]["API_KIND"] == "${PANOGS_API_KIND:-full}"
    assert services["api"]["build"]["args"]["TORCH_VARIANT"] == "cpu"
    assert services["api"]["build"]["args"]["TORCH_INDEX_URL"] == services["worker"]["build"]["args"]["TORCH_INDEX_URL"]


def test_only_torch_builds_that_exist_are_named() -> None:
    for name in (*DEPLOYMENT_FILES, "tools/docker/image/panogs-install-torch"):
        text = (REPO / name).read_text()
        if name == "docs/service.md":
            text = text.split("## Deployment", 1)[1]
        named = set(re.findall(r"\bcu\d{3}\b", text))
        assert named, f"{name} names no CUDA variant"
        assert named <= CUDA_VARIANTS, f"{name} names {sorted(named - CUDA_VARIANTS)}, not builds of torch 2.13.0"


def test_dockerignore_keeps_secrets_out_and_the_image_scripts_in() -> None:
    lines = [line.strip() for line in (REPO / ".dockerignore").read_text().splitlines()]
    assert ".env" in lines
    assert "**/.env" in lines
    assert "!tools/docker/image" in lines
    assert "!tools/docker/wheels" in lines


def run_script(name: str, *args: str) -> subprocess.CompletedProcess[str]:
    """An image script run on this machine, with this interpreter as the image's ``python``."""
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    return subprocess.run(
        ["sh", str(IMAGE_SCRIPTS / name), *args], capture_output=True, text=True, env=env, timeout=120
    )


def test_install_torch_refuses_a_variant_that_does_not_exist() -> None:
    done = run_script("panogs-install-torch", "cu124")
    assert done.returncode == 1
    assert "TORCH_VARIANT=cu124 does not exist for torch 2.13.0" in done.stderr
    assert all(variant in done.stderr for variant in CUDA_VARIANTS)


def test_install_torch_pins_the_build_and_the_constraints() -> None:
    text = (IMAGE_SCRIPTS / "panogs-install-torch").read_text()
    assert 'spec="torch==2.13.0+$variant"' in text  # a local version: PyPI's plain 2.13.0 never matches
    assert "pip install -c /app/constraints.txt" in text
    assert 'panogs-check-torch "$variant"' in text


@pytest.mark.slow  # two fresh interpreters import torch
def test_check_torch_tells_the_build_apart() -> None:
    pytest.importorskip("torch")
    import torch

    here = "cpu" if torch.version.cuda is None else "cu" + torch.version.cuda.replace(".", "")
    other = "cu130" if here == "cpu" else "cpu"
    assert run_script("panogs-check-torch", here).returncode == 0
    refused = run_script("panogs-check-torch", other)
    assert refused.returncode != 0
    assert f"is not the {other} build of 2.13.0" in refused.stderr


def test_image_check_refuses_torch_in_a_slim_api() -> None:
    pytest.importorskip("torch")  # this environment has every extra, so as a slim API it must fail
    done = run_script("panogs-image-check", "service")
    assert done.returncode != 0
    assert "torch is installed in an image built without the pipeline or text extra" in done.stderr


def test_every_install_follows_the_constraints() -> None:
    stages = dockerfile_stages()
    assert "COPY constraints.txt ./" in stages["base"]
    assert "WORKDIR /app" in stages["base"]
    for name in ("api-slim", "pipeline"):
        installs = [line for line in stages[name].splitlines() if "pip install" in line]
        assert installs
        assert all("-c constraints.txt" in line for line in installs), f"{name}: {installs}"


def test_compose_builds_each_service_from_its_target(compose: dict[str, Any]) -> None:
    services = compose["services"]
    assert services["api"]["build"]["target"] == "api"
    for name in ("worker", "worker-gpu"):
        assert services[name]["build"]["target"] == "worker"


def test_env_example_lists_every_setting() -> None:
    text = (REPO / ".env.example").read_text()
    named = set(re.findall(r"\bPANOGS_[A-Z0-9_]+(?==)", text))
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


def test_the_missing_extras_messages_say_what_to_do_in_the_deployment() -> None:
    from service.job_results import _text_extra_hint

    missing = "minilm-l6: sentence-transformers is not installed (pip install 'panogs[text]')"
    assert "rebuild the API image with --build-arg API_KIND=full" in _text_extra_hint(missing)
    assert _text_extra_hint("free-text queries are switched off on this server") == ""
    assert "--build-arg API_KIND=full" in (REPO / "service" / "render_child.py").read_text()


def test_no_image_declares_a_volume() -> None:
    # An image's VOLUME gives each container an anonymous volume that `docker compose down` and a scale-down leave
    # behind (a worker's bundle cache, up to 8 GiB each); what must last is a named volume in the compose file.
    lines = (REPO / "Dockerfile").read_text().splitlines()
    assert not [line for line in lines if line.strip().upper().startswith("VOLUME")]


def test_install_torch_says_where_a_wheel_goes_when_the_index_is_unreachable(tmp_path: Path) -> None:
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}",
        "TORCH_INDEX_URL": "http://127.0.0.1:9/simple",  # the discard port: nothing answers
        "PIP_NO_INDEX": "1",  # and pip may reach no other index: it cannot find the pinned build
        "PIP_DRY_RUN": "1",
    }
    done = subprocess.run(
        ["sh", str(IMAGE_SCRIPTS / "panogs-install-torch"), "cpu"], capture_output=True, text=True, env=env, timeout=120
    )
    assert done.returncode == 1
    assert "the torch index http://127.0.0.1:9/simple does not answer from this build" in done.stderr
    assert "UNREACHABLE" in done.stderr
    assert "in tools/docker/wheels/ of the build context" in done.stderr


def test_a_placeholder_secret_is_named_with_where_to_set_it(tmp_path: Path) -> None:
    env = {**os.environ, "PANOGS_ENVIRONMENT": "production", "PANOGS_DATA_DIR": str(tmp_path)}
    env |= {
        "PANOGS_DATABASE_URL": "postgresql+psycopg://panogs:s3cret@db/panogs",
        "PANOGS_BROKER_URL": "redis://r:6379/0",
    }
    env |= {"PANOGS_S3_SECRET_ACCESS_KEY": "changethis", "PANOGS_STORAGE_URL": "s3://panogs/data"}
    done = subprocess.run(
        [sys.executable, "-m", "panogs_core.cli", "keys", "list"], capture_output=True, text=True, env=env, timeout=120
    )
    assert done.returncode == 1
    assert "panogs: the settings are not valid:" in done.stderr
    assert "PANOGS_S3_SECRET_ACCESS_KEY still holds the placeholder 'changethis': set your own secret" in done.stderr
    assert "Traceback" not in done.stderr
