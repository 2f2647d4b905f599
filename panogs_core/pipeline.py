"""The whole PanoGS pipeline: a scene bundle in, panoptic labels, instances and exports out.

``run_pipeline`` runs the stages of DESIGN.md in order. Each stage's output is checkpointed under
``out_dir/stages/`` together with a key (a hash of the input bundle, the stage's config and its upstream keys),
so a crashed job resumes from its last finished stage and a re-run with new clustering thresholds reuses the
fusion and the distilled field.
"""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from panogs_core import __version__
from panogs_core.bundle import Scene, open_bundle
from panogs_core.config import PipelineConfig
from panogs_core.profiling import StageStats, StageTimer, lifetime_peak_rss_bytes
from panogs_core.progress import ProgressFn
from panogs_core.types import Vocabulary

log = logging.getLogger(__name__)

STAGES = (
    "validate",
    "primitives",
    "appearance",
    "visibility",
    "fusion",
    "language_field",
    "masks",
    "superprimitives",
    "clustering",
    "labeling",
    "export",
)

StageProgressFn = Callable[[str, int, int], None]
T = TypeVar("T")


@dataclass
class PipelineResult:
    """What a run produced. Files are in ``out_dir``; arrays are the in-memory copies."""

    out_dir: Path
    scene_name: str
    num_primitives: int
    instances: list[dict[str, Any]]
    timings: list[StageStats]
    metrics: dict[str, Any] | None = None
    files: dict[str, Path] = field(default_factory=dict)
    unseen: dict[str, int] = field(default_factory=dict)  # primitives no key frame saw, and how each was labelled
    appearance: dict[str, Any] = field(default_factory=dict)  # the Gaussian scene's fit (PSNR before/after...)


def _hash_json(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def hash_bundle(scene: Scene) -> str:
    """SHA-256 over ``scene.json`` and every file it references (streamed, 1 MiB chunks)."""
    digest = hashlib.sha256()
    paths = [scene.root / "scene.json"]
    for frame in scene.frames:
        paths += [scene.root / p for p in (frame.depth, frame.color, frame.features, frame.masks) if p]
    for extra in ("geometry.ply", "vocabulary.json", "vocabulary.npy", "gt/labels.npz"):
        if (scene.root / extra).is_file():
            paths.append(scene.root / extra)
    for path in paths:
        digest.update(str(path.relative_to(scene.root)).encode())
        with open(path, "rb") as fh:
            while chunk := fh.read(1 << 20):
                digest.update(chunk)
    return digest.hexdigest()


class _Checkpoints:
    """Stage outputs under ``stages/`` with a manifest of the key each was made with."""

    def __init__(self, root: Path, enabled: bool) -> None:
        self.root = root
        self.enabled = enabled
        root.mkdir(parents=True, exist_ok=True)
        self._manifest_path = root / "manifest.json"
        self.manifest: dict[str, str] = {}
        if enabled and self._manifest_path.is_file():
            self.manifest = json.loads(self._manifest_path.read_text())

    def path(self, stage: str) -> Path:
        return self.root / f"{stage}.npz"

    def has(self, stage: str, key: str) -> bool:
        return self.enabled and self.manifest.get(stage) == key and self.path(stage).is_file()

    def record(self, stage: str, key: str) -> None:
        self.manifest[stage] = key
        tmp = self._manifest_path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.manifest, indent=1))
        tmp.replace(self._manifest_path)


class _StageProgress:
    """A stage's ``on_progress(done, total)``, forwarded with the stage name; remembers the stage's units."""

    def __init__(self, stage: str, sink: StageProgressFn | None) -> None:
        self.stage = stage
        self.sink = sink
        self.total = 1

    def __call__(self, done: int, total: int) -> None:
        self.total = total
        if self.sink is not None:
            self.sink(self.stage, done, total)

    def finish(self) -> None:
        """Report the stage complete, in its own units."""
        self(self.total, self.total)


class _Runner:
    """Runs stages with timing, progress and checkpoints; holds nothing but bookkeeping."""

    def __init__(self, out_dir: Path, resume: bool, on_progress: StageProgressFn | None) -> None:
        self.checkpoints = _Checkpoints(out_dir / "stages", resume)
        self.on_progress = on_progress
        self.timings: list[StageStats] = []

    def progress_for(self, stage: str) -> _StageProgress:
        return _StageProgress(stage, self.on_progress)

    def stage(
        self,
        name: str,
        key: str,
        compute: Callable[[ProgressFn], T],
        load: Callable[[Path], T] | None = None,
        save: Callable[[T, Path], None] | None = None,
    ) -> T:
        """Load the checkpoint of ``name`` if its key matches, else compute (and save) it."""
        report = self.progress_for(name)
        with StageTimer(name) as timer:
            report(0, 1)
            if load is not None and self.checkpoints.has(name, key):
                result = load(self.checkpoints.path(name))
                timer.stats.cached = True
            else:
                result = compute(report)
                if save is not None:
                    tmp = self.checkpoints.path(name).with_suffix(".tmp.npz")
                    save(result, tmp)
                    tmp.replace(self.checkpoints.path(name))
                    self.checkpoints.record(name, key)
            report.finish()
        self.timings.append(timer.stats)
        log.info(
            "stage %s: %.2f s, peak %.0f MB%s",
            name,
            timer.stats.wall_s,
            timer.stats.peak_rss_mb,
            " (checkpoint)" if timer.stats.cached else "",
        )
        return result


def resolve_scene_vocabulary(scene: Scene, spec: str | None) -> Vocabulary:
    """The label set of a run: ``spec`` (name or file) > the bundle's > ScanNet-20 for the CLIP space.

    Embeddings are added with the space's text encoder when the chosen vocabulary has none.
    """
    from panogs_core.errors import InputError
    from panogs_core.labelsets import ensure_embeddings, resolve_vocabulary

    if spec is not None:
        vocabulary = resolve_vocabulary(spec, feature_space=scene.feature_space)
    elif scene.vocabulary is not None:
        vocabulary = scene.vocabulary
    elif scene.feature_space == "clip-vit-b32":
        vocabulary = resolve_vocabulary("scannet20", feature_space=scene.feature_space)
    else:
        raise InputError(
            f"{scene.root / 'scene.json'}: the bundle has no vocabulary.json and features.space "
            f"{scene.feature_space!r} has no default label set; pass a vocabulary "
            "(--vocabulary scannet20|matterport21|FILE)"
        )
    return ensure_embeddings(vocabulary, scene.feature_space, scene.feature_dim)


def run_pipeline(
    bundle: str | Path | Scene,
    out_dir: str | Path,
    config: PipelineConfig | None = None,
    *,
    vocabulary: str | None = None,
    on_progress: StageProgressFn | None = None,
    resume: bool = True,
) -> PipelineResult:
    """Run every stage on a bundle and write the outputs of DESIGN.md into ``out_dir``.

    Args:
        bundle: Bundle folder or archive, or an already opened :class:`Scene`.
        out_dir: Output folder (created). Checkpoints go to ``out_dir/stages``.
        config: Pipeline settings; defaults to :class:`PipelineConfig()`.
        vocabulary: ``scannet20`` | ``matterport21`` | a vocabulary.json path; overrides the bundle's.
        on_progress: ``on_progress(stage, done, total)``; may raise :class:`Cancelled` to stop.
        resume: Reuse checkpoints whose keys match.

    Returns:
        The result summary; files are in ``out_dir``.

    Raises:
        BundleError: the bundle is invalid (every problem listed).
        Cancelled: the progress callback asked to stop.
    """
    from panogs_core import stages as st

    cfg = config or PipelineConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runner = _Runner(out, resume, on_progress)
    t_start = time.perf_counter()

    scene = runner.stage(
        "validate", "", lambda _: bundle if isinstance(bundle, Scene) else open_bundle(bundle, workdir=out / "bundle")
    )
    input_hash = hash_bundle(scene)
    vocab = resolve_scene_vocabulary(scene, vocabulary)
    keys = st.stage_keys(input_hash, cfg, vocab)

    prims = runner.stage(
        "primitives", keys["primitives"], lambda p: st.primitives(scene, cfg, p), *st.io_for("primitives")
    )
    gaussians = runner.stage(
        "appearance", keys["appearance"], lambda p: st.appearance(scene, prims, cfg, p), *st.io_for("appearance")
    )
    vis = runner.stage(
        "visibility", keys["visibility"], lambda p: st.visibility(scene, prims, cfg, p), *st.io_for("visibility")
    )
    fused = runner.stage("fusion", keys["fusion"], lambda p: st.fusion(scene, vis, prims, cfg, p), *st.io_for("fusion"))
    field_ = None
    if cfg.features_source == "field":
        field_ = runner.stage(
            "language_field",
            keys["language_field"],
            lambda p: st.language_field(prims, fused, cfg, p),
            *st.io_for("language_field"),
        )
    features = st.primitive_features(field_, fused, cfg)
    masks = runner.stage("masks", keys["masks"], lambda p: st.masks(scene, vis, cfg, p), *st.io_for("masks"))
    graph = runner.stage(
        "superprimitives",
        keys["superprimitives"],
        lambda p: st.superprimitives(prims, features, masks, cfg, p),
        *st.io_for("superprimitives"),
    )
    clusters = runner.stage(
        "clustering",
        keys["clustering"],
        lambda p: st.clustering(graph, masks, features, cfg, p),
        *st.io_for("clustering"),
    )
    labels = runner.stage(
        "labeling",
        keys["labeling"],
        lambda p: st.labeling(prims, features, fused, graph, clusters, vocab, cfg),
        *st.io_for("labeling"),
    )

    def export(_: ProgressFn) -> PipelineResult:
        from panogs_core.export import write_outputs

        files, metrics = write_outputs(out, scene, prims, fused, graph, clusters, labels, vocab, gaussians=gaussians)
        return PipelineResult(
            appearance=gaussians.summary(),
            unseen=dict(labels.unseen),
            out_dir=out,
            scene_name=scene.name,
            num_primitives=int(prims.points.shape[0]),
            instances=[i.to_json() for i in labels.instances],
            timings=runner.timings,
            metrics=metrics,
            files=files,
        )

    result = runner.stage("export", "", export)
    _write_report(out, scene, cfg, vocabulary, input_hash, runner.timings, time.perf_counter() - t_start, result)
    return result


def _write_report(
    out: Path,
    scene: Scene,
    cfg: PipelineConfig,
    vocabulary_spec: str | None,
    input_hash: str,
    timings: list[StageStats],
    total_s: float,
    result: PipelineResult,
) -> None:
    import torch

    from panogs_core.appearance import resolve_schedule

    # The language field and the appearance fit run on a torch device; every other stage runs on the CPU.
    fit_device = resolve_schedule(cfg.appearance, scene.camera.width, torch.cuda.is_available()).device
    torch_device_stages = {"language_field": cfg.language_field.device, "appearance": fit_device}
    stages = [{**t.to_json(), "device": torch_device_stages.get(t.name, "cpu")} for t in timings]
    report = {
        "scene": scene.name,
        "input_sha256": input_hash,
        "num_primitives": result.num_primitives,
        "num_instances": len(result.instances),
        # Primitives that no key frame saw, and how many of them each rule labelled (labeling.label_unseen).
        "unseen_primitives": result.unseen,
        # The Gaussian scene's appearance fit: PSNR / SSIM before and after, frames without colour, notes.
        "appearance": result.appearance,
        "num_frames": len(scene.frames),
        "feature_space": scene.feature_space,
        "feature_dim": scene.feature_dim,
        "vocabulary": vocabulary_spec or ("bundle" if scene.vocabulary is not None else "default"),
        "stages": stages,
        "total_wall_s": round(total_s, 3),
        "peak_rss_mb": round(lifetime_peak_rss_bytes() / 2**20, 1),
        "config": cfg.to_dict(),
        "versions": {
            "panogs": __version__,
            "python": platform.python_version(),
            "numpy": np.__version__,
            "torch": torch.__version__,
            "cuda": torch.version.cuda,  # None in a CPU build of torch
        },
    }
    (out / "report.json").write_text(json.dumps(report, indent=2))
    result.files["report.json"] = out / "report.json"
