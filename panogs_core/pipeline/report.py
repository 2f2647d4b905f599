"""``report.json``: what a run cost and how it ended, written by the untiled and the tiled run alike.

Per stage its wall time, peak memory, device and whether it came from a checkpoint; the scene, the bundle's hash,
the result's counts, the Gaussian fit's state, the config and the versions (docs/architecture.md, "Outputs of a
run"). A tiled run's report has ``tiling`` too (the plan and every tile).
"""

from __future__ import annotations

import json
import platform
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core import __version__
from panogs_core.io.bundle import Bundle
from panogs_core.io.run_folder import REPORT_JSON
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.profiling import StageStats, lifetime_peak_rss_bytes
from panogs_core.pipeline.result import PipelineResult
from panogs_core.types import Vocabulary


def vocabulary_label(spec: str | Vocabulary | None, scene: Bundle) -> str:
    """What report.json says of the run's label set: its built-in name, ``inline``, ``bundle`` or ``default``."""
    if isinstance(spec, Vocabulary):
        return "inline"
    return spec or ("bundle" if scene.vocabulary is not None else "default")


def report_versions() -> dict[str, str | None]:
    """The ``versions`` of report.json: panogs, Python, numpy, torch and its CUDA (None in a CPU build)."""
    import torch

    return {
        "panogs": __version__,
        "python": platform.python_version(),
        "numpy": np.__version__,
        "torch": torch.__version__,
        "cuda": torch.version.cuda,
    }


def stage_rows(timings: Sequence[StageStats], devices: dict[str, str] | None = None) -> list[dict[str, object]]:
    """report.json's ``stages``: each stage's timing and the device it ran on (``devices``, else ``cpu``)."""
    devices = devices or {}
    return [{**t.to_json(), "device": devices.get(t.name, "cpu")} for t in timings]


def torch_devices(scene: Bundle, cfg: PipelineConfig) -> dict[str, str]:
    """The device of each stage that runs on a torch device: the 2D maps, the language field and the appearance
    fit (every other stage runs on the CPU)."""
    import torch

    from panogs_core.gaussians import resolve_schedule

    fit_device = resolve_schedule(cfg.appearance, scene.camera.width, torch.cuda.is_available()).device
    maps_device = cfg.maps2d.device
    if maps_device == "auto":  # as the stage picks it (stages/maps2d/models.py): CUDA in half precision, else CPU
        maps_device = "cuda" if torch.cuda.is_available() else "cpu"
    return {"maps_2d": maps_device, "language_field": cfg.language_field.device, "appearance": fit_device}


def write_report(
    out: Path,
    scene: Bundle,
    cfg: PipelineConfig,
    vocabulary_spec: str | Vocabulary | None,
    input_hash: str | None,
    result: PipelineResult,
    stages: list[dict[str, object]],
    *,
    tiling: dict[str, Any] | None = None,
) -> None:
    """Write ``report.json`` into ``out`` and name it in ``result.files``.

    Args:
        out: The run folder.
        scene: The run's bundle.
        cfg: The run's settings.
        vocabulary_spec: The run's ``vocabulary`` argument (:func:`vocabulary_label` says what it was).
        input_hash: The bundle's SHA-256; None while it is being computed (the results' report of a run with no
            checkpoint to read back, on a busy machine: the run's last report has it).
        result: The run's result: counts, unseen primitives, the fit's state and the wall time so far.
        stages: Per stage its row (:func:`stage_rows`).
        tiling: A tiled run's plan and tiles; absent from an untiled run's report.
    """
    report: dict[str, Any] = {
        "scene": scene.name,
        "input_sha256": input_hash,
        "num_primitives": result.num_primitives,
        "num_instances": len(result.instances),
        # Primitives that no key frame saw, and how many of them each rule labelled (labeling.label_unseen); a
        # tiled run counts them per tile, under "tiling" (a tile counts its halo too).
        "unseen_primitives": result.unseen,
        # The Gaussian scene's appearance fit: PSNR / SSIM before and after, frames without colour, notes.
        "appearance": result.appearance,
        "num_frames": len(scene.frames),
        "feature_space": scene.feature_space,
        "feature_dim": scene.feature_dim,
        "vocabulary": vocabulary_label(vocabulary_spec, scene),
        "stages": stages,
        "total_wall_s": round(result.total_s, 3),
        # The time to the results (the labels and their files, before the appearance fit); absent from a tiled run.
        **({"results_wall_s": round(result.results_s, 3)} if result.results_s else {}),
        "peak_rss_mb": round(lifetime_peak_rss_bytes() / 2**20, 1),
    }
    if tiling is not None:
        report["tiling"] = tiling
    report["config"] = cfg.to_dict()
    report["versions"] = report_versions()
    REPORT_JSON.path(out).write_text(json.dumps(report, indent=2))
    result.files[REPORT_JSON.name] = REPORT_JSON.path(out)
