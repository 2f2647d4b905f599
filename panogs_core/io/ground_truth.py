"""Ground truth for evaluation, read from the files researchers have, checked, and tied to a set of vertices.

Two sources are understood (``load_ground_truth`` picks by file name):

- ``.npz`` in the bundle's ``gt/labels.npz`` layout (docs/scene_format.md §4): ``semantic`` and ``instance`` ``(G,)``
  integers (integral floats are accepted and converted: the reference's ScanNet ground truth is float64),
  optional ``points`` ``(G, 3)``. Without points the labels are per vertex of the scene's geometry.
- ScanNet v2's own annotations: ``<scene>_vh_clean_2.labels.ply`` (vertex property ``label`` = NYU40 id) and,
  beside it, ``<scene>.aggregation.json`` (``segGroups``: ``objectId``, ``label``, ``segments``) with
  ``<scene>_vh_clean_2.0.010000.segs.json`` (``segIndices``: one over-segment id per vertex). Semantics map
  NYU40 ids to the ScanNet-20 order of ``label_sets`` (other ids: -1, unannotated); every segGroup is one instance
  (its ``objectId``); vertices in no group, and stuff (wall, floor), get instance -1. That is the reference's
  coding (docs/method.md §1.7: wall and floor share instance 0, which is our -1), so both evaluation modes score the
  same as the reference's ground-truth files. Points are the mesh vertices.

When the labelled points are exactly the vertices the prediction lives on (the bundle's ``geometry.ply`` at
import, a run's primitives at evaluation), the points are dropped and the labels compared by index, as the
published numbers are; otherwise evaluation gives each labelled point the prediction of its nearest primitive.
"""

from __future__ import annotations

import json
import logging
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.ply import read_ply_vertices
from panogs_core.language.label_sets import BUILTIN_VOCABULARIES, STUFF_NAMES, builtin_vocabulary
from panogs_core.types import GroundTruth, Vocabulary

logger = logging.getLogger(__name__)

# NYU40 ids of the ScanNet-20 classes, in the order of ``label_sets`` "scannet20" (wall ... otherfurniture).
SCANNET20_NYU40_IDS = (1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 14, 16, 24, 28, 33, 34, 36, 39)
LABELS_PLY_SUFFIX = "_vh_clean_2.labels.ply"
SEGS_SUFFIX = "_vh_clean_2.0.010000.segs.json"
AGGREGATION_SUFFIX = ".aggregation.json"
# Labelled points within this distance (m, per coordinate) of the vertices, one to one, are those vertices.
# PLY stores float32: the same mesh read twice agrees exactly; 1e-5 m only absorbs a float64 round trip.
SAME_VERTEX_ATOL = 1e-5


def nyu40_to_scannet20(nyu40: np.ndarray) -> np.ndarray:  # (G,) int -> (G,) int64 in [-1, 20)
    """ScanNet-20 class index of NYU40 ids; ids outside the 20 classes (and 0, unannotated) give -1.

    Example:
        >>> nyu40_to_scannet20(np.array([0, 1, 2, 13, 14, 39, 40])).tolist()
        [-1, 0, 1, -1, 12, 19, -1]
    """
    ids = np.asarray(nyu40).astype(np.int64)
    table = np.full(max(SCANNET20_NYU40_IDS) + 1, -1, dtype=np.int64)
    table[list(SCANNET20_NYU40_IDS)] = np.arange(len(SCANNET20_NYU40_IDS))
    inside = (ids >= 0) & (ids < len(table))
    return np.where(inside, table[np.clip(ids, 0, len(table) - 1)], -1)


def is_scannet_annotation(path: str | Path) -> bool:
    """True for a ``.ply`` ground-truth file (ScanNet's labelled mesh); ``.npz`` files are the bundle layout."""
    return Path(path).suffix.lower() == ".ply"


def is_scannet20(vocabulary: Vocabulary) -> bool:
    """True when the class names are ScanNet-20's, in its order (case-insensitive)."""
    return tuple(n.lower() for n in vocabulary.names) == BUILTIN_VOCABULARIES["scannet20"][0]


def vocabulary_for_ground_truth(
    path: str | Path, vocabulary: Vocabulary | None, *, feature_space: str | None = None
) -> Vocabulary:
    """The vocabulary an import with ground truth ``path`` must write: checked, or ScanNet-20 by default.

    Args:
        path: The ground-truth file.
        vocabulary: The vocabulary asked for, or None.
        feature_space: The scene's feature space (for the built-in ScanNet-20 embeddings).

    Raises:
        InputError: ScanNet annotations with a vocabulary other than ScanNet-20, or an ``.npz`` without any
            vocabulary (its semantic values index one).
    """
    path = Path(path)
    if is_scannet_annotation(path):
        if vocabulary is None:
            return builtin_vocabulary("scannet20", feature_space=feature_space)
        require_scannet20(vocabulary, path)
        return vocabulary
    if vocabulary is None:
        raise InputError(
            f"{path}: semantic: class indices need a vocabulary to index, none given; "
            "pass --vocabulary scannet20|matterport21|FILE (the classes the indices refer to)"
        )
    return vocabulary


def require_scannet20(vocabulary: Vocabulary, source: str | Path) -> None:
    """Refuse a vocabulary that is not ScanNet-20 for ScanNet annotations.

    Raises:
        InputError: naming the file and the classes found.
    """
    if not is_scannet20(vocabulary):
        names = ", ".join(vocabulary.names[:6]) + (" ..." if len(vocabulary.names) > 6 else "")
        raise InputError(
            f"{source}: ScanNet annotations are labelled in ScanNet-20 (NYU40 ids mapped to wall, floor, cabinet, "
            f"...), but the vocabulary has {len(vocabulary.names)} classes ({names}); use --vocabulary scannet20"
        )


def load_ground_truth(
    path: str | Path,
    vocabulary: Vocabulary,
    *,
    vertices: np.ndarray | None = None,  # (N, 3) float: the vertices the prediction lives on, or None
    vertices_name: str = "geometry",
) -> GroundTruth:
    """Read, check and tie ground truth to ``vertices``.

    Args:
        path: An ``.npz`` (``semantic``, ``instance``, optional ``points``) or a ScanNet
            ``<scene>_vh_clean_2.labels.ply`` with its aggregation and segments files beside it.
        vocabulary: The classes the semantic labels index (ScanNet-20 for ScanNet annotations).
        vertices: Positions of the geometry vertices (import) or of a run's primitives (evaluation). Labels
            with points exactly on them, one to one, become per-vertex labels (points dropped); labels without
            points must have one entry per vertex.
        vertices_name: What ``vertices`` are, for error messages.

    Returns:
        int64 ``semantic`` in ``[-1, L)`` and ``instance`` >= -1, and float32 ``points`` or None (per vertex).

    Raises:
        InputError: naming the file, the field and the value, for a file that is missing, unreadable, of an
            unknown kind, or inconsistent (lengths, ranges, dtypes, vocabulary, vertex count).
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: ground truth file does not exist")
    if path.suffix.lower() == ".npz":
        gt = read_npz_ground_truth(path, num_classes=len(vocabulary.names))
    elif is_scannet_annotation(path):
        require_scannet20(vocabulary, path)
        gt = read_scannet_ground_truth(path, is_thing=vocabulary.is_thing)
    else:
        raise InputError(
            f"{path}: unknown ground truth kind {path.suffix!r}, expected an .npz (semantic, instance[, points]) "
            f"or ScanNet's <scene>{LABELS_PLY_SUFFIX}"
        )
    return attach_to_vertices(gt, vertices, source=path, vertices_name=vertices_name)


def attach_to_vertices(
    gt: GroundTruth, vertices: np.ndarray | None, *, source: str | Path, vertices_name: str = "geometry"
) -> GroundTruth:
    """Per-vertex ground truth when ``gt`` lies exactly on ``vertices``; checks per-vertex labels' length.

    Raises:
        InputError: labels without points and no vertices, or a count that is not the vertex count.
    """
    g = len(gt.semantic)
    if gt.points is not None:
        if vertices is not None and _same_points(gt.points, vertices):
            return GroundTruth(semantic=gt.semantic, instance=gt.instance, points=None)
        return gt
    if vertices is None:
        raise InputError(
            f"{source}: points: missing, so the {g} labels are per vertex of the geometry, but there is none; "
            "add points (G, 3) to the file or import with --geometry MESH.ply"
        )
    if len(vertices) != g:
        raise InputError(
            f"{source}: semantic: {g} labels without points, expected one per vertex of {vertices_name} "
            f"({len(vertices)} vertices)"
        )
    return gt


def _same_points(points: np.ndarray, vertices: np.ndarray) -> bool:
    a, b = np.asarray(points, np.float64), np.asarray(vertices, np.float64)
    return a.shape == b.shape and bool(np.all(np.abs(a - b) <= SAME_VERTEX_ATOL))


# -- .npz ----------------------------------------------------------------------------------------------------


def read_npz_ground_truth(path: str | Path, *, num_classes: int) -> GroundTruth:
    """Ground truth from an ``.npz`` in the bundle layout, every field checked.

    Raises:
        InputError: unreadable or pickled file, a missing key, labels that are not ``(G,)`` integers (or
            integral floats), different lengths, semantic outside ``[-1, num_classes)``, instance below -1,
            points that are not ``(G, 3)`` finite floats.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            arrays = {key: npz[key] for key in npz.files}
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as exc:
        raise InputError(f"{path}: not a readable .npz of plain arrays ({exc})") from exc
    for key in ("semantic", "instance"):
        if key not in arrays:
            raise InputError(f"{path}: key {key!r} missing, expected (G,) int64; found keys {sorted(arrays)}")
    sem = _integer_labels(arrays["semantic"], path, "semantic")
    ins = _integer_labels(arrays["instance"], path, "instance")
    if len(ins) != len(sem):
        raise InputError(f"{path}: instance has {len(ins)} values, expected {len(sem)} (as semantic)")
    if len(sem) and (sem.min() < -1 or sem.max() >= num_classes):
        raise InputError(
            f"{path}: semantic in [{sem.min()}, {sem.max()}], expected [-1, {num_classes}) "
            f"(class indices of the {num_classes}-class vocabulary, -1 = unannotated)"
        )
    if len(ins) and ins.min() < -1:
        raise InputError(f"{path}: instance has minimum {ins.min()}, expected ids >= -1")
    points = None
    if "points" in arrays:
        pts = arrays["points"]
        if pts.shape != (len(sem), 3) or pts.dtype.kind != "f" or not np.all(np.isfinite(pts)):
            raise InputError(f"{path}: points {pts.dtype} {pts.shape}, expected ({len(sem)}, 3) finite floats")
        points = pts.astype(np.float32)
    return GroundTruth(semantic=sem, instance=ins, points=points)


def _integer_labels(arr: np.ndarray, path: Path, key: str) -> np.ndarray:  # (G,) int64
    if arr.ndim != 1 or not (np.issubdtype(arr.dtype, np.integer) or arr.dtype.kind == "f"):
        raise InputError(f"{path}: {key} {arr.dtype} {arr.shape}, expected (G,) integers")
    if arr.dtype.kind == "f":  # the reference's ground truth is float64 with integral values (and -0.0)
        bad = ~np.isfinite(arr) | (arr != np.round(arr))
        if bad.any():
            raise InputError(f"{path}: {key} has non-integer value {float(arr[bad][0])}, expected integer labels")
    return arr.astype(np.int64)


# -- ScanNet annotations -------------------------------------------------------------------------------------


def scannet_annotation_files(labels_ply: str | Path) -> tuple[Path, Path]:
    """``(<scene>.aggregation.json, <scene>_vh_clean_2.0.010000.segs.json)`` beside a labels PLY.

    Raises:
        InputError: if the file name is not ``<scene>_vh_clean_2.labels.ply`` or either file is missing.
    """
    path = Path(labels_ply)
    if not path.name.endswith(LABELS_PLY_SUFFIX):
        raise InputError(
            f"{path}: expected ScanNet's <scene>{LABELS_PLY_SUFFIX} (the name locates <scene>{AGGREGATION_SUFFIX} "
            f"and <scene>{SEGS_SUFFIX} beside it)"
        )
    scene = path.name[: -len(LABELS_PLY_SUFFIX)]
    aggregation = path.with_name(scene + AGGREGATION_SUFFIX)
    segs = path.with_name(scene + SEGS_SUFFIX)
    missing = [p.name for p in (aggregation, segs) if not p.is_file()]
    if missing:
        raise InputError(
            f"{path}: instances need {' and '.join(missing)} in {path.parent} (ScanNet v2 release layout), not found"
        )
    return aggregation, segs


def read_scannet_ground_truth(labels_ply: str | Path, *, is_thing: np.ndarray | None = None) -> GroundTruth:
    """ScanNet-20 semantics and per-object instances of a ScanNet v2 scene, per vertex, with the vertices.

    Args:
        labels_ply: ``<scene>_vh_clean_2.labels.ply``; the aggregation and segments files lie beside it.
        is_thing: ``(20,)`` per ScanNet-20 class, True for things; stuff vertices get instance -1. Default:
            the built-in kinds (wall and floor are stuff).

    Returns:
        ``semantic`` ``(G,)`` in ``[-1, 20)``, ``instance`` ``(G,)`` (segGroup ``objectId``, -1 for none and
        stuff) and ``points`` ``(G, 3)`` float32.

    Raises:
        InputError: naming the file, field and value, for a missing ``label`` property, malformed JSON,
            a ``segIndices`` count that is not the vertex count, or a group without an integer ``objectId``.
    """
    path = Path(labels_ply)
    aggregation, segs = scannet_annotation_files(path)
    vertices = read_ply_vertices(path)
    for key in ("x", "y", "z", "label"):
        if key not in vertices:
            raise InputError(
                f"{path}: vertex property {key!r} missing, expected x, y, z and label (NYU40 id); "
                f"found {', '.join(sorted(vertices))}"
            )
    points = np.stack([vertices[k] for k in "xyz"], axis=1).astype(np.float32)
    semantic = nyu40_to_scannet20(vertices["label"])
    seg_indices = _read_seg_indices(segs, len(points))
    instance = _instances_from_groups(_read_seg_groups(aggregation), seg_indices, aggregation)
    if is_thing is None:
        is_thing = np.array([name not in STUFF_NAMES for name in BUILTIN_VOCABULARIES["scannet20"][0]])
    stuff = (semantic >= 0) & ~np.asarray(is_thing, bool)[np.maximum(semantic, 0)]
    instance[stuff] = -1
    return GroundTruth(semantic=semantic, instance=instance, points=points)


def _read_json(path: Path) -> Any:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: not readable JSON ({exc})") from exc


def _read_seg_indices(path: Path, num_vertices: int) -> np.ndarray:  # (G,) int64
    doc = _read_json(path)
    seg = doc.get("segIndices") if isinstance(doc, dict) else None
    if not isinstance(seg, list):
        found = "missing" if seg is None else f"is a {type(seg).__name__}"
        raise InputError(f"{path}: segIndices {found}, expected a list of one segment id per vertex")
    try:
        ids = np.asarray(seg, dtype=np.int64)
    except (TypeError, ValueError, OverflowError) as exc:
        raise InputError(f"{path}: segIndices holds non-integer values ({exc})") from exc
    if ids.ndim != 1 or len(ids) != num_vertices:
        raise InputError(
            f"{path}: segIndices has {ids.size} entries, expected {num_vertices} (the vertices of the labels "
            "PLY; is it the segments file of another mesh?)"
        )
    return ids


def _read_seg_groups(path: Path) -> list[tuple[int, list[int]]]:  # (objectId, segments) per group, in order
    doc = _read_json(path)
    groups = doc.get("segGroups") if isinstance(doc, dict) else None
    if not isinstance(groups, list):
        found = "missing" if groups is None else f"is a {type(groups).__name__}"
        raise InputError(f"{path}: segGroups {found}, expected a list of {{objectId, label, segments}}")
    out: list[tuple[int, list[int]]] = []
    for i, group in enumerate(groups):
        obj = group.get("objectId", group.get("id")) if isinstance(group, dict) else None
        segments = group.get("segments") if isinstance(group, dict) else None
        if isinstance(obj, bool) or not isinstance(obj, int) or obj < 0:
            raise InputError(f"{path}: segGroups[{i}].objectId {obj!r}, expected an integer >= 0")
        if not isinstance(segments, list) or not all(isinstance(s, int) and not isinstance(s, bool) for s in segments):
            raise InputError(f"{path}: segGroups[{i}].segments {_short(segments)}, expected a list of integers")
        out.append((obj, segments))
    objects = [obj for obj, _ in out]
    if len(set(objects)) != len(objects):
        repeated = sorted({o for o in objects if objects.count(o) > 1})
        raise InputError(f"{path}: segGroups objectId {repeated[0]} repeated, expected one group per object")
    return out


def _instances_from_groups(groups: list[tuple[int, list[int]]], seg_indices: np.ndarray, source: Path) -> np.ndarray:
    """(G,) int64: the objectId of the group holding each vertex's segment, -1 where none does."""
    if not groups:
        return np.full(len(seg_indices), -1, dtype=np.int64)
    seg = np.concatenate([np.asarray(s, np.int64) for _, s in groups])
    obj = np.concatenate([np.full(len(s), o, np.int64) for o, s in groups])
    # A segment listed by two groups (rare annotation slips) goes to the later one, as overwriting would.
    uniq, last = np.unique(seg[::-1], return_index=True)
    owner = obj[::-1][last]
    if len(uniq) < len(seg):
        logger.warning("%s: %d segments are in two groups; the later group keeps them", source, len(seg) - len(uniq))
    pos = np.clip(np.searchsorted(uniq, seg_indices), 0, len(uniq) - 1)
    return np.where(uniq[pos] == seg_indices, owner[pos], -1)


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."
