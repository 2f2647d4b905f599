"""Synthetic 2D language feature maps: the text embedding of each pixel's class, degraded like a real model.

Noise model (all sigmas per dimension, in units of ``s_c``, the median distance from class c's unit embedding
to the other class embeddings (``catalog.class_noise_scale``); a perturbation of half the distance to another
class, along the line to it, flips the argmax, so one set of numbers gives about the same pixel error rate in
the CLIP space, whose rows are 0.35-0.7 apart, and in MiniLM, whose rows are 0.9-1.2 apart):

1. instance: each instance i of class c gets ``v_i = e_c + instance_spread * s_c * g_i / sqrt(D)`` (fixed
   for the scene; a length, not a per-dimension sigma, so instances of one class stay alike in any D);
   a fraction ``confused_instances`` of instances lean towards a confusable class c':
   ``v_i <- (1 - w) v_i + w e_c'``, with w drawn from ``confusion_weight`` (w > 0.5 flips the instance);
2. view: per frame, ``v_i + view_sigma * s_c * g_if`` (appearance changes with the view);
3. region confusion: smooth blobs covering ``confused_area`` of each frame lean towards a confusable class
   with weight ``area_weight``;
4. resolution: the full-resolution map is area-averaged into the feature-map cells, so cells on a boundary
   mix the classes on both sides; then an optional Gaussian blur of ``blur_cells``;
5. pixel: independent noise ``pixel_sigma * s * g`` per cell (s: the cell's area-weighted ``s_c``);
6. every cell is L2-normalised and stored as float16.

Confusable classes come from ``catalog.CONFUSABLE``; realistic scenes (preset ``scan``) take
``catalog.RELATED`` instead and add errors that are the same in every view (``anchored.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panogs_core.synthetic.catalog import class_noise_scale, confusion_targets
from panogs_core.synthetic.degrade import blob_mask
from panogs_core.synthetic.presets import FeatureNoise


@dataclass(frozen=True)
class FeatureModel:
    """Per-scene state of the feature noise model (steps 1 and 3 of the module docstring)."""

    class_embeddings: np.ndarray  # (L, D) float32, unit rows
    class_scale: np.ndarray  # (L,) float32, noise unit s_c (median distance to the other classes)
    instance_class: np.ndarray  # (I,) int64
    instance_vectors: np.ndarray  # (I, D) float32, v_i (not normalised)
    noise: FeatureNoise
    related: bool = False  # confusions drawn from catalog.RELATED (realistic scenes) instead of CONFUSABLE


def make_feature_model(
    class_embeddings: np.ndarray,  # (L, D)
    instance_class: np.ndarray,  # (I,) int64
    noise: FeatureNoise,
    rng: np.random.Generator,
    related: bool = False,
) -> FeatureModel:
    """Draw the fixed per-instance feature directions of a scene.

    Args:
        class_embeddings: Unit text embeddings of the catalogue classes ``(L, D)``.
        instance_class: Catalogue class of every instance ``(I,)``.
        noise: Feature noise parameters.
        rng: Source of the noise.
        related: Confuse classes with their related classes (``catalog.RELATED``, realistic scenes) rather
            than with ``catalog.CONFUSABLE``.

    Returns:
        The model to pass to :func:`synthesize_features` for every frame.
    """
    emb = class_embeddings / np.linalg.norm(class_embeddings, axis=1, keepdims=True)
    scale = class_noise_scale(emb)
    cls = np.asarray(instance_class, dtype=np.int64)
    g = rng.standard_normal((len(cls), emb.shape[1])).astype(np.float32)
    vec = emb[cls] + noise.instance_spread * scale[cls, None] * g / np.sqrt(emb.shape[1])
    confused = rng.random(len(cls)) < noise.confused_instances
    targets = _pick_confusable(cls, rng, related)
    weight = rng.uniform(*noise.confusion_weight, len(cls)) * confused
    vec = (1.0 - weight[:, None]) * vec + weight[:, None] * emb[targets]
    return FeatureModel(emb.astype(np.float32), scale, cls, vec.astype(np.float32), noise, related)


def synthesize_features(
    model: FeatureModel,
    instance: np.ndarray,  # (H, W) int64 instance per pixel, -1 = nothing
    shape: tuple[int, int],  # (Hf, Wf)
    rng: np.random.Generator,
) -> np.ndarray:  # (Hf, Wf, D) float16
    """One frame's feature map (steps 2-6 of the module docstring).

    Cell (r, c) averages the pixels (v, u) with ``floor((v + 0.5) * Hf / H) == r`` and
    ``floor((u + 0.5) * Wf / W) == c``, the sampling rule of docs/scene_format.md §2.3.

    Args:
        model: From :func:`make_feature_model`.
        instance: Ground-truth instance id per pixel at the camera resolution.
        shape: Feature-map size ``(Hf, Wf)``.
        rng: Source of the per-frame noise.

    Returns:
        Unit feature vectors, float16.
    """
    _, compact, sources, source_scale, blob = frame_instance_sources(model, instance, rng)
    source = 2 * compact + blob  # source 2k: instance k as is, 2k + 1: instance k inside a confusion blob
    return feature_cells(source, sources, source_scale, shape, model.noise, rng)


def feature_cells(
    source: np.ndarray,  # (H, W) int64 source index per pixel
    sources: np.ndarray,  # (S, D) float32 source vectors
    source_scale: np.ndarray,  # (S,) float32 noise unit of each source
    shape: tuple[int, int],  # (Hf, Wf)
    noise: FeatureNoise,
    rng: np.random.Generator,
) -> np.ndarray:  # (Hf, Wf, D) float16
    """Steps 4-6: area-average the per-pixel sources into cells, blur, add the cell noise, normalise."""
    hf, wf = shape
    h, w = source.shape
    row = ((np.arange(h) + 0.5) * hf / h).astype(np.int64)
    col = ((np.arange(w) + 0.5) * wf / w).astype(np.int64)
    cell = (row[:, None] * wf + col[None, :]).ravel()
    counts = np.bincount(cell * len(sources) + source.ravel(), minlength=hf * wf * len(sources))
    weights = counts.reshape(hf, wf, len(sources)).astype(np.float32)
    weights /= np.maximum(weights.sum(axis=2, keepdims=True), 1.0)
    if noise.blur_cells > 0:  # blurring is linear: blur the (few) source weights, not the D-dim features
        weights = np.einsum("ij,jks->iks", _blur_matrix(hf, noise.blur_cells), weights)
        weights = np.einsum("kl,ils->iks", _blur_matrix(wf, noise.blur_cells), weights)
    flat = weights.reshape(hf * wf, -1)  # 2-D products: numpy's stacked matmul is far slower here
    feat = (flat @ sources).reshape(hf, wf, -1)
    cell_scale = (flat @ source_scale).reshape(hf, wf, 1)
    feat = feat + noise.pixel_sigma * cell_scale * rng.standard_normal(feat.shape, dtype=np.float32)
    feat /= np.maximum(np.linalg.norm(feat, axis=-1, keepdims=True), 1e-6)
    return feat.astype(np.float16)


def _pick_confusable(cls: np.ndarray, rng: np.random.Generator, related: bool = False) -> np.ndarray:  # (n,) int64
    """One confusable class per entry of ``cls``, uniformly among that class's confusables.

    With ``related``, from ``catalog.RELATED``, where a class without related classes (the floor) is its own
    target: leaning towards it changes nothing.
    """
    table, count = confusion_targets(related)
    picked = table[cls, (rng.random(len(cls)) * count[cls]).astype(np.int64)]
    return np.where(picked >= 0, picked, cls)


def _blur_matrix(n: int, sigma: float) -> np.ndarray:  # (n, n) float32, rows sum to 1
    """1-D Gaussian blur as a matrix; rows renormalised at the borders."""
    x = np.arange(n, dtype=np.float32)
    g = np.exp(-0.5 * ((x[:, None] - x[None, :]) / sigma) ** 2)
    return (g / g.sum(axis=1, keepdims=True)).astype(np.float32)


def frame_instance_sources(
    model: FeatureModel, instance: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The instances a frame shows and their sources: ``(ids (K,), compact (H, W) index into ids, sources (2K, D),
    source scales (2K,), confusion blob (H, W) 0/1)``, drawing from ``rng`` in this order (frames stay
    reproducible)."""
    ids, compact = np.unique(instance, return_inverse=True)
    sources, source_scale = frame_sources(model, ids, rng)
    blob = blob_mask(instance.shape, model.noise.confused_area, rng)
    return ids, compact.reshape(instance.shape), sources, source_scale, blob


def frame_sources(
    model: FeatureModel, ids: np.ndarray, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:  # (2K, D), (2K,)
    """Per visible instance: its view-perturbed vector and the same leaning towards a confusable class."""
    noise, emb = model.noise, model.class_embeddings
    known = ids >= 0
    cls = np.where(known, model.instance_class[np.maximum(ids, 0)], 0)
    scale = np.where(known, model.class_scale[cls], 0.0).astype(np.float32)
    g = rng.standard_normal((len(ids), emb.shape[1]), dtype=np.float32)
    own = model.instance_vectors[np.maximum(ids, 0)] + noise.view_sigma * scale[:, None] * g
    own[~known] = 0.0  # pixels that hit nothing carry only the per-cell noise
    targets = _pick_confusable(cls, rng, model.related)
    leaned = (1.0 - noise.area_weight) * own + noise.area_weight * emb[targets] * known[:, None]
    sources = np.stack([own, leaned], axis=1).reshape(2 * len(ids), -1)
    return sources.astype(np.float32), np.repeat(scale, 2)
