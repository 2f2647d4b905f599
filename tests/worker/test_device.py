"""The device a job trains on: the worker's CUDA device when it has one, the job's own choice when it names one,
decided when the task builds its environment, and recorded in the job's report.json."""

from __future__ import annotations

import dataclasses
import json
import threading
import uuid
from collections.abc import Callable
from pathlib import Path

import pytest
import scripted_pipeline as scripted
from wk_helpers import read_job

from panogs_core.errors import ConfigError
from panogs_core.pipeline.config import PipelineConfig
from service.db.models import JobState
from service.settings import Settings
from worker import leased, runner, tasks
from worker.device import device_config_factory, requested_device, resolve_device, with_device

Env = Callable[..., leased.JobEnv]
MakeJob = Callable[..., uuid.UUID]


@pytest.mark.parametrize(
    ("requested", "has_cuda", "expected"),
    [(None, True, "cuda"), (None, False, "cpu"), ("cpu", True, "cpu"), ("cuda:1", True, "cuda:1")],
)
def test_resolve_device(requested: str | None, has_cuda: bool, expected: str) -> None:
    assert resolve_device(requested, has_cuda) == expected


def test_cuda_requested_on_a_worker_without_it_is_a_config_error() -> None:
    with pytest.raises(ConfigError, match="no CUDA device"):
        resolve_device("cuda", has_cuda=False)


def test_with_device_keeps_the_other_overrides_and_copies() -> None:
    overrides = {"language_field": {"epochs": 2}, "clustering": {"thresholds": [0.9]}}
    placed = with_device(overrides, "cuda")
    assert placed == {"language_field": {"epochs": 2, "device": "cuda"}, "clustering": {"thresholds": [0.9]}}
    assert overrides == {"language_field": {"epochs": 2}, "clustering": {"thresholds": [0.9]}}
    assert requested_device(overrides) is None
    assert requested_device(placed) == "cuda"


def test_pipeline_config_lands_on_the_gpu_of_a_cuda_worker() -> None:
    make = device_config_factory(PipelineConfig.from_dict, has_cuda=True)
    config = make({"language_field": {"epochs": 2}})
    assert config.language_field.device == "cuda"
    assert config.language_field.epochs == 2
    assert make({"language_field": {"device": "cpu"}}).language_field.device == "cpu"
    assert device_config_factory(PipelineConfig.from_dict, has_cuda=False)({}).language_field.device == "cpu"


def test_the_task_decides_the_device_when_it_builds_its_environment(
    settings: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The real pipeline's configs follow ``torch.cuda.is_available()`` as the task sees it."""
    torch = pytest.importorskip("torch")
    real = settings  # the worker's tests put no stand-in in runner.load_pipeline: it loads the core's pipeline
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert tasks.build_job_env(real, threading.Event()).make_config({}).language_field.device == "cuda"
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert tasks.build_job_env(real, threading.Event()).make_config({}).language_field.device == "cpu"


def test_report_says_where_the_job_ran(make_env: Env, make_job: MakeJob, settings: Settings) -> None:
    env = dataclasses.replace(make_env(), make_config=device_config_factory(scripted.make_config, has_cuda=True))
    job_id = make_job()
    assert runner.execute_job(job_id, lease="t", worker="test", env=env) == JobState.SUCCEEDED
    job = read_job(settings, job_id)
    report = next(a for a in job.artifacts if a.name == "report.json")
    assert json.loads((settings.storage / report.path).read_text())["device"] == "cuda"
    assert job.config == {"stage_s": 0.01}, "the job's stored overrides stay as the client sent them"


def test_cuda_job_on_a_cpu_worker_fails_with_a_clear_message(
    make_env: Env, make_job: MakeJob, settings: Settings
) -> None:
    env = dataclasses.replace(make_env(), make_config=device_config_factory(scripted.make_config, has_cuda=False))
    job_id = make_job(config={"stage_s": 0.01, "language_field": {"device": "cuda"}})
    assert runner.execute_job(job_id, lease="t", worker="test", env=env) == JobState.FAILED
    job = read_job(settings, job_id)
    assert job.error_type == "ConfigError"
    assert "no CUDA device" in (job.error_message or "")


@pytest.mark.slow
def test_pipeline_report_names_a_device_per_stage(tmp_path: Path, synth_tiny: Path) -> None:
    """The real pipeline's report.json: the language field on the configured device, the rest on the CPU."""
    pytest.importorskip("torch")
    from panogs_core.pipeline.run import run_pipeline

    bundle = synth_tiny  # only read: the run writes under tmp_path
    config = PipelineConfig.from_dict(
        {"language_field": {"epochs": 1, "min_steps": 1, "device": "cpu"}, "appearance": {"iterations": 2}}
    )
    run_pipeline(bundle, tmp_path / "run", config)
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    devices = {entry["stage"]: entry["device"] for entry in report["stages"]}
    assert devices["language_field"] == "cpu"
    assert set(devices.values()) == {"cpu"}
    assert "cuda" in report["versions"]
