"""Backend choice: the torch rasteriser without CUDA, a clear error when gsplat cannot run."""

from __future__ import annotations

import pytest
import torch
from torch_threads import one_torch_thread  # noqa: F401  (autouse fixture: small tensors)

from panogs_core.errors import ConfigError
from panogs_core.gaussians.backends import resolve_backend


def test_cpu_tensors_use_the_torch_rasteriser() -> None:
    assert resolve_backend("auto", torch.device("cpu")) == "torch"
    assert resolve_backend("torch", torch.device("cpu")) == "torch"


def test_gsplat_on_the_cpu_is_refused_with_the_reason() -> None:
    with pytest.raises(ConfigError, match="CUDA device and the gpu extra"):
        resolve_backend("gsplat", torch.device("cpu"))
