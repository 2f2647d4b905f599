"""The torch half's model loading: a Segment-Anything-family model and a CLIP-family image tower, with their
processors, from a folder in the Hugging Face layout (through :mod:`transformers`; no model code here).

Processors are the Pillow ones (``...ImageProcessorPil``): the default ones of transformers 5 need torchvision,
which does not load beside the CPU build of torch here, and the Pillow ones give the same pixels on every install.
Weights load with ``local_files_only``: a hub name is resolved to the local cache first
(:func:`panogs_core.language.model_identity.resolve_model_dir`), so nothing is fetched here.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch

from panogs_core.language.model_identity import ModelLoadError, read_config

SAM_TYPES = ("sam",)  # SAM ViT-B/L/H, SlimSAM (pruned SAM, same classes)
CLIP_TYPES = ("clip",)


@dataclass(frozen=True)
class LoadedModel:
    """A model ready to run: the module in eval mode on its device, and its processor."""

    model: Any
    processor: Any
    folder: Path
    device: torch.device
    dtype: torch.dtype


def pick_device(device: str, cpu_precision: str = "float32") -> tuple[torch.device, torch.dtype]:
    """The device and dtype of a ``Maps2DConfig.device`` and ``cpu_precision``: CUDA in half precision; the CPU in
    bfloat16 when asked, or for "auto" when it has native bfloat16 arithmetic (:func:`cpu_has_native_bfloat16`),
    else in float32."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(device)
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise ModelLoadError(f"maps2d.device {device!r}: torch sees no CUDA device")
    if dev.type == "cuda":
        return dev, torch.float16
    bf16 = cpu_precision == "bfloat16" or (cpu_precision == "auto" and cpu_has_native_bfloat16())
    return dev, (torch.bfloat16 if bf16 else torch.float32)


def cpu_has_native_bfloat16() -> bool:
    """Whether this CPU does bfloat16 arithmetic in hardware (AVX512-BF16 or AMX), as torch's CPU dispatch sees it.
    Without it oneDNN emulates bfloat16, many times slower than float32 (docs/benchmarks.md)."""
    checks = ("_is_avx512_bf16_supported", "_is_amx_tile_supported")  # torch.cpu's; absent in some builds
    for name in checks:
        check = getattr(torch.cpu, name, None)
        try:
            if check is not None and check():
                return True
        except RuntimeError:
            continue
    return False


def load_sam(folder: Path, device: str, cpu_precision: str = "float32") -> LoadedModel:
    """A SAM-family model and its processor.

    Raises:
        ModelLoadError: the folder is not a SAM model's, or its files do not load.
    """
    from transformers import SamImageProcessorPil, SamModel

    kind = read_config(folder).get("model_type")
    if kind not in SAM_TYPES:
        raise ModelLoadError(
            f"{folder}: config.json model_type {kind!r}, expected a Segment Anything model ('sam': SAM ViT-B/L/H, "
            "SlimSAM)"
        )
    _need_processor(folder, "SAM")
    dev, dtype = pick_device(device, cpu_precision)
    try:
        processor = SamImageProcessorPil.from_pretrained(folder, local_files_only=True)
        model: Any = SamModel.from_pretrained(folder, local_files_only=True, dtype=dtype)
    except Exception as exc:  # transformers and safetensors raise many types for a bad file; all mean "no"
        raise ModelLoadError(f"{folder}: the SAM model does not load: {exc}") from exc
    return LoadedModel(model.to(dev).eval(), processor, folder, dev, dtype)


def load_clip(folder: Path, device: str, cpu_precision: str = "float32") -> LoadedModel:
    """A CLIP model's image tower with its projection, and its image processor.

    Only the image tower is built (``CLIPVisionModelWithProjection`` reads the vision weights of a ``CLIPModel``
    checkpoint and leaves the rest): the text tower, a third of CLIP ViT-B's weights (250 MB in float32), is
    never in the stage's memory; :mod:`panogs_core.language.text_encoders` loads it from the same folder for the
    labels and queries.

    Raises:
        ModelLoadError: the folder is not a CLIP model's, or its files do not load.
    """
    from transformers import CLIPImageProcessorPil, CLIPVisionConfig, CLIPVisionModelWithProjection
    from transformers.utils import logging as hf_logging

    config = read_config(folder)
    kind = config.get("model_type")
    if kind not in CLIP_TYPES:
        raise ModelLoadError(f"{folder}: config.json model_type {kind!r}, expected a CLIP model ('clip')")
    _need_processor(folder, "CLIP")
    dev, dtype = pick_device(device, cpu_precision)
    # The projection's width is the whole model's setting; the vision section of config.json may hold a stale one.
    width = config.get("projection_dim")
    verbosity = hf_logging.get_verbosity()
    try:
        processor = CLIPImageProcessorPil.from_pretrained(folder, local_files_only=True)
        vision: Any = CLIPVisionConfig.from_pretrained(folder, local_files_only=True)
        if isinstance(width, int):
            vision.projection_dim = width
        hf_logging.set_verbosity_error()  # the text tower's weights are left on purpose: no "unexpected keys" report
        model: Any = CLIPVisionModelWithProjection.from_pretrained(
            folder, config=vision, local_files_only=True, dtype=dtype
        )
    except Exception as exc:  # as above
        raise ModelLoadError(f"{folder}: the CLIP model does not load: {exc}") from exc
    finally:
        hf_logging.set_verbosity(verbosity)
    return LoadedModel(model.to(dev).eval(), processor, folder, dev, dtype)


def _need_processor(folder: Path, what: str) -> None:
    if not (folder / "preprocessor_config.json").is_file():
        raise ModelLoadError(
            f"{folder}: no preprocessor_config.json; save the {what} processor beside the model "
            "(processor.save_pretrained(folder))"
        )
