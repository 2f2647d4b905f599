"""Feature errors of realistic scenes that are the same in every view: world-anchored confusions and clutter.

A real 2D open-vocabulary model errs consistently: the same stretch of a kitchen front reads as "counter" in
every frame that sees it, a door next to a wall as "wall". Per-frame errors (``features.py`` steps 2, 3 and 5)
average out over the views of a point; these do not, so multi-view fusion keeps them.

* Anchored regions: spheres fixed in the world, centred on surface points of classes that have related
  classes (``catalog.RELATED``), added until they hold ``anchored_area`` of those points. Inside a sphere, every
  pixel of such a class leans towards one of its related classes, ``v <- (1 - w) v + w e_t``: sphere r picks
  ``RELATED[c][floor(u_r * n_c)]`` for class c (one draw u_r per sphere, so a sphere turns a counter into a
  cabinet and the cabinet beside it into a desk, consistently), with w drawn per sphere from
  ``anchored_weight`` (w > 0.5 flips the fused argmax).
* Clutter (unannotated instances) gets a feature between its look-alike class and a random direction,
  ``v = e_look + CLUTTER_RANDOM * g / |g|``: nearest to the look-alike class but far from every class, as
  real maps show things outside the vocabulary. It never leans.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from scipy.spatial import cKDTree

from panogs_core.synthetic.catalog import confusion_targets
from panogs_core.synthetic.features import FeatureModel, feature_cells, frame_instance_sources

CLUTTER_RANDOM = 0.8  # length of the random part of a clutter feature (class rows are 0.35-0.7 apart in CLIP)
_MAX_REGIONS = 2000  # safety bound on the number of spheres


@dataclass(frozen=True)
class Anchors:
    """World-anchored confusion regions of one scene."""

    centres: np.ndarray  # (S, 3) float64, world, metres
    radii: np.ndarray  # (S,) float64, metres
    pick: np.ndarray  # (S,) float64 in [0, 1): which related class the region leans to
    weight: np.ndarray  # (S,) float64 lean

    def region(self, points: np.ndarray) -> np.ndarray:  # (M,) int64, -1 = in no region
        """The first region (lowest index) holding each point ``(M, 3)``."""
        out = np.full(len(points), -1, dtype=np.int64)
        if not len(self.radii) or not len(points):
            return out
        tree = cKDTree(points)
        for r in range(len(self.radii) - 1, -1, -1):  # reverse, so that the lowest index is written last
            out[tree.query_ball_point(self.centres[r], self.radii[r])] = r
        return out


def make_anchors(
    points: np.ndarray,  # (N, 3) surface points of the scene
    semantic: np.ndarray,  # (N,) catalogue class, -1 = unannotated
    area: float,
    weight: tuple[float, float],
    radius: tuple[float, float],
    rng: np.random.Generator,
) -> Anchors:
    """Draw spheres on the surface until they hold ``area`` of the points whose class can lean.

    Args:
        points: Surface points (the scene's geometry).
        semantic: Their classes; unannotated points and classes without related classes never lean.
        area: Target fraction of the leaning-capable points inside some sphere (0 = no regions).
        weight: Range of the lean per region.
        radius: Range of the radii, metres.
        rng: Source of the regions.

    Returns:
        The regions, in drawing order.
    """
    _, count = confusion_targets(related=True)
    able = np.flatnonzero((semantic >= 0) & (count[np.maximum(semantic, 0)] > 0))
    centres: list[np.ndarray] = []
    radii: list[float] = []
    if area > 0 and len(able):
        tree, inside = cKDTree(points[able]), np.zeros(len(able), dtype=bool)
        while inside.mean() < area and len(radii) < _MAX_REGIONS:
            centre, r = points[able[rng.integers(len(able))]], rng.uniform(*radius)
            inside[tree.query_ball_point(centre, r)] = True
            centres.append(centre)
            radii.append(r)
    n = len(radii)
    return Anchors(
        centres=np.asarray(centres, dtype=np.float64).reshape(n, 3),
        radii=np.asarray(radii, dtype=np.float64),
        pick=rng.random(n),
        weight=rng.uniform(*weight, n),
    )


def with_clutter(model: FeatureModel, annotated: np.ndarray, rng: np.random.Generator) -> FeatureModel:
    """The model with the vectors of unannotated instances replaced by clutter features (module docstring)."""
    emb, vec = model.class_embeddings, model.instance_vectors.copy()
    clutter = np.flatnonzero(~annotated)
    g = rng.standard_normal((len(clutter), emb.shape[1])).astype(np.float32)
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    vec[clutter] = emb[model.instance_class[clutter]] + CLUTTER_RANDOM * g
    return replace(model, instance_vectors=vec)


def synthesize_anchored_features(
    model: FeatureModel,
    anchors: Anchors,
    annotated: np.ndarray,  # (I,) bool
    instance: np.ndarray,  # (H, W) int64 instance per pixel, -1 = nothing
    world: np.ndarray,  # (H, W, 3) world point of each pixel (clean depth)
    shape: tuple[int, int],  # (Hf, Wf)
    rng: np.random.Generator,
) -> np.ndarray:  # (Hf, Wf, D) float16
    """One frame's feature map: ``features.synthesize_features`` with the anchored leans of the pixels.

    Args:
        model: From ``features.make_feature_model`` (and :func:`with_clutter`).
        anchors: From :func:`make_anchors`.
        annotated: Per instance, False for clutter (never leans).
        instance: Ground-truth instance per pixel at the camera resolution.
        world: World point of every pixel.
        shape: Feature-map size.
        rng: Source of the per-frame noise.

    Returns:
        Unit feature vectors, float16.
    """
    ids, compact, sources, source_scale, blob = frame_instance_sources(model, instance, rng)
    region = anchors.region(world.reshape(-1, 3)).reshape(instance.shape)
    slots = len(anchors.radii) + 1
    # one source per (instance, blob, region) that occurs in the frame; region slot 0 = in no region
    keys, source = np.unique((2 * compact + blob) * slots + region + 1, return_inverse=True)
    base, r = keys // slots, keys % slots - 1
    inst = ids[base // 2]
    target = _region_targets(model, anchors, inst, r, annotated)
    w = np.where(target >= 0, np.append(anchors.weight, 0.0)[r], 0.0).astype(np.float32)[:, None]  # [-1]: 0
    vec = (1.0 - w) * sources[base] + w * model.class_embeddings[np.maximum(target, 0)]
    return feature_cells(
        source.reshape(instance.shape), vec.astype(np.float32), source_scale[base], shape, model.noise, rng
    )


def _region_targets(
    model: FeatureModel, anchors: Anchors, inst: np.ndarray, region: np.ndarray, annotated: np.ndarray
) -> np.ndarray:  # (K,) int64 class to lean to, -1 = none
    """The related class each (instance, region) pair leans to; -1 outside regions, for clutter and no-hit."""
    table, count = confusion_targets(related=True)
    cls = model.instance_class[np.maximum(inst, 0)]
    pick = np.append(anchors.pick, 0.0)[region]  # region -1 takes the appended 0 (masked out below)
    target = table[cls, np.minimum((pick * count[cls]).astype(np.int64), table.shape[1] - 1)]
    ok = (region >= 0) & (inst >= 0) & annotated[np.maximum(inst, 0)] & (count[cls] > 0)
    return np.where(ok, target, -1)
