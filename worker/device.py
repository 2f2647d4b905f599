"""Which torch device a job trains on: the worker's GPU when it has one, unless the job asked for a device.

Decided inside the task, never at import: a prefork worker's parent process that touched CUDA (or ran any torch op)
before forking deadlocks its children, so ``cuda_available`` imports torch only when a task calls it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from panogs_core.errors import ConfigError

# The pipeline setting the worker decides: the language field's torch device (PipelineConfig.language_field.device).
# The 2D-maps stage has its own, ``maps2d.device``, whose default ``auto`` already takes the GPU when torch sees one.
DEVICE_SECTION = "language_field"
DEVICE_KEY = "device"


def cuda_available() -> bool:
    """True when torch sees a CUDA device from this process (imports torch: call it from a task only)."""
    import torch

    return bool(torch.cuda.is_available())


def requested_device(overrides: dict[str, Any]) -> str | None:
    """The device a job's config overrides name, or None when they leave it to the worker."""
    section = overrides.get(DEVICE_SECTION)
    if not isinstance(section, dict):
        return None
    value = section.get(DEVICE_KEY)
    return str(value) if value is not None else None


def resolve_device(requested: str | None, has_cuda: bool) -> str:
    """The device to train on: the requested one, else ``cuda`` when this worker has it, else ``cpu``.

    Raises:
        ConfigError: the job asked for CUDA on a worker without it (a config error, not a crash: the job
            fails with this message instead of a torch traceback).
    """
    if requested is None:
        return "cuda" if has_cuda else "cpu"
    if requested.startswith("cuda") and not has_cuda:
        raise ConfigError(f"{DEVICE_SECTION}.{DEVICE_KEY}={requested!r}: this worker has no CUDA device")
    return requested


def with_device(overrides: dict[str, Any], device: str) -> dict[str, Any]:
    """``overrides`` with the device set (a copy; the job's stored overrides stay as the client sent them)."""
    section = overrides.get(DEVICE_SECTION)
    merged = {**(section if isinstance(section, dict) else {}), DEVICE_KEY: device}
    return {**overrides, DEVICE_SECTION: merged}


ConfigFactory = Callable[[dict[str, Any]], Any]


def device_config_factory(make_config: ConfigFactory, has_cuda: bool) -> ConfigFactory:
    """Wrap a pipeline's config factory so that every job's config names the device this worker decided."""

    def make(overrides: dict[str, Any]) -> Any:
        device = resolve_device(requested_device(overrides), has_cuda)
        return make_config(with_device(overrides, device))

    return make
