"""The whole PanoGS pipeline: a scene bundle in, panoptic labels, instances and exports out.

``run_pipeline`` runs the stages of ``STAGES`` in order (docs/architecture.md has the table and the data each
passes on). Each stage's output is checkpointed under
``out_dir/stages/`` together with a key (a hash of the input bundle, the stage's config and its upstream keys),
so a crashed job resumes from its last finished stage and a re-run with new clustering thresholds reuses the
fusion and the distilled field. The appearance fit also keeps snapshots of its partial work
(:mod:`panogs_core.pipeline.snapshots`), so a run stopped in the middle of the fit resumes there.
"""

from __future__ import annotations

import hashlib
import json
import logging
import platform
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from functools import partial
from pathlib import Path
from typing import Any, Protocol, TypeVar

import numpy as np

from panogs_core import __version__
from panogs_core.errors import Cancelled
from panogs_core.io.bundle import Bundle, open_bundle
from panogs_core.io.run_folder import BUNDLE_FOLDER, GAUSSIANS_PLY, REPORT_JSON, STAGES_FOLDER
from panogs_core.pipeline import stage_table as st
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.input_hash import hash_bundle
from panogs_core.pipeline.profiling import StageStats, StageTimer, lifetime_peak_rss_bytes
from panogs_core.pipeline.snapshots import StageSnapshot
from panogs_core.progress import ProgressFn
from panogs_core.types import Vocabulary

log = logging.getLogger(__name__)

STAGES = (
    "validate",
    "primitives",
    "visibility",
    "fusion",
    "language_field",
    "masks",
    "neighbors",
    "superprimitives",
    "clustering",
    "labeling",
    "export",
    "appearance",
)
# The results (labels, instances, queries, the point views) are written by "export"; the appearance fit comes after
# them, since the labels do not depend on it, and replaces the initialisation's gaussians.ply when it ends.

# report.json's ``appearance.state``: where the Gaussian fit stands (docs/gaussians.md, "Results before the fit").
FIT_RUNNING = "running"  # the results are written; the fit goes on and gaussians.ply is the initialisation
FIT_SUCCEEDED = "succeeded"  # gaussians.ply is the fitted scene
FIT_SKIPPED = "skipped"  # no fit was made (appearance.enabled false, no colour frame); gaussians.ply is final
FIT_FAILED = "failed"  # the fit raised; the results stand, gaussians.ply is the initialisation
FIT_CANCELED = "canceled"  # the run was stopped during the fit; the results stand, a re-run resumes the fit
FIT_STATES = (FIT_RUNNING, FIT_SUCCEEDED, FIT_SKIPPED, FIT_FAILED, FIT_CANCELED)
ResultsFn = Callable[["PipelineResult"], None]

StageProgressFn = Callable[[str, int, int], None]
T = TypeVar("T")
C = TypeVar("C", bound=st.Checkpoint)


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
    appearance: dict[str, Any] = field(default_factory=dict)  # the Gaussian scene's fit: state, PSNR before/after
    total_s: float = 0.0  # wall time of the run so far

    @property
    def fit_state(self) -> str:
        """Where the Gaussian fit stands, one of ``FIT_STATES``."""
        return str(self.appearance.get("state", FIT_RUNNING))


def _hash_json(obj: Any) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


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

    def snapshot(self, stage: str, key: str) -> StageSnapshot:
        """Where ``stage`` keeps its partial work under ``key``; read only when resuming."""
        return StageSnapshot(self.root / f"{stage}.partial.pt", key, readable=self.enabled)

    def may_have(self, stage: str) -> bool:
        """Whether a checkpoint of ``stage`` might be reused (its key is then needed before the stage runs)."""
        return self.enabled and stage in self.manifest and self.path(stage).is_file()

    def record(self, stage: str, key: str) -> None:
        self.manifest[stage] = key
        self._write_manifest()

    def forget(self, stage: str) -> None:
        """Drop the key of ``stage`` (its file is about to change and its new key is not known yet)."""
        if self.manifest.pop(stage, None) is not None:
            self._write_manifest()

    def _write_manifest(self) -> None:
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


class SharedCheckpoints(Protocol):
    """Checkpoints kept beyond one run folder (the service keeps them under the scene, by key): a run whose stage
    key was computed before fetches the checkpoint instead of computing the stage, and stores what it computed."""

    def fetch(self, stage: str, key: str, dest: Path) -> bool:
        """Write the checkpoint of ``stage`` under ``key`` to ``dest`` (whole) and return True; False when there
        is none, and then this run computes it (and calls :meth:`store`)."""
        ...

    def store(self, stage: str, key: str, path: Path) -> None:
        """Keep the checkpoint at ``path``, just computed, for later runs."""
        ...

    def known_input_hash(self) -> str | None:
        """The bundle's hash (:func:`hash_bundle`) as an earlier run of this same bundle kept it, or None: a
        scene's bundle never changes, and hashing it is most of a re-run's time at ScanNet size."""
        ...

    def keep_input_hash(self, sha256: str) -> None:
        """Keep the bundle's hash, computed by this run, for the later runs of the same bundle."""
        ...


class _Runner:
    """Runs stages with timing, progress and checkpoints; holds nothing but bookkeeping."""

    def __init__(
        self, out_dir: Path, resume: bool, on_progress: StageProgressFn | None, shared: SharedCheckpoints | None
    ) -> None:
        self.checkpoints = _Checkpoints(STAGES_FOLDER.path(out_dir), resume)
        self.on_progress = on_progress
        self.shared = shared if resume else None
        self.timings: list[StageStats] = []
        self._unrecorded: list[str] = []  # stages whose checkpoint is written, waiting for their key
        # Checkpoints are written by one thread beside the next stages (the field's and the fusion's are 0.2-0.4 s
        # of file writes each at ScanNet size, and with a shared store an upload); the manifest is the two
        # threads' only shared state, under this lock.
        self._writer = ThreadPoolExecutor(max_workers=1, thread_name_prefix="checkpoint-writer")
        self._writes: list[Future[None]] = []
        self._book = threading.Lock()

    def record_checkpoints(self, keys: _LazyKeys, *, wait: bool) -> None:
        """Record the keys of the checkpoints written before the keys were known (all of them, every pending
        write finished first, when ``wait``)."""
        if wait:
            self.flush()
        else:
            self._raise_failed_write()
        with self._book:
            if self._unrecorded and (wait or keys.ready()):
                for name in self._unrecorded:
                    self._recorded(name, keys[name])
                self._unrecorded.clear()

    def flush(self) -> None:
        """Wait for every checkpoint write; raise the first one's error."""
        writes, self._writes = self._writes, []
        for write in writes:
            write.result()

    def close(self, *, failing: bool = False) -> None:
        """Finish the pending writes (a finished stage's checkpoint stays good for a resumed run) and stop the
        writer; a write's error is raised, unless the run is already failing (then it is logged)."""
        try:
            self.flush()
        except Exception:
            if not failing:
                raise
            log.exception("a checkpoint could not be written (the run failed too)")
        finally:
            self._writer.shutdown(wait=True)

    def _raise_failed_write(self) -> None:
        for write in self._writes:
            if write.done() and write.exception() is not None:
                self.flush()  # raises it

    def _recorded(self, name: str, key: str) -> str:
        """Record the checkpoint just written of ``name`` under ``key`` (its partial work is done with); ``key``."""
        self.checkpoints.record(name, key)
        self.checkpoints.snapshot(name, key).discard()
        return key

    def progress_for(self, stage: str) -> _StageProgress:
        return _StageProgress(stage, self.on_progress)

    def stage(self, spec: st.StageSpec[C], keys: _LazyKeys, compute: Callable[[ProgressFn], C]) -> C:
        """Load the checkpoint of ``spec`` if its key matches, else compute and save it.

        The key is waited for only when a checkpoint of the stage exists (the keys hash the whole bundle, which
        the first stages need not wait for: :class:`_LazyKeys`); else the checkpoint is recorded once it is known.
        """

        def load_or_compute(report: ProgressFn, stats: StageStats) -> C:
            self.record_checkpoints(keys, wait=False)  # what the stages before have written, if it can be
            path = self.checkpoints.path(spec.name)
            if self._reusable(spec.name, keys, path):
                stats.cached = True
                return spec.load(path)
            result = compute(report)
            self._writes.append(self._writer.submit(self._write_checkpoint, spec.name, result, path, keys))
            return result

        return self._timed(spec.name, load_or_compute)

    def _write_checkpoint(self, name: str, result: st.Checkpoint, path: Path, keys: _LazyKeys) -> None:
        """Save ``result`` as the checkpoint of ``name`` (in the writer thread: no stage changes a stage's output
        in place, so it is the output as computed) and record or store it under its key."""
        tmp = path.with_suffix(".tmp.npz")
        result.save(tmp)
        shared = self.shared
        key = None if shared is None else keys[name]  # the shared store files it under its key: wait for it
        with self._book:
            self.checkpoints.forget(name)  # a stale key must never name the new file
            tmp.replace(path)
            if shared is None or key is None:
                self._unrecorded.append(name)
                return
            self._recorded(name, key)
        shared.store(name, key, path)

    def _reusable(self, name: str, keys: _LazyKeys, path: Path) -> bool:
        """Whether ``path`` holds the stage's checkpoint for its current key: in the run folder, else fetched from
        the shared store (which needs the key, so a run with a shared store waits for the bundle's hash here)."""
        with self._book:  # the keys are read outside it: they may wait for the bundle's hash
            recorded = self.checkpoints.manifest[name] if self.checkpoints.may_have(name) else None
        if recorded is not None and recorded == keys[name]:  # no wait without a checkpoint to compare
            return True
        if self.shared is None:
            return False
        key = keys[name]
        with self._book:
            self.checkpoints.forget(name)  # the fetch may replace the file: no stale key may name it
        if self.shared.fetch(name, key, path):
            with self._book:
                self.checkpoints.record(name, key)
            return True
        return False

    def step(self, name: str, compute: Callable[[ProgressFn], T]) -> T:
        """Run a stage that has no checkpoint (it is cheap, or its outputs are the run's files)."""
        return self._timed(name, lambda report, _: compute(report))

    def _timed(self, name: str, body: Callable[[ProgressFn, StageStats], T]) -> T:
        report = self.progress_for(name)
        with StageTimer(name) as timer:
            report(0, 1)
            result = body(report, timer.stats)
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


class _LazyKeys(Mapping[str, str]):
    """The stages' checkpoint keys, made from the bundle's hash once it is ready.

    Hashing the bundle reads every file of it (2 GB at ScanNet size, about 2 s): it runs in a thread (hashlib and
    file reads release the GIL) while the first stages compute, and a stage waits for it only to look up or to
    record its checkpoint.
    """

    def __init__(self, scene: Bundle, cfg: PipelineConfig, vocab: Vocabulary, known_hash: str | None = None) -> None:
        self._hash: Future[str]
        if known_hash is None:
            pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="hash-bundle")
            self._hash = pool.submit(hash_bundle, scene)
            pool.shutdown(wait=False)  # the one task runs on; nothing more is submitted
        else:
            self._hash = Future()
            self._hash.set_result(known_hash)
        self._cfg, self._vocab = cfg, vocab
        self._keys: dict[str, str] | None = None

    def ready(self) -> bool:
        """Whether the bundle's hash is done (the keys are then known without waiting)."""
        return self._hash.done()

    @property
    def input_hash(self) -> str:
        """The bundle's SHA-256 (waits for the hashing thread; raises what it raised)."""
        return self._hash.result()

    def _resolved(self) -> dict[str, str]:
        if self._keys is None:
            self._keys = st.stage_keys(self.input_hash, self._cfg, self._vocab)
        return self._keys

    def __getitem__(self, name: str) -> str:
        return self._resolved()[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._resolved())

    def __len__(self) -> int:
        return len(self._resolved())


def resolve_scene_vocabulary(scene: Bundle, spec: str | Vocabulary | None) -> Vocabulary:
    """The label set of a run: ``spec`` > the bundle's > ScanNet-20 for the CLIP space.

    ``spec`` is a built-in label-set name or an already parsed :class:`Vocabulary`; never a path, so that a
    service job cannot name a file of the worker's host (the CLI reads a ``--vocabulary FILE`` itself). Embeddings
    are added with the space's text encoder when the chosen vocabulary has none.
    """
    from panogs_core.errors import InputError
    from panogs_core.language.label_sets import builtin_vocabulary, ensure_embeddings

    if isinstance(spec, Vocabulary):
        vocabulary = spec
    elif spec is not None:
        vocabulary = builtin_vocabulary(spec, feature_space=scene.feature_space)
    elif scene.vocabulary is not None:
        vocabulary = scene.vocabulary
    elif scene.feature_space == "clip-vit-b32":
        vocabulary = builtin_vocabulary("scannet20", feature_space=scene.feature_space)
    else:
        raise InputError(
            f"{scene.root / 'scene.json'}: the bundle has no vocabulary.json and features.space "
            f"{scene.feature_space!r} has no default label set; pass a vocabulary "
            "(--vocabulary scannet20|matterport21|FILE)"
        )
    return ensure_embeddings(vocabulary, scene.feature_space, scene.feature_dim)


def run_pipeline(
    bundle: str | Path | Bundle,
    out_dir: str | Path,
    config: PipelineConfig | None = None,
    *,
    vocabulary: str | Vocabulary | None = None,
    on_progress: StageProgressFn | None = None,
    resume: bool = True,
    on_results: ResultsFn | None = None,
    shared: SharedCheckpoints | None = None,
) -> PipelineResult:
    """Run every stage on a bundle and write the outputs (docs/architecture.md, "Outputs of a run") into ``out_dir``.

    The results come first: every labelling stage runs, the label outputs, the initialisation's ``gaussians.ply``
    and ``report.json`` (``appearance.state`` ``running``) are written, ``on_results`` is called, and only then
    does the appearance fit run; its scene replaces ``gaussians.ply`` atomically and ``report.json`` is written
    again. A fit that raises leaves the results as they are: an error is recorded (``appearance.state``
    ``failed``, with ``error``) and the result returned; a stop (:class:`Cancelled`, Ctrl-C) is recorded as
    ``canceled`` and raised.

    Args:
        bundle: Bundle folder or archive, or an already opened :class:`Bundle`.
        out_dir: Output folder (created). Checkpoints go to ``out_dir/stages``.
        config: Pipeline settings; defaults to :class:`PipelineConfig()`.
        vocabulary: ``scannet20`` | ``matterport21`` | a :class:`Vocabulary` (e.g. a job's inline one, or the
            CLI's ``--vocabulary FILE`` read by the CLI); overrides the bundle's. Never a path.
        on_progress: ``on_progress(stage, done, total)``; may raise :class:`Cancelled` to stop.
        resume: Reuse checkpoints whose keys match.
        on_results: Called once the results are written, before the fit, with the result so far (its
            ``fit_state`` is ``running``); may raise :class:`Cancelled` to stop.
        shared: Checkpoints shared beyond ``out_dir`` (with ``resume``): fetched when this folder has none of a
            stage's key, given each checkpoint this run computes.

    Returns:
        The result summary; files are in ``out_dir``. ``appearance["state"]`` says how the fit ended.

    Raises:
        BundleError: the bundle is invalid (every problem listed).
        Cancelled: the progress callback asked to stop.
    """
    cfg = config or PipelineConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    runner = _Runner(out, resume, on_progress, shared)
    try:
        result = _run_stages(runner, bundle, out, cfg, vocabulary, on_results)
    except BaseException:
        runner.close(failing=True)
        raise
    runner.close()
    return result


def _run_stages(
    runner: _Runner,
    bundle: str | Path | Bundle,
    out: Path,
    cfg: PipelineConfig,
    vocabulary: str | Vocabulary | None,
    on_results: ResultsFn | None,
) -> PipelineResult:
    """:func:`run_pipeline`'s stages in order: the labelling, the results' files and ``on_results``, the fit."""
    t_start = time.perf_counter()

    scene = runner.step(
        "validate",
        lambda _: bundle if isinstance(bundle, Bundle) else open_bundle(bundle, workdir=BUNDLE_FOLDER.path(out)),
    )
    vocab = resolve_scene_vocabulary(scene, vocabulary)
    shared = runner.shared
    known_hash = None if shared is None else shared.known_input_hash()
    keys = _LazyKeys(scene, cfg, vocab, known_hash)
    hash_to_keep = shared is not None and known_hash is None  # this run hashes the bundle: the store keeps it once

    prims = runner.stage(st.PRIMITIVES, keys, lambda p: st.primitives(scene, cfg, p))
    result, colors, semantic, instance = _label_scene(runner, keys, scene, prims, cfg, vocab, out)

    def report() -> None:
        nonlocal hash_to_keep
        runner.record_checkpoints(keys, wait=True)
        if shared is not None and hash_to_keep:
            shared.keep_input_hash(keys.input_hash)
            hash_to_keep = False
        result.total_s = time.perf_counter() - t_start
        _write_report(out, scene, cfg, vocabulary, keys.input_hash, runner.timings, result.total_s, result)

    report()
    if on_results is not None:
        on_results(result)

    fit_snapshot = runner.checkpoints.snapshot(st.APPEARANCE.name, keys[st.APPEARANCE.name])
    try:
        gaussians = runner.stage(st.APPEARANCE, keys, lambda p: st.appearance(scene, prims, cfg, p, fit_snapshot))
    except (Cancelled, KeyboardInterrupt) as exc:
        if getattr(exc, "save_partial_work", True):  # a run that must write nothing more (lease lost) does not
            result.appearance = {"state": FIT_CANCELED, "error": _error_text(exc)}
            report()
        raise
    except Exception as exc:  # the fit's failure is the fit's: the results stand
        log.exception("the appearance fit failed; the results stand, gaussians.ply keeps the initialisation")
        result.appearance = {"state": FIT_FAILED, "error": _error_text(exc)}
        report()
        return result

    from panogs_core.stages.export import write_gaussians

    path = GAUSSIANS_PLY.path(out)
    tmp = path.with_name(f".{path.name}.tmp")
    write_gaussians(tmp, prims, colors, semantic, instance, gaussians)
    tmp.replace(path)  # atomic: a reader sees the initialisation or the fitted scene, never half of one
    result.appearance = {**gaussians.summary(), "state": FIT_SUCCEEDED if gaussians.fitted else FIT_SKIPPED}
    report()
    return result


def _label_scene(
    runner: _Runner,
    keys: _LazyKeys,
    scene: Bundle,
    prims: st.Primitives,
    cfg: PipelineConfig,
    vocab: Vocabulary,
    out: Path,
) -> tuple[PipelineResult, np.ndarray, np.ndarray, np.ndarray]:
    """The labelling stages and the results' files; returns the result and what the Gaussian scene's file needs
    (the primitives' colours, semantic and instance labels).

    Every stage output lives only as long as a later stage reads it: the fused features (161 MB at ScanNet size)
    once the field is fitted (the labelling reads their cosines with the classes), the visibility after the masks,
    the masks after the clustering, and the decoded features and segments when this returns, so the appearance
    fit runs without them.
    """
    from panogs_core.stages.export import primitive_colors, write_outputs

    vis = runner.stage(st.VISIBILITY, keys, lambda p: st.visibility(scene, prims, cfg, p))
    fused = runner.stage(st.FUSION, keys, partial(st.fusion, scene, vis, prims, cfg))
    field_ = None
    if cfg.features_source == "field":
        field_ = runner.stage(st.LANGUAGE_FIELD, keys, lambda p: st.language_field(prims, fused, cfg, p))
    features = st.primitive_features(field_, fused)
    # The (N, D) fused features are read no more: the labelling reads their (N, L) cosines, the export their
    # colours. Dropped here, they are never held beside the decoded ones (161 MB each at ScanNet size).
    evidence, fused = st.fused_evidence(fused, vocab), _colours_only(fused)
    masks = runner.stage(st.MASKS, keys, partial(st.masks, scene, vis, cfg))
    del vis
    knn = runner.stage(st.NEIGHBORS, keys, lambda _: st.neighbors(prims, cfg))
    sp = runner.stage(st.SUPERPRIMITIVES, keys, partial(st.superprimitives, prims, features, masks, knn, cfg))
    clusters = runner.stage(st.CLUSTERING, keys, partial(st.clustering, sp, knn, masks, features, cfg))
    del masks
    labels = runner.stage(
        st.LABELING, keys, lambda _: st.labeling(prims, features, evidence, sp, knn, clusters, vocab, cfg)
    )

    def export(_: ProgressFn) -> PipelineResult:
        # gaussians.ply is the initialisation here (the labels with the primitives' colours and scales), so that the
        # point views have what they read; the fit replaces it.
        files, metrics = write_outputs(out, scene, prims, fused, sp, clusters, labels, vocab, gaussians=None)
        return PipelineResult(
            appearance={"state": FIT_RUNNING},
            unseen=dict(labels.unseen),
            out_dir=out,
            scene_name=scene.name,
            num_primitives=int(prims.points.shape[0]),
            instances=[i.to_json() for i in labels.instances],
            timings=runner.timings,
            metrics=metrics,
            files=files,
        )

    result = runner.step("export", export)
    return result, primitive_colors(prims, fused), labels.semantic, labels.instance


def _colours_only(fused: st.FusedFeatures) -> st.FusedFeatures:
    """``fused`` without its features (an ``(N, 0)`` array): the weights, seen counts and colours stay."""
    return replace(fused, features=np.empty((fused.features.shape[0], 0), np.float32))


def _error_text(exc: BaseException) -> str:
    """``Type: message`` of an exception, for report.json and the job's fit error."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


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


def _write_report(
    out: Path,
    scene: Bundle,
    cfg: PipelineConfig,
    vocabulary_spec: str | Vocabulary | None,
    input_hash: str,
    timings: list[StageStats],
    total_s: float,
    result: PipelineResult,
) -> None:
    import torch

    from panogs_core.gaussians import resolve_schedule

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
        "vocabulary": vocabulary_label(vocabulary_spec, scene),
        "stages": stages,
        "total_wall_s": round(total_s, 3),
        "peak_rss_mb": round(lifetime_peak_rss_bytes() / 2**20, 1),
        "config": cfg.to_dict(),
        "versions": report_versions(),
    }
    REPORT_JSON.path(out).write_text(json.dumps(report, indent=2))
    result.files[REPORT_JSON.name] = REPORT_JSON.path(out)
