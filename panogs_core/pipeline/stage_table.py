"""The stage table: every stage of a run, in order, with how it is called and what its checkpoint key covers.

:func:`panogs_core.pipeline.run.run_pipeline` reads :data:`PIPELINE` and nothing else to know the stages, their
order and their calls; adding a stage is adding its entry here. Importing this module imports the stage modules,
which are light (numpy, scipy): each imports torch or open3d only inside the function that needs it, so a stage's
heavy imports still happen only when that stage runs.

A stage is a :class:`StageSpec`: its name, the values of the run it reads (the bundle, the vocabulary, the outputs
of the stages before it) and the one it writes, its call, and for a checkpointed stage how its output is read back
and what its key covers, namely the keys of the stages it reads and exactly the settings it reads (never a whole
config section that other stages share), so that changing one stage's setting redoes that stage and those after
it, no more. The run drops each value after the last stage that reads it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Generic, Protocol, TypeVar

import numpy as np

from panogs_core.errors import InputError
from panogs_core.gaussians import GaussianScene, fit_appearance
from panogs_core.heap import return_freed_heap
from panogs_core.io.bundle import Bundle, open_bundle
from panogs_core.io.run_folder import BUNDLE_FOLDER, STAGES_FOLDER
from panogs_core.language.label_sets import builtin_vocabulary, ensure_embeddings
from panogs_core.language.model_identity import resolve_model_dir
from panogs_core.language.text_encoders import get_text_encoder, is_model_space
from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.profiling import StageStats
from panogs_core.progress import ProgressFn
from panogs_core.snapshots import StageSnapshot
from panogs_core.stages.affinity import AffinityConfig, segment_affinity
from panogs_core.stages.clustering import Clusters, progressive_clustering
from panogs_core.stages.fusion import FusedFeatures, fuse_features
from panogs_core.stages.labeling import (
    FusedEvidence,
    NearestSeen,
    PanopticLabels,
    assign_panoptic,
    nearest_seen,
    unit_embeddings,
)
from panogs_core.stages.language_field import LanguageField, finish_language_field, set_up_language_field
from panogs_core.stages.maps2d import MapModels
from panogs_core.stages.maps2d.stage import SharedFolders, with_computed_maps
from panogs_core.stages.masks import MaskObservations, observe_masks
from panogs_core.stages.neighbors import KnnGraph, build_knn
from panogs_core.stages.primitives import Primitives, build_primitives
from panogs_core.stages.superprimitives import SuperPrimitives, graph_cut_superprimitives
from panogs_core.stages.visibility import Visibility, compute_visibility
from panogs_core.types import Vocabulary

# The values a run starts with: the ``bundle`` argument (a path or an opened bundle), the run folder and the
# ``vocabulary`` argument. Every other value is written by a stage of the table.
RUN_ARGUMENTS = ("source", "out", "vocabulary_spec", "map_models", "shared")


class Checkpoint(Protocol):
    """A stage output that writes itself to one ``.npz`` (its class's ``load`` reads it back)."""

    def save(self, path: Path) -> None: ...


KeyFn = Callable[[Mapping[str, str], PipelineConfig], str]
T = TypeVar("T")


class Handover(Generic[T]):
    """A value handed to a stage that takes it (``StageSpec.takes``): the stage takes it out once (:meth:`take`)
    and keeps it only as long as it needs it. Where no later stage on the run's thread reads the value, the run
    keeps no reference of its own, so that the value is freed then (the fused features once the field's training
    set is built, before its decoding makes as many bytes again)."""

    def __init__(self, value: T) -> None:
        self._value: T | None = value
        self._taken = False

    def take(self) -> T:
        """The value; the box holds it no more."""
        if self._taken:
            raise RuntimeError("a handed-over value is taken once")
        value, self._value, self._taken = self._value, None, True
        return value  # type: ignore[return-value]  # None only after the one take


@dataclass(frozen=True)
class StageSpec:
    """One entry of the stage table.

    Attributes:
        name: The stage's name in ``STAGES``, progress, ``report.json`` and ``stages/manifest.json``.
        call: ``call(*values, cfg, progress)``: the values named by ``reads``, in order, then the pipeline config
            and the stage's progress callback; returns the value the stage writes.
        reads: The values it takes: ``source``, ``out``, ``vocabulary_spec`` (:data:`RUN_ARGUMENTS`) or what an
            entry before it writes.
        writes: The value it writes (default: its name). A stage that writes a value an earlier one wrote
            replaces it for the stages after it.
        timed: A stage of ``STAGES``: timed, reported in ``report.json``, its progress sent. False for a value
            derived between two stages (the features the labelling reads, the fused colours), which is neither.
        when: Runs only when this says so of the config; else its value is None and it is not reported.
        after_results: Runs after the results are written and ``on_results`` is called (the appearance fit): its
            failure leaves the results (``appearance.state`` ``failed``).
        every_core: Keeps every core busy (frames decoded ahead on threads): a run with no checkpoint to read back
            starts hashing the bundle only after the last such stage (the hash would take their cycles).
        one_core: Keeps one core busy for long and leaves the others idle (the language field's fit, one torch
            thread): the later stages whose inputs are all made already (:meth:`may_run_beside`) run beside it, in
            table order, on one thread of their own; each is taken at its own place in the table, where its
            progress is sent and its error raised. Such a stage must not change torch's thread count (the
            process's: the fit's bits depend on it).
        resumable: Takes ``snapshot=`` (:class:`StageSnapshot`), to keep and resume its partial work.
        own_checkpoint: Keeps its own checkpoint (not a ``load``ed file): takes ``stats=`` (:class:`StageStats`)
            and sets ``stats.cached`` when it reused it rather than computed.
        load: A checkpointed stage's reader of its checkpoint (the output class's ``load``); None: no checkpoint.
        inputs: The keys its key includes: upstream stages, or ``"input"`` (the bundle's hash), ``"features"``
            (the per-primitive language features, see :func:`primitive_features`), ``"vocabulary"``.
        settings: Exactly the settings the stage reads, from the pipeline config (with ``inputs``, its key).
        key_of: A key made otherwise than from ``inputs`` and ``settings`` (the features': the field's or the
            fusion's, by ``features_source``).
        takes: Of ``reads``, the values it is handed in a :class:`Handover` rather than given: the run drops its
            own reference when no later stage on the run's thread reads the value (stages made beside hold their
            own), so the stage frees it by taking it out once it has what it needs.
    """

    name: str
    call: Callable[..., Any]
    reads: tuple[str, ...]
    writes: str = ""
    timed: bool = True
    when: Callable[[PipelineConfig], bool] | None = None
    after_results: bool = False
    every_core: bool = False
    one_core: bool = False
    resumable: bool = False
    own_checkpoint: bool = False
    load: Callable[[Path], Any] | None = None
    inputs: tuple[str, ...] = ()
    settings: Callable[[PipelineConfig], object] | None = None
    key_of: KeyFn | None = None
    takes: tuple[str, ...] = ()

    @property
    def output(self) -> str:
        """The name of the value it writes."""
        return self.writes or self.name

    def runs(self, cfg: PipelineConfig) -> bool:
        return self.when is None or self.when(cfg)

    def may_run_beside(self, cfg: PipelineConfig) -> bool:
        """Whether it may run beside a ``one_core`` stage before its place: a plain stage that runs, replaces no
        earlier value, keeps no partial work of its own and comes before the results."""
        plain = not (self.writes or self.after_results or self.resumable or self.own_checkpoint)
        return plain and self.runs(cfg)

    def key(self, keys: Mapping[str, str], cfg: PipelineConfig) -> str | None:
        """Its key: a hash of the input keys and the settings; None for a stage without one."""
        if self.key_of is not None:
            return self.key_of(keys, cfg)
        if self.settings is None:
            return None
        return _key(*(keys[name] for name in self.inputs), self.settings(cfg))


def _affinity_measure(cfg: AffinityConfig) -> dict[str, object]:
    """The affinity settings the clustering reads: all but the two the mask look-ups read (same YAML section)."""
    return {f.name: getattr(cfg, f.name) for f in dataclasses.fields(cfg) if not f.name.startswith("mask_")}


def _plain(obj: object) -> object:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return dataclasses.asdict(obj)
    return str(obj)


def _key(*parts: object) -> str:
    blob = json.dumps(parts, sort_keys=True, default=_plain).encode()
    return hashlib.sha256(blob).hexdigest()[:20]


def _vocabulary_hash(vocab: Vocabulary) -> str:
    digest = hashlib.sha256(json.dumps([vocab.names, vocab.kinds]).encode())
    if vocab.embeddings is not None:
        digest.update(np.ascontiguousarray(vocab.embeddings, dtype=np.float32).tobytes())
    return digest.hexdigest()[:20]


def stage_keys(input_hash: str, cfg: PipelineConfig, vocab: Vocabulary, maps: str = "bundle") -> dict[str, str]:
    """Checkpoint key of every stage that has one (and of the inputs they name), in table order.

    ``maps``: the key of the maps the 2D-maps stage computed ("bundle" when every map is the bundle's, which
    ``input_hash`` covers); the stages reading maps name it among their inputs."""
    keys = {"input": input_hash, "vocabulary": _vocabulary_hash(vocab), "maps_2d": maps}
    for spec in PIPELINE:
        key = spec.key(keys, cfg)
        if key is not None:
            keys[spec.name] = key
    return keys


def resolve_scene_vocabulary(
    scene: Bundle, spec: str | Vocabulary | None, map_models: MapModels | None = None
) -> Vocabulary:
    """The label set of a run: ``spec`` > the bundle's > ScanNet-20 for a CLIP space.

    ``spec`` is a built-in label-set name or an already parsed :class:`Vocabulary`; never a path, so that a
    service job cannot name a file of the worker's host (the CLI reads a ``--vocabulary FILE`` itself). Embeddings
    are added with the space's text encoder when the chosen vocabulary has none: for feature maps the 2D-maps
    stage computed, the text tower of the features model that computed them (``map_models.features``).
    """
    if isinstance(spec, Vocabulary):
        vocabulary = spec
    elif spec is not None:
        vocabulary = builtin_vocabulary(spec, feature_space=scene.feature_space)
    elif scene.vocabulary is not None:
        vocabulary = scene.vocabulary
    elif scene.feature_space == "clip-vit-b32" or is_model_space(scene.feature_space):
        vocabulary = builtin_vocabulary("scannet20", feature_space=scene.feature_space)
    else:
        raise InputError(
            f"{scene.root / 'scene.json'}: the bundle has no vocabulary.json and features.space "
            f"{scene.feature_space!r} has no default label set; pass a vocabulary "
            "(--vocabulary scannet20|matterport21|FILE)"
        )
    encoder = None
    computed = scene.computed
    if computed is not None and computed.serves("features") and vocabulary.embeddings is None:
        assert map_models is not None
        assert map_models.features is not None
        folder = resolve_model_dir(map_models.features, allow_download=map_models.allow_download)
        encoder = get_text_encoder(scene.feature_space, model_path=str(folder))
    return ensure_embeddings(vocabulary, scene.feature_space, scene.feature_dim, encoder=encoder)


def validate(source: str | Path | Bundle, out: Path, cfg: PipelineConfig, progress: ProgressFn) -> Bundle:
    """The bundle, opened and validated (an archive extracted into the run folder's ``bundle/``)."""
    return source if isinstance(source, Bundle) else open_bundle(source, workdir=BUNDLE_FOLDER.path(out))


def maps_2d(
    bundle: Bundle,
    out: Path,
    models: MapModels | None,
    shared: SharedFolders | None,
    cfg: PipelineConfig,
    progress: ProgressFn,
    stats: StageStats,
) -> Bundle:
    """The bundle with the 2D maps it lacks computed by ``models`` (itself, at once, when it lacks none); maps
    this run folder or the shared store already has are reused (``stats.cached``)."""

    def reused() -> None:
        stats.cached = True

    return with_computed_maps(
        bundle, STAGES_FOLDER.path(out), cfg.maps2d, models, progress, shared=shared, on_reused=reused
    )


def primitives(bundle: Bundle, cfg: PipelineConfig, progress: ProgressFn) -> Primitives:

    return build_primitives(bundle, cfg.primitives, on_progress=progress)


def appearance(
    bundle: Bundle, prims: Primitives, cfg: PipelineConfig, progress: ProgressFn, snapshot: StageSnapshot | None = None
) -> GaussianScene:
    """The Gaussian scene fitted to the colour frames, from the primitives' colours (grey where they have none:
    fused colours come later, and the fit learns the colour anyway)."""
    colors = prims.colors if prims.colors is not None else np.full((prims.points.shape[0], 3), 0.5, np.float32)
    return fit_appearance(bundle, prims, colors, cfg.appearance, on_progress=progress, snapshot=snapshot)


def visibility(bundle: Bundle, prims: Primitives, cfg: PipelineConfig, progress: ProgressFn) -> Visibility:

    return compute_visibility(bundle, prims.points, cfg.visibility, on_progress=progress)


def fusion(
    bundle: Bundle, vis: Visibility, prims: Primitives, cfg: PipelineConfig, progress: ProgressFn
) -> FusedFeatures:
    """The fused features; colours only for primitives that have none of their own (the export reads the
    geometry's first, so fusing them would read every colour frame for nothing). The input's hash, in the key,
    says which."""
    settings = cfg.fusion if prims.colors is None else dataclasses.replace(cfg.fusion, fuse_colors=False)
    fused = fuse_features(bundle, vis, int(prims.points.shape[0]), settings, on_progress=progress)
    return_freed_heap()  # the maps its threads read stay resident once freed, else: the field's peak comes next
    return fused


def language_field(
    prims: Primitives, fused: Handover[FusedFeatures], cfg: PipelineConfig, progress: ProgressFn
) -> LanguageField:
    """The fitted field. It takes the fused features (``StageSpec.takes``) and holds them only while its training
    set is built: with the scene's basis that set holds their coefficients, so the decoding's ``(N, D)`` output is
    not made beside the fused ``(N, D)`` features (161 MB each at ScanNet size)."""
    setup = set_up_language_field(prims.points, fused.take(), cfg.language_field)
    return finish_language_field(setup, on_progress=progress)


def unit_fused_rows(fused: FusedFeatures) -> np.ndarray:  # (N, D) float32, unit rows
    """The fused means as unit rows: the language features downstream when no field is fitted."""
    feats = np.asarray(fused.features, dtype=np.float32)
    norms = np.linalg.norm(feats, axis=1, keepdims=True)
    return feats / np.maximum(norms, 1e-12)


def primitive_features(field: LanguageField | None, fused_rows: np.ndarray | None) -> np.ndarray:  # (N, D) unit
    """The per-primitive language features used downstream: the decoded field, or (no field) the fused means."""
    if field is not None:
        return np.asarray(field.features, dtype=np.float32)
    assert fused_rows is not None, "no field and no fused rows"
    return fused_rows


def fused_evidence(fused: FusedFeatures, vocab: Vocabulary) -> FusedEvidence:
    """What the labelling reads of the fused features (``(N, L)`` cosines and the seen rows), so that the pipeline
    can drop the ``(N, D)`` features once the field is fitted."""
    return FusedEvidence.of(np.asarray(fused.features, np.float32), unit_embeddings(vocab))


def masks(bundle: Bundle, vis: Visibility, cfg: PipelineConfig, progress: ProgressFn) -> MaskObservations:

    return observe_masks(bundle, vis, cfg.affinity.mask_lookup(), on_progress=progress)


def neighbors(prims: Primitives, cfg: PipelineConfig, progress: ProgressFn | None = None) -> KnnGraph:
    """The kNN graph (``progress``: the table passes every stage one; this one reports no steps of its own)."""
    return build_knn(prims.points, cfg.superprimitives.k_neighbors)


def superprimitives(
    prims: Primitives,
    features: np.ndarray,
    observations: MaskObservations,
    knn: KnnGraph,
    cfg: PipelineConfig,
    progress: ProgressFn,
) -> SuperPrimitives:

    feats = features if cfg.superprimitives.use_language else None
    return graph_cut_superprimitives(
        prims.points, prims.normals, feats, knn, cfg.superprimitives, masks=observations, on_progress=progress
    )


def clustering(
    sp: SuperPrimitives,
    knn: KnnGraph,
    observations: MaskObservations,
    features: np.ndarray,
    cfg: PipelineConfig,
    progress: ProgressFn,
) -> Clusters:

    affinity = segment_affinity(sp.labels, observations, cfg.affinity, features=features)
    return progressive_clustering(sp, knn, affinity, cfg.clustering, on_progress=progress)


def labeling(
    prims: Primitives,
    features: np.ndarray,
    fused: FusedEvidence,
    sp: SuperPrimitives,
    knn: KnnGraph,
    clusters: Clusters,
    vocab: Vocabulary,
    nearest: NearestSeen | None,
    cfg: PipelineConfig,
    progress: ProgressFn | None = None,
) -> PanopticLabels:
    """The panoptic labels (``progress``: the table passes every stage one; this one reports no steps of its own)."""
    return assign_panoptic(
        prims.points,
        features,
        sp,
        clusters,
        vocab,
        cfg.labeling,
        neighbors=knn.neighbors,
        fused=fused,
        nearest=nearest,
    )


def fused_colours(fused: FusedFeatures) -> FusedFeatures:
    """``fused`` without its features (an ``(N, 0)`` array): the weights, seen counts and colours stay.

    What the export reads of the fusion once the labelling has its cosines: the ``(N, D)`` fused features are
    then dropped, never held beside the decoded ones (161 MB each at ScanNet size)."""
    return dataclasses.replace(fused, features=np.empty((fused.features.shape[0], 0), np.float32))


def export(
    out: Path,
    bundle: Bundle,
    prims: Primitives,
    fused: FusedFeatures,
    sp: SuperPrimitives,
    clusters: Clusters,
    labels: PanopticLabels,
    vocab: Vocabulary,
    cfg: PipelineConfig,
    progress: ProgressFn,
) -> tuple[dict[str, Path], dict[str, Any] | None]:
    """The results' files and the metrics (with ground truth). ``gaussians.ply`` is the initialisation here (the
    labels with the primitives' colours and scales), so that the point views have what they read; the fit
    replaces it."""
    from panogs_core.stages.export import write_outputs

    return write_outputs(out, bundle, prims, fused, sp, clusters, labels, vocab, gaussians=None)


def gaussian_colours(prims: Primitives, fused: FusedFeatures) -> np.ndarray:  # (N, 3) float32
    """The primitives' colours, as the Gaussian scene's file takes them (the geometry's, else the fused ones)."""
    from panogs_core.stages.export import primitive_colors

    return primitive_colors(prims, fused)


def _features_key(keys: Mapping[str, str], cfg: PipelineConfig) -> str:
    """The features' key: the field's, or the fusion's when ``features_source`` is ``fused``."""
    return _key(keys["language_field" if cfg.features_source == "field" else "fusion"], cfg.features_source)


def _fits_field(cfg: PipelineConfig) -> bool:
    return cfg.features_source == "field"


# The stages of a run, in order. The results (labels, instances, queries, the point views) are written by "export";
# the appearance fit comes after them, since the labels do not depend on it, and replaces the initialisation's
# gaussians.ply when it ends. Every value is dropped after the last entry that reads it: the fused features once
# the field is fitted, the visibility after the masks, the masks after the clustering, the decoded features and the
# segments after the export, so the appearance fit runs without them.
PIPELINE: tuple[StageSpec, ...] = (
    StageSpec("validate", validate, ("source", "out"), writes="bundle"),
    # The maps the bundle lacks, computed from its colour frames (its own checkpoint folder, keyed by the models'
    # identities, the frames and the maps' settings); the stages after it read the bundle it writes.
    StageSpec("maps_2d", maps_2d, ("bundle", "out", "map_models", "shared"), writes="bundle", own_checkpoint=True),
    StageSpec(
        "vocabulary",
        lambda bundle, spec, models, _c, _p: resolve_scene_vocabulary(bundle, spec, models),
        ("bundle", "vocabulary_spec", "map_models"),
        timed=False,
    ),
    StageSpec(
        "primitives",
        primitives,
        ("bundle",),
        every_core=True,
        load=Primitives.load,
        inputs=("input",),
        settings=lambda c: c.primitives,
    ),
    # "with-depth-residual": checkpoints written before Visibility carried depth residuals must not be reused.
    StageSpec(
        "visibility",
        visibility,
        ("bundle", "primitives"),
        every_core=True,
        load=Visibility.load,
        inputs=("primitives",),
        settings=lambda c: (c.visibility, "with-depth-residual"),
    ),
    StageSpec(
        "fusion",
        fusion,
        ("bundle", "visibility", "primitives"),
        every_core=True,
        load=FusedFeatures.load,
        inputs=("visibility", "maps_2d"),
        settings=lambda c: c.fusion,
    ),
    # The features downstream when no field is fitted (``features_source: fused``); made before the field, so that
    # the field's stage is the last on the run's thread to read the fused features and takes them (``takes``).
    StageSpec(
        "fused_rows",
        lambda fused, _c, _p: unit_fused_rows(fused),
        ("fusion",),
        timed=False,
        when=lambda c: not _fits_field(c),
    ),
    StageSpec(
        "language_field",
        language_field,
        ("primitives", "fusion"),
        when=_fits_field,
        one_core=True,
        load=LanguageField.load,
        inputs=("fusion",),
        settings=lambda c: c.language_field,
        takes=("fusion",),
    ),
    StageSpec(
        "features",
        lambda field, fused_rows, _c, _p: primitive_features(field, fused_rows),
        ("language_field", "fused_rows"),
        timed=False,
        key_of=_features_key,
    ),
    StageSpec(
        "evidence", lambda fused, vocab, _c, _p: fused_evidence(fused, vocab), ("fusion", "vocabulary"), timed=False
    ),
    StageSpec("fused_colours", lambda fused, _c, _p: fused_colours(fused), ("fusion",), timed=False),
    StageSpec(
        "masks",
        masks,
        ("bundle", "visibility"),
        load=MaskObservations.load,
        inputs=("visibility", "maps_2d"),
        settings=lambda c: c.affinity.mask_lookup(),
    ),
    StageSpec(
        "neighbors",
        neighbors,
        ("primitives",),
        load=KnnGraph.load,
        inputs=("primitives",),
        settings=lambda c: c.superprimitives.k_neighbors,
    ),
    # The labelling's first search for the unseen primitives (``labeling.unseen`` ``segment-field``): it reads no
    # value of the field, so it is made beside the field's fit (``one_core``).
    StageSpec(
        "nearest_seen",
        lambda prims, knn, evidence, _c, _p: nearest_seen(prims.points, knn.neighbors, ~evidence.seen),
        ("primitives", "neighbors", "evidence"),
        timed=False,
        when=lambda c: c.labeling.unseen == "segment-field",
    ),
    StageSpec(
        "superprimitives",
        superprimitives,
        ("primitives", "features", "masks", "neighbors"),
        load=SuperPrimitives.load,
        inputs=("primitives", "features", "masks", "neighbors"),
        settings=lambda c: c.superprimitives,
    ),
    StageSpec(
        "clustering",
        clustering,
        ("superprimitives", "neighbors", "masks", "features"),
        load=Clusters.load,
        inputs=("superprimitives", "neighbors", "masks", "features"),
        settings=lambda c: (c.clustering, _affinity_measure(c.affinity)),
    ),
    StageSpec(
        "labeling",
        labeling,
        (
            "primitives",
            "features",
            "evidence",
            "superprimitives",
            "neighbors",
            "clustering",
            "vocabulary",
            "nearest_seen",
        ),
        load=PanopticLabels.load,
        inputs=("clustering", "superprimitives", "neighbors", "features", "fusion", "vocabulary"),
        settings=lambda c: c.labeling,
    ),
    StageSpec(
        "export",
        export,
        ("out", "bundle", "primitives", "fused_colours", "superprimitives", "clustering", "labeling", "vocabulary"),
    ),
    StageSpec(
        "colours",
        lambda prims, fused, _c, _p: gaussian_colours(prims, fused),
        ("primitives", "fused_colours"),
        timed=False,
    ),
    # Reads the colour frames (covered by "input" through the primitives' key) and its own settings.
    StageSpec(
        "appearance",
        appearance,
        ("bundle", "primitives"),
        after_results=True,
        resumable=True,
        load=GaussianScene.load,
        inputs=("primitives",),
        settings=lambda c: c.appearance,
    ),
)
BY_NAME: dict[str, StageSpec] = {spec.name: spec for spec in PIPELINE}
# The stages a run reports, in order (report.json's "stages", the progress of a job).
STAGES: tuple[str, ...] = tuple(spec.name for spec in PIPELINE if spec.timed)
