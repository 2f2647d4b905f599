"""The whole PanoGS pipeline: a scene bundle in, panoptic labels, instances and exports out.

``run_pipeline`` runs the stages of the stage table (:data:`panogs_core.pipeline.stage_table.PIPELINE`) in order;
docs/architecture.md has the table and the data each stage passes on. Each checkpointed stage goes through the
checkpoint store (:mod:`panogs_core.pipeline.checkpoints`), so a crashed job resumes from its last finished stage;
the report writer (:mod:`panogs_core.pipeline.report`) writes ``report.json``. The appearance fit also keeps
snapshots of its partial work (:mod:`panogs_core.snapshots`), so a run stopped in the middle of the fit resumes
there.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from contextlib import AbstractContextManager, nullcontext
from functools import partial
from pathlib import Path
from typing import Any

from panogs_core.errors import Cancelled
from panogs_core.io.bundle import Bundle
from panogs_core.io.run_folder import GAUSSIANS_PLY, STAGES_FOLDER
from panogs_core.pipeline import stage_table as st
from panogs_core.pipeline.beside import Beside, Made
from panogs_core.pipeline.checkpoints import CheckpointStore, SharedCheckpoints, StageKeys
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.input_hash import hash_bundle
from panogs_core.pipeline.lane import background_turn
from panogs_core.pipeline.profiling import StageStats, StageTimer
from panogs_core.pipeline.report import stage_rows, torch_devices, write_report
from panogs_core.pipeline.result import (
    FIT_CANCELED,
    FIT_FAILED,
    FIT_RUNNING,
    FIT_SKIPPED,
    FIT_STATES,
    FIT_SUCCEEDED,
    PipelineResult,
    ResultsFn,
    StageProgressFn,
)
from panogs_core.pipeline.stage_table import STAGES, resolve_scene_vocabulary
from panogs_core.progress import ProgressFn
from panogs_core.stages.maps2d import MapModels
from panogs_core.stages.maps2d.stage import forget_maps
from panogs_core.threads import decode_threads
from panogs_core.types import Vocabulary

# What the callers of a run import from here (the worker, the tiled run, the CLI, the benchmarks).
__all__ = [
    "FIT_CANCELED",
    "FIT_FAILED",
    "FIT_RUNNING",
    "FIT_SKIPPED",
    "FIT_STATES",
    "FIT_SUCCEEDED",
    "STAGES",
    "PipelineResult",
    "ResultsFn",
    "SharedCheckpoints",
    "StageProgressFn",
    "hash_bundle",
    "resolve_scene_vocabulary",
    "run_pipeline",
]

log = logging.getLogger(__name__)

# Values that outlive the last stage reading them: the report, the result and the fitted scene's file read them
# once the stages are done. (A value no stage reads is never dropped: the export's files, the colours.)
_KEPT = frozenset({"bundle", "primitives", "labeling"})


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


def _quiet(done: int, total: int) -> None:
    """The progress of a value derived between two stages: it reports none."""


def _last_readers(specs: Iterable[st.StageSpec]) -> dict[str, str]:
    """For each value, the stage after which no stage reads it (the run drops it there)."""
    last: dict[str, str] = {}
    for spec in specs:
        for name in spec.reads:
            last[name] = spec.name
    return last


class _Run:
    """One run's bookkeeping: the values the stages pass on, their timings, the checkpoint store and the keys."""

    def __init__(
        self,
        out: Path,
        cfg: PipelineConfig,
        values: dict[str, Any],
        *,
        resume: bool,
        on_progress: StageProgressFn | None,
        shared: SharedCheckpoints | None,
        input_hash: str | None = None,
    ) -> None:
        self.out, self.cfg, self.values = out, cfg, values
        self.input_hash = input_hash  # known to the caller: the bundle is not hashed
        self.on_progress = on_progress
        self.store = CheckpointStore(STAGES_FOLDER.path(out), resume, shared)
        self.timings: list[StageStats] = []
        self.keys: StageKeys | None = None
        self.hash_to_keep = False  # this run hashes the bundle: a shared store keeps the hash once
        self._drop_after = _last_readers(st.PIPELINE)
        # A run that reads no checkpoint back needs the bundle's hash only to record its checkpoints: it starts
        # hashing after the last stage that keeps every core busy, not beside it.
        self._hash_after = next((spec.name for spec in reversed(st.PIPELINE) if spec.every_core), None)
        self._beside: Beside | None = None  # the stages running beside a ``one_core`` stage

    def run_stages(self, specs: Iterable[st.StageSpec]) -> None:
        """Run ``specs`` in order, each writing its value; drop each value after its last reader. A ``one_core``
        stage first starts the later stages that can run beside it (:class:`Beside`)."""
        specs = list(specs)
        for at, spec in enumerate(specs):
            if self._beside is not None and spec.name in self._beside:
                self.values[spec.output] = self._take_beside(spec)
            elif spec.runs(self.cfg):
                if spec.one_core:
                    self._start_beside(spec, specs[at + 1 :])
                self.values[spec.output] = self._run(spec, specs[at + 1 :])
            else:
                self.values[spec.output] = None
            for name, last in self._drop_after.items():
                if last == spec.name and name not in _KEPT:
                    self.values.pop(name, None)
            self._start_keys()
            if self.keys is not None and spec.name == self._hash_after:
                self.keys.start()

    def settle(self) -> None:
        """Wait for the stages running beside (a failing run must not close the store under them)."""
        if self._beside is not None:
            self._beside.wait()

    def _start_beside(self, leader: st.StageSpec, later: list[st.StageSpec]) -> None:
        """Start, beside ``leader``, the later stages whose inputs are made now or by a stage started before them;
        none in a process given one thread (``--threads 1``, a tile's share of the cores): no core is left idle."""
        if decode_threads() < 2:
            return
        made = set(self.values)
        chosen = []
        for spec in later:
            if spec.may_run_beside(self.cfg) and all(name in made for name in spec.reads):
                chosen.append(spec)
                made.add(spec.output)
        if chosen:
            inputs = {name: self.values[name] for spec in chosen for name in spec.reads if name in self.values}
            self._beside = Beside(leader.name, chosen, inputs, partial(self._compute, turn=background_turn))

    def _take_beside(self, spec: st.StageSpec) -> Any:
        """The value of a stage made beside, at its place: its progress sent (done) and its row kept in order."""
        assert self._beside is not None
        value, stats = self._beside.take(spec.name)
        if stats is not None:
            progress = _StageProgress(spec.name, self.on_progress)
            progress(0, 1)
            progress.finish()
            self.timings.append(stats)
        return value

    def _run(self, spec: st.StageSpec, later: list[st.StageSpec]) -> Any:
        value, stats = self._compute(spec, self._arguments(spec, later), self.on_progress)
        if stats is not None:
            self.timings.append(stats)
        return value

    def _arguments(self, spec: st.StageSpec, later: list[st.StageSpec]) -> list[Any]:
        """The values ``spec`` reads; those it takes in a :class:`~panogs_core.pipeline.stage_table.Handover`,
        which is the run's only reference to one no later stage on this thread reads (the stages made beside hold
        their own): the stage frees it by taking it out."""
        if not spec.takes:
            return [self.values[name] for name in spec.reads]
        read_later = {
            name
            for later_spec in later
            if later_spec.runs(self.cfg) and not (self._beside is not None and later_spec.name in self._beside)
            for name in later_spec.reads
        }
        args = []
        for name in spec.reads:
            if name not in spec.takes:
                args.append(self.values[name])
            elif name in read_later or name in _KEPT:
                args.append(st.Handover(self.values[name]))
            else:
                args.append(st.Handover(self.values.pop(name)))
        return args

    def _compute(
        self,
        spec: st.StageSpec,
        args: list[Any],
        sink: StageProgressFn | None,
        turn: Callable[[], AbstractContextManager[Any]] = nullcontext,
    ) -> Made:
        """The stage's value (from its checkpoint, or computed and its checkpoint written) and, for a timed stage,
        what it cost; its progress goes to ``sink``. The computation itself runs inside ``turn()`` (a stage made
        beside takes a turn on the background lane for it, not for its checkpoint's look-up: :mod:`.lane`)."""

        def call(*more: Any, **named: Any) -> Any:  # the stage's own computation, in its turn
            with turn():
                return spec.call(*args, self.cfg, *more, **named)

        if not spec.timed:
            return call(_quiet), None
        extra: dict[str, Any] = {}
        if spec.resumable:
            extra["snapshot"] = self.store.snapshot(spec.name, self._keys()[spec.name])
        if spec.load is None:
            if spec.own_checkpoint:
                return self._timed(spec.name, sink, lambda rep, stats: call(rep, stats=stats))
            return self._timed(spec.name, sink, lambda report, _: call(report, **extra))

        def load_or_compute(report: ProgressFn, stats: StageStats) -> Any:
            def compute() -> Any:
                return call(report, **extra)

            return self.store.load_or_compute(spec, self._keys(), compute, stats)

        return self._timed(spec.name, sink, load_or_compute)

    def _timed(
        self, name: str, sink: StageProgressFn | None, body: Callable[[ProgressFn, StageStats], Any]
    ) -> tuple[Any, StageStats]:
        report = _StageProgress(name, sink)
        with StageTimer(name) as timer:
            report(0, 1)
            result = body(report, timer.stats)
            report.finish()
        log.info(
            "stage %s: %.2f s, peak %.0f MB%s",
            name,
            timer.stats.wall_s,
            timer.stats.peak_rss_mb,
            " (checkpoint)" if timer.stats.cached else "",
        )
        return result, timer.stats

    def _start_keys(self) -> None:
        """Make the stages' keys once the bundle and the label set are known (a shared store may know the bundle's
        hash already). The hashing starts now if a checkpoint may be read back, else after ``_hash_after``."""
        if self.keys is not None or self.values.get("bundle") is None or self.values.get("vocabulary") is None:
            return
        shared = self.store.shared
        known_hash = self.input_hash or (None if shared is None else shared.known_input_hash())
        # With checkpoints to look up, every stage needs its key: hash now. Else the hash waits for the cores.
        start = self.store.may_reuse()
        self.keys = StageKeys(self.values["bundle"], self.cfg, self.values["vocabulary"], known_hash, start=start)
        self.hash_to_keep = shared is not None and known_hash is None

    def _keys(self) -> StageKeys:
        assert self.keys is not None, "a stage with a key runs before the bundle and the vocabulary are known"
        return self.keys

    def report(
        self, result: PipelineResult, vocabulary_spec: str | Vocabulary | None, t_start: float, *, results: bool = False
    ) -> None:
        """Write ``report.json`` once every pending checkpoint is written; recorded too, unless ``results``.

        The results' report (``results``) waits for no bundle hash: the hash only names the checkpoints for a later
        run, it runs at a lower priority, and on a busy machine it could hold the results back for many seconds
        (its ``input_sha256`` is then null). Every later report, the run's last among them, waits for it.
        """
        keys = self._keys()
        if results:
            self.store.flush()
            self.store.record_checkpoints(keys, wait=False)  # those the hash is known for already
            result.results_s = time.perf_counter() - t_start  # the results are out once their report is written
        else:
            self.store.record_checkpoints(keys, wait=True)
        input_hash = keys.input_hash if keys.ready() else None
        shared = self.store.shared
        if shared is not None and self.hash_to_keep and input_hash is not None:
            shared.keep_input_hash(input_hash)
            self.hash_to_keep = False
        result.total_s = time.perf_counter() - t_start
        scene: Bundle = self.values["bundle"]
        rows = stage_rows(self.timings, torch_devices(scene, self.cfg))
        write_report(self.out, scene, self.cfg, vocabulary_spec, input_hash, result, rows)


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
    map_models: MapModels | None = None,
    input_hash: str | None = None,
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
        resume: Reuse checkpoints whose keys match (the computed 2D maps too; without, they are removed).
        on_results: Called once the results are written, before the fit, with the result so far (its
            ``fit_state`` is ``running``); may raise :class:`Cancelled` to stop.
        shared: Checkpoints shared beyond ``out_dir`` (with ``resume``): fetched when this folder has none of a
            stage's key, given each checkpoint this run computes.
        map_models: The models that compute the 2D maps the bundle lacks (docs/method.md §17); None, or None for
            a kind: the bundle must bring it. A kind the bundle brings is never recomputed.
        input_hash: A hash known to name the bundle's bytes, used instead of hashing them (a tile's: made from its
            scene's hash and the tile, :func:`panogs_core.tiling.tile.tile_input_hash`); None: the bundle is hashed
            (or ``shared`` knows it).

    Returns:
        The result summary; files are in ``out_dir``. ``appearance["state"]`` says how the fit ended.

    Raises:
        BundleError: the bundle is invalid (every problem listed).
        InputError: the bundle lacks a kind of map and no model is named to compute it.
        ModelLoadError: a model of ``map_models`` does not load (before any frame is computed).
        Cancelled: the progress callback asked to stop.
    """
    cfg = config or PipelineConfig()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if not resume:
        forget_maps(STAGES_FOLDER.path(out))
    values: dict[str, Any] = {"source": bundle, "out": out, "vocabulary_spec": vocabulary, "map_models": map_models}
    run = _Run(out, cfg, values, resume=resume, on_progress=on_progress, shared=shared, input_hash=input_hash)
    values["shared"] = run.store.shared  # None without resume: nothing is then fetched
    try:
        result = _run_stages(run, vocabulary, on_results)
    except BaseException:
        run.settle()
        run.store.close(failing=True)
        raise
    run.store.close()
    return result


def _run_stages(run: _Run, vocabulary: str | Vocabulary | None, on_results: ResultsFn | None) -> PipelineResult:
    """:func:`run_pipeline`'s stages in order: the labelling, the results' files and ``on_results``, the fit."""
    t_start = time.perf_counter()
    run.run_stages(spec for spec in st.PIPELINE if not spec.after_results)
    result = _results(run)
    run.report(result, vocabulary, t_start, results=True)
    if on_results is not None:
        on_results(result)

    try:
        run.run_stages(spec for spec in st.PIPELINE if spec.after_results)
    except (Cancelled, KeyboardInterrupt) as exc:
        if getattr(exc, "save_partial_work", True):  # a run that must write nothing more (lease lost) does not
            result.appearance = {"state": FIT_CANCELED, "error": _error_text(exc)}
            run.report(result, vocabulary, t_start)
        raise
    except Exception as exc:  # the fit's failure is the fit's: the results stand
        log.exception("the appearance fit failed; the results stand, gaussians.ply keeps the initialisation")
        result.appearance = {"state": FIT_FAILED, "error": _error_text(exc)}
        run.report(result, vocabulary, t_start)
        return result

    gaussians = run.values["appearance"]
    _replace_gaussians(run)
    result.appearance = {**gaussians.summary(), "state": FIT_SUCCEEDED if gaussians.fitted else FIT_SKIPPED}
    run.report(result, vocabulary, t_start)
    return result


def _results(run: _Run) -> PipelineResult:
    """The result once the results' files are written (the fit still to come)."""
    labels, prims = run.values["labeling"], run.values["primitives"]
    files, metrics = run.values["export"]
    return PipelineResult(
        appearance={"state": FIT_RUNNING},
        unseen=dict(labels.unseen),
        out_dir=run.out,
        scene_name=run.values["bundle"].name,
        num_primitives=int(prims.points.shape[0]),
        instances=[i.to_json() for i in labels.instances],
        timings=run.timings,
        metrics=metrics,
        files=files,
    )


def _replace_gaussians(run: _Run) -> None:
    """The fitted scene in place of the initialisation's ``gaussians.ply``."""
    from panogs_core.stages.export import write_gaussians

    values = run.values
    labels = values["labeling"]
    path = GAUSSIANS_PLY.path(run.out)
    tmp = path.with_name(f".{path.name}.tmp")
    write_gaussians(tmp, values["primitives"], values["colours"], labels.semantic, labels.instance,
                    values["appearance"])  # fmt: skip
    tmp.replace(path)  # atomic: a reader sees the initialisation or the fitted scene, never half of one


def _error_text(exc: BaseException) -> str:
    """``Type: message`` of an exception, for report.json and the job's fit error."""
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__
