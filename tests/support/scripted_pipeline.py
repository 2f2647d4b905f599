"""A scripted stand-in for ``panogs_core.pipeline.run.run_pipeline``, to test and benchmark the service itself.

Same signature and the same outputs' names, no torch, and a known duration: each stage takes
``PANOGS_SCRIPTED_STAGE_S`` seconds (default 0.2) in 5 progress steps, and leaves a checkpoint so that a
resumed run skips it. The config overrides it accepts are ``{"fail_at": "<stage>"}`` (raise a
``NumericalError`` there; in ``appearance`` the fit fails and the results stand), ``{"stage_s": <seconds>}``,
``{"fit_s": <seconds>}`` (the fit's time, after the results) and, as the real config has it,
``{"language_field": {"device": ...}}`` (the worker sets it; report.json records it). ``pipeline_stand_in`` puts
it in place of the pipeline (in a started process: ``PANOGS_TEST_PIPELINE=scripted_pipeline`` and
``tests/support`` on the Python path). A test double, not shipped: its outputs are placeholders (two instances,
"chair" and "table"; given a parsed ``Vocabulary``, as the worker passes a job's inline one, they take its first
class names and ``vocabulary.json`` lists its classes). Like the real pipeline it takes a built-in name or a
``Vocabulary``, never a path.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import Cancelled, ConfigError, NumericalError
from panogs_core.types import Vocabulary

STAGES = ("validate", "primitives", "fusion", "clustering", "labeling", "export", "appearance")
RESULTS_AFTER = "export"  # like the real pipeline: the results are written here, then the fit ("appearance") runs
STEPS = 5
INSTANCES = [
    {"id": 0, "class_name": "chair", "class_index": 1, "kind": "thing", "score": 0.9, "num_points": 2,
     "centroid": [1.0, 0.0, 0.5], "bbox_min": [0.8, -0.2, 0.0], "bbox_max": [1.2, 0.2, 1.0]},
    {"id": 1, "class_name": "table", "class_index": 2, "kind": "thing", "score": 0.8, "num_points": 2,
     "centroid": [-1.0, 0.0, 0.4], "bbox_min": [-1.5, -0.5, 0.0], "bbox_max": [-0.5, 0.5, 0.8]},
]  # fmt: skip


@dataclass
class ScriptedResult:
    """What :func:`run_pipeline` returns (a subset of ``PipelineResult``)."""

    out_dir: Path
    instances: list[dict[str, Any]]
    timings: dict[str, float] = field(default_factory=dict)
    appearance: dict[str, Any] = field(default_factory=dict)  # the fit's ``state`` (and ``error``), as the real one


# "settings": {stage: value}: what each stage "reads"; a stage's key hashes its own and every earlier stage's, as
# the real stage keys do, so two jobs that differ only in a late stage's setting share the earlier checkpoints.
KNOWN_KEYS = ("fail_at", "language_field", "stage_s", "fit_s", "settings")


def make_config(overrides: dict[str, Any]) -> dict[str, Any]:
    """Validate the scripted pipeline's overrides (unknown keys are refused, as ``PipelineConfig`` does)."""
    unknown = sorted(set(overrides) - set(KNOWN_KEYS))
    if unknown:
        raise ConfigError(f"config: unknown key(s) {unknown}; known keys are {list(KNOWN_KEYS)}")
    extra = sorted(set(overrides.get("language_field", {})) - {"device"})
    if extra:
        raise ConfigError(f"config.language_field: unknown key(s) {extra}; the scripted pipeline knows ['device']")
    return dict(overrides)


def device_of(config: dict[str, Any]) -> str:
    """The device the config names, ``cpu`` by default (as ``LanguageFieldConfig``)."""
    return str(config.get("language_field", {}).get("device", "cpu"))


def run_pipeline(
    bundle: str | Path,
    out_dir: str | Path,
    config: dict[str, Any] | None = None,
    *,
    vocabulary: str | Vocabulary | None = None,
    on_progress: Callable[[str, int, int], None] | None = None,
    resume: bool = True,
    on_results: Callable[[Any], None] | None = None,
    shared: Any = None,
) -> ScriptedResult:
    """Walk the stages with progress and checkpoints, writing the placeholder outputs after ``export`` and calling
    ``on_results`` then, before the fit (``appearance``, ``fit_s`` seconds if given). ``fail_at: appearance`` makes
    the fit fail as the real one does: the results stand and the result says ``appearance.state`` failed."""
    config = config or {}
    out = Path(out_dir)
    (out / "stages").mkdir(parents=True, exist_ok=True)
    stage_s = float(config.get("stage_s", os.environ.get("PANOGS_SCRIPTED_STAGE_S", "0.2")))
    timings: dict[str, float] = {}
    result = ScriptedResult(out_dir=out, instances=[], timings=timings)
    for stage in STAGES:
        try:
            _run_stage(stage, out, config, stage_s, timings, on_progress, resume, shared)
        except Exception as exc:  # as the real pipeline: any error of the fit but a cancel is the fit's failure
            if stage != "appearance" or isinstance(exc, Cancelled):
                raise
            result.appearance = {"state": "failed", "error": f"{type(exc).__name__}: {exc}"}
            return result
        if stage == RESULTS_AFTER:
            result.instances = _write_outputs(out, Path(bundle), vocabulary, device_of(config))
            result.appearance = {"state": "running"}
            if on_results is not None:
                on_results(result)
    (out / "gaussians.ply").write_text((out / "panoptic.ply").read_text())  # "fitted"
    result.appearance = {"state": "succeeded"}
    return result


def _run_stage(
    stage: str,
    out: Path,
    config: dict[str, Any],
    stage_s: float,
    timings: dict[str, float],
    on_progress: Callable[[str, int, int], None] | None,
    resume: bool,
    shared: Any = None,
) -> None:
    marker = out / "stages" / f"{stage}.done"
    key = stage_key(stage, config)
    start = time.perf_counter()
    if resume and (
        (marker.exists() and marker.read_text() in (key, "done"))
        or (shared is not None and shared.fetch(stage, key, marker))
    ):
        if on_progress is not None:
            on_progress(stage, 1, 1)
        CACHED.setdefault(str(out), set()).add(stage)
        return
    seconds = float(config.get("fit_s", stage_s)) if stage == "appearance" else stage_s
    for step in range(STEPS):
        if on_progress is not None:
            on_progress(stage, step, STEPS)
        if config.get("fail_at") == stage:
            raise NumericalError(f"{stage}: scripted failure (config fail_at={stage!r})")
        time.sleep(seconds / STEPS)
    if on_progress is not None:
        on_progress(stage, STEPS, STEPS)
    marker.write_text(key)
    if resume and shared is not None:
        shared.store(stage, key, marker)
    timings[stage] = time.perf_counter() - start


# The stages each run folder took from a checkpoint (its own or a shared one), for tests to read.
CACHED: dict[str, set[str]] = {}


def stage_key(stage: str, config: dict[str, Any]) -> str:
    """The scripted stage key: a hash of the ``settings`` of this stage and every earlier one."""
    settings = config.get("settings", {})
    upstream = [[name, settings.get(name)] for name in STAGES[: STAGES.index(stage) + 1]]
    return hashlib.sha256(json.dumps(upstream).encode()).hexdigest()[:16]


def _write_outputs(out: Path, bundle: Path, vocabulary: str | Vocabulary | None, device: str) -> list[dict[str, Any]]:
    instances = INSTANCES
    label: str | None = vocabulary if not isinstance(vocabulary, Vocabulary) else "inline"
    if isinstance(vocabulary, Vocabulary):
        names = [*vocabulary.names, *vocabulary.names][:2]
        instances = [
            {**inst, "class_name": name, "class_index": i} for i, (inst, name) in enumerate(zip(INSTANCES, names))
        ]
        classes = [{"name": n, "kind": k} for n, k in zip(vocabulary.names, vocabulary.kinds)]
        doc: dict[str, Any] = {"classes": classes}
        if vocabulary.embeddings is not None:  # then the run folder answers queries: each instance its class's vector
            np.save(out / "vocabulary.npy", vocabulary.embeddings.astype(np.float32))
            count = len(vocabulary.names)  # fewer classes than instances: the names repeat
            rows = [vocabulary.embeddings[int(inst["class_index"]) % count] for inst in instances]
            np.save(out / "instance_features.npy", np.stack(rows).astype(np.float32))
            doc["embeddings"] = "vocabulary.npy"
        (out / "vocabulary.json").write_text(json.dumps(doc))
    (out / "instances.json").write_text(json.dumps(instances))
    points = np.array([[0.9, 0, 0.5], [1.1, 0, 0.5], [-1.2, 0, 0.4], [-0.8, 0, 0.4]], np.float32)
    semantic = np.array([1, 1, 2, 2], np.int64)
    instance = np.array([0, 0, 1, 1], np.int64)
    np.savez(out / "labels.npz", semantic=semantic, instance=instance, superprimitive=instance)
    header = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n"
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty int semantic\n"
        "property int instance\nend_header\n"
    )
    rows = [f"{x} {y} {z} 128 128 128 {s} {i}" for (x, y, z), s, i in zip(points, semantic, instance)]
    (out / "panoptic.ply").write_text(header + "\n".join(rows) + "\n")
    (out / "gaussians.ply").write_text(header + "\n".join(rows) + "\n")
    report = {"scene": bundle.name, "vocabulary": label, "stages": list(STAGES), "device": device}
    (out / "report.json").write_text(json.dumps(report))
    return instances
