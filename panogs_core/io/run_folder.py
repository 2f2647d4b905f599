"""The run folder: the declaration of every file a run writes, and the reader of a finished run.

``RUN_FILES`` is the one list of a run's files: name, media type, content, the module that writes it, those that
read it back, whether a finished run may lack it, and whether the API serves it for download. The exporter, the
run reader, the renders, the viewer, the worker's artifact list and the API's download route take their names
and media types from it, and the tables of README.md and docs/architecture.md are generated from it
(``tools/run_folder_docs.py``). The API imports this module: it imports numpy and the bounded readers, never the
stages or torch.

Queries need ``instances.json``, ``instance_features.npy`` and ``vocabulary.json`` (+ ``vocabulary.npy``);
evaluation needs ``labels.npz``, ``panoptic.ply`` (the primitive positions) and ``vocabulary.json``.

>>> DOWNLOADABLE["report.json"].media_type
'application/json'
>>> STAGES_FOLDER.path(Path("run")).as_posix()
'run/stages'
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.ply import read_ply_vertices
from panogs_core.io.run_json import read_run_json
from panogs_core.types import InstanceInfo, Vocabulary

BINARY = "application/octet-stream"
JSON = "application/json"
FOLDER = "inode/directory"  # never served; the shared-mime-info name of a folder


@dataclass(frozen=True)
class RunFile:
    """One entry of a run's folder."""

    name: str  # relative to the run folder; a folder's name ends with "/"
    media_type: str  # what the API answers a download with
    content: str  # one line: the "content" column of the docs tables
    writer: str  # the module that puts it in the run folder
    readers: tuple[str, ...]  # the modules that read it back
    optional: bool = False  # a finished run may lack it (``content`` says when)
    downloadable: bool = False  # listed and served under ``/v1/jobs/{id}/artifacts``

    @property
    def is_folder(self) -> bool:
        return self.name.endswith("/")

    def path(self, run_dir: str | Path) -> Path:
        """Where it lies in ``run_dir``."""
        return Path(run_dir) / self.name.rstrip("/")


_EXPORT = "panogs_core.stages.export"
_PIPELINE = "panogs_core.pipeline.run"
_REPORT = "panogs_core.pipeline.report"
_CHECKPOINTS = "panogs_core.pipeline.checkpoints"
_STAGE_TABLE = "panogs_core.pipeline.stage_table"  # its validate stage opens the bundle
_READER = "panogs_core.io.run_folder"

PANOPTIC_PLY = RunFile(
    "panoptic.ply",
    BINARY,
    "x, y, z, red, green, blue, semantic, instance per primitive; the colours show the segmentation (one colour per "
    "instance, stuff by class)",
    _EXPORT,
    (_READER,),
    downloadable=True,
)
LABELS_NPZ = RunFile(
    "labels.npz",
    BINARY,
    "per primitive `semantic`, `instance`, `superprimitive`, `cluster` (int64, -1 = void) and `class_names`",
    _EXPORT,
    (_READER,),
    downloadable=True,
)
INSTANCES_JSON = RunFile(
    "instances.json",
    JSON,
    "per instance: id, class_name, class_index, kind (thing/stuff), score, num_points, centroid, bbox_min, "
    "bbox_max (axis-aligned)",
    _EXPORT,
    (_READER, "service.job_results", "service.viewer.scene"),
    downloadable=True,
)
INSTANCE_FEATURES_NPY = RunFile(
    "instance_features.npy",
    BINARY,
    "(I, D) float32 unit mean language feature per instance (row = instance id), for queries",
    _EXPORT,
    (_READER,),
)
VOCABULARY_JSON = RunFile(
    "vocabulary.json",
    JSON,
    "the run's label set (each class's name and kind, thing or stuff), its feature `space`, and `embeddings`: "
    "the file of the class embeddings",
    _EXPORT,
    (_READER, "service.viewer.scene"),
    downloadable=True,
)
VOCABULARY_NPY = RunFile(
    "vocabulary.npy",
    BINARY,
    "(L, D) float32 embedding per class of `vocabulary.json`, in the run's feature space",
    _EXPORT,
    (_READER,),
)
GAUSSIANS_PLY = RunFile(
    "gaussians.ply",
    BINARY,
    "the Gaussian scene in the standard 3D Gaussian splatting layout (x, y, z, nx, ny, nz, `f_dc_*`, `f_rest_*`, "
    "logit `opacity`, log `scale_*`, `rot_*`) plus `semantic` and `instance`; opens in the common splat viewers. "
    "Written by the exporter with the results as the initialisation (the primitives' colours), replaced "
    "atomically by the fitted scene when the fit ends: `report.json`'s `appearance.state` says which it holds",
    _PIPELINE,
    ("panogs_core.gaussians.views", "service.viewer.scene", "service.render_child"),
    downloadable=True,
)
CAMERAS_JSON = RunFile(
    "cameras.json",
    JSON,
    "the camera, the pose of every frame of the bundle and of the capture frames the importer left out "
    "(`skipped`: true), so that `panogs render --frame` needs no bundle, and the run's `up` (unit vector, world) "
    "with `up_source` (`bundle`, `floor` or `cameras`: docs/scene_format.md §2.5), which the viewer's first view "
    "and orbit use",
    _EXPORT,
    ("panogs_core.gaussians.views", "service.render_child", "service.viewer.scene"),
    downloadable=True,
)
REPORT_JSON = RunFile(
    "report.json",
    JSON,
    "per stage: wall time, peak memory, device (`cpu`, `cuda`), whether it came from a checkpoint and the stage "
    "it ran `beside` (if any); config, input hash, versions, `appearance` (the fit's PSNR / SSIM before and after), "
    "and `unseen_primitives`: how many primitives no key frame saw and how each was labelled (`segment`, `graph`, "
    "`nearest`). Written when the results are (`appearance.state` `running`, `results_wall_s`; the input hash may "
    "be null there while it is still being computed), again when the fit ends (`succeeded`, `skipped`, `failed` "
    "or `canceled`, with `error`). A tiled run's (`panogs run --tiles`) has `tiling`: the plan and per tile its core "
    "and halo primitives, frames, wall time and peak memory",
    _REPORT,
    ("bench.speed", "bench.service.bench_service", "bench.tiling"),
    downloadable=True,
)
METRICS_JSON = RunFile(
    "metrics.json",
    JSON,
    "mIoU, mAcc, PRQ(T), PRQ(S) in `standard` and `paper` modes; only when the bundle has `gt/labels.npz` in the "
    "run's vocabulary",
    _EXPORT,
    ("panogs_core.cli.commands.eval",),
    optional=True,
    downloadable=True,
)
STAGES_FOLDER = RunFile(
    "stages/",
    FOLDER,
    "the stage checkpoints (`<stage>.npz`), `manifest.json` (the key each was made with) and a stopped fit's "
    "`appearance.partial.pt`: what a re-run resumes from",
    _CHECKPOINTS,
    (_CHECKPOINTS,),
)
BUNDLE_FOLDER = RunFile(
    "bundle/",
    FOLDER,
    "the input archive, extracted; only when the run was given a `.zip` or `.tar.gz`",
    _STAGE_TABLE,
    (_STAGE_TABLE,),
    optional=True,
)
TILES_FOLDER = RunFile(
    "tiles/",
    FOLDER,
    "a tiled run's tiles (`panogs run --tiles`): `plan.json` (every tile's rectangles and frames) and one run "
    "folder per tile, `tile-<k>-<digest>/` (its labels, `report.json`, the checkpoints the merge reads and "
    "`tile.json` once it is finished: the fusion's and the field's bulky ones are deleted then), which the merge "
    "reads and a re-run resumes tile by tile, keeping the finished ones",
    "panogs_core.tiling.runner",
    ("panogs_core.tiling.runner",),
    optional=True,
)

RUN_FILES: tuple[RunFile, ...] = (
    PANOPTIC_PLY,
    LABELS_NPZ,
    INSTANCES_JSON,
    INSTANCE_FEATURES_NPY,
    VOCABULARY_JSON,
    VOCABULARY_NPY,
    GAUSSIANS_PLY,
    CAMERAS_JSON,
    REPORT_JSON,
    METRICS_JSON,
    STAGES_FOLDER,
    BUNDLE_FOLDER,
    TILES_FOLDER,
)
# What the API lists and serves for a finished job, by name (docs/service.md).
DOWNLOADABLE: dict[str, RunFile] = {f.name: f for f in RUN_FILES if f.downloadable}


@dataclass(frozen=True)
class LoadedResult:
    """What a query needs from a run."""

    instances: tuple[InstanceInfo, ...]
    vocabulary: Vocabulary
    feature_space: str


@dataclass(frozen=True)
class RunLabels:
    """What evaluation needs from a run: the labelled primitives and the classes their labels index."""

    points: np.ndarray  # (N, 3) float32, primitive positions
    semantic: np.ndarray  # (N,) int64, -1 void
    instance: np.ndarray  # (N,) int64, -1 none
    vocabulary: Vocabulary


def load_vocabulary(out_dir: Path) -> tuple[Vocabulary, str]:
    """The run's vocabulary (with embeddings) and its feature space."""
    doc = read_run_json(VOCABULARY_JSON.path(out_dir))
    assert isinstance(doc, dict)
    classes = doc.get("classes", [])
    embeddings = None
    if doc.get("embeddings"):
        embeddings = np.load(out_dir / str(doc["embeddings"]), allow_pickle=False).astype(np.float32)
    vocab = Vocabulary(
        names=tuple(c["name"] for c in classes), kinds=tuple(c["kind"] for c in classes), embeddings=embeddings
    )
    return vocab, str(doc.get("space", ""))


def load_result(out_dir: str | Path) -> LoadedResult:
    """Instances (with their features), vocabulary and feature space of a finished run.

    Raises:
        InputError: a file is missing or does not match the others.
    """
    out = Path(out_dir)
    vocab, space = load_vocabulary(out)
    rows = read_run_json(INSTANCES_JSON.path(out))
    assert isinstance(rows, list)
    feats_path = INSTANCE_FEATURES_NPY.path(out)
    if not feats_path.is_file():
        raise InputError(f"{feats_path}: missing; is {out} the --out folder of a finished run?")
    feats = np.load(feats_path, allow_pickle=False).astype(np.float32)
    if feats.shape[0] != len(rows):
        raise InputError(f"{feats_path}: {feats.shape[0]} rows but {INSTANCES_JSON.name} lists {len(rows)} instances")
    instances = tuple(
        InstanceInfo(
            id=int(r["id"]),
            class_index=int(r["class_index"]),
            class_name=str(r["class_name"]),
            kind=str(r["kind"]),
            score=float(r["score"]),
            num_points=int(r["num_points"]),
            centroid=np.asarray(r["centroid"], np.float32),
            bbox_min=np.asarray(r["bbox_min"], np.float32),
            bbox_max=np.asarray(r["bbox_max"], np.float32),
            feature=feats[i],
        )
        for i, r in enumerate(rows)
    )
    return LoadedResult(instances=instances, vocabulary=vocab, feature_space=space)


def load_run_labels(out_dir: str | Path) -> RunLabels:
    """Primitive positions (``panoptic.ply``), labels (``labels.npz``) and vocabulary of a finished run.

    Raises:
        InputError: a file is missing, unreadable, or does not match the others.
    """
    out = Path(out_dir)
    vocab, _ = load_vocabulary(out)
    labels_path, ply_path = LABELS_NPZ.path(out), PANOPTIC_PLY.path(out)
    for path in (labels_path, ply_path):
        if not path.is_file():
            raise InputError(f"{path}: missing; is {out} the --out folder of a finished run?")
    try:
        with np.load(labels_path, allow_pickle=False) as npz:
            semantic, instance = npz["semantic"].astype(np.int64), npz["instance"].astype(np.int64)
    except (OSError, ValueError, KeyError) as exc:
        raise InputError(f"{labels_path}: expected semantic and instance arrays ({exc})") from exc
    vertices = read_ply_vertices(ply_path)
    if not {"x", "y", "z"} <= vertices.keys():
        raise InputError(f"{ply_path}: vertex properties {sorted(vertices)}, expected x, y, z")
    points = np.stack([vertices[k] for k in "xyz"], axis=1).astype(np.float32)
    if not (len(points) == len(semantic) == len(instance)):
        raise InputError(
            f"{labels_path}: semantic {semantic.shape}, instance {instance.shape}, expected ({len(points)},) "
            f"(the vertices of {ply_path.name})"
        )
    return RunLabels(points=points, semantic=semantic, instance=instance, vocabulary=vocab)
