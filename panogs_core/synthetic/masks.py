"""SAM-like 2D instance masks from the ground-truth instance image of a frame.

Steps, each with its rate in :class:`MaskNoise`:

1. under-segmentation: objects that touch in 3D (``Layout.contacts``) and are adjacent in the image share a
   mask with probability ``merge_touching``; any two adjacent regions with probability ``merge_any``;
2. over-segmentation: a wall / floor / ceiling region is cut into ``stuff_pieces`` Voronoi cells with
   probability ``stuff_split``; an object is cut into its parts (its boxes, or the faces of a one-box object)
   with probability ``part_split``;
3. boundary noise: every boundary moves with a smooth random displacement of about ``jitter_px`` pixels, and a
   band of ``gap_px`` pixels along the boundaries is left without a mask;
4. masks below ``min_area`` of the image are dropped, and any mask is missed with probability ``miss``;
5. the surviving masks get ids 1..M in a random order (0 = no mask), as SAM's ids mean nothing across frames.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from panogs_core.synthetic.degrade import smooth_field
from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.presets import MaskNoise


def adjacent_pairs(labels: np.ndarray) -> np.ndarray:  # (E, 2) int64, a < b
    """Distinct label pairs that are 4-neighbours somewhere in a label image."""
    a = np.concatenate([labels[:, :-1].ravel(), labels[:-1, :].ravel()])
    b = np.concatenate([labels[:, 1:].ravel(), labels[1:, :].ravel()])
    diff = a != b
    pairs = np.stack([np.minimum(a[diff], b[diff]), np.maximum(a[diff], b[diff])], 1)
    return np.unique(pairs, axis=0) if len(pairs) else pairs.reshape(0, 2)


def _merge_groups(
    instance: np.ndarray, layout: Layout, noise: MaskNoise, rng: np.random.Generator
) -> np.ndarray:  # (I,) int64 group per instance
    """Union of instances merged by step 1."""
    n = len(layout.instance_class)
    pairs = adjacent_pairs(instance)
    pairs = pairs[(pairs >= 0).all(axis=1)]
    touching = {tuple(sorted(p)) for p in layout.contacts.tolist()}
    is_contact = np.array([tuple(p) in touching for p in pairs.tolist()], dtype=bool)
    prob = np.where(is_contact, 1 - (1 - noise.merge_touching) * (1 - noise.merge_any), noise.merge_any)
    merged = pairs[rng.random(len(pairs)) < prob]
    graph = coo_matrix((np.ones(len(merged)), (merged[:, 0], merged[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def _stuff_pieces(region: np.ndarray, pieces: int, rng: np.random.Generator) -> np.ndarray:  # (P,)
    """Voronoi cell (of ``pieces`` random seeds among the region's pixels) of every pixel of the region."""
    v, u = np.nonzero(region)
    seeds = rng.choice(len(v), size=min(pieces, len(v)), replace=False)
    d = (v[:, None] - v[None, seeds]) ** 2 + (u[:, None] - u[None, seeds]) ** 2
    return d.argmin(axis=1)


def _split(
    instance: np.ndarray,
    box: np.ndarray,
    face: np.ndarray,
    group: np.ndarray,
    layout: Layout,
    noise: MaskNoise,
    rng: np.random.Generator,
) -> np.ndarray:  # (H, W) int64 sub-region id within each group
    """Step 2: sub-region ids (0 = not split)."""  # fmt: skip
    sub = np.zeros(instance.shape, dtype=np.int64)
    group_size = np.bincount(group, minlength=len(group))
    boxes_per_instance = np.bincount(layout.box_instance, minlength=len(group))
    for i in np.unique(instance[instance >= 0]):
        if group_size[group[i]] > 1:
            continue  # merged regions stay whole
        region = instance == i
        if i < layout.num_stuff:
            if rng.random() < noise.stuff_split:
                pieces = int(rng.integers(noise.stuff_pieces[0], noise.stuff_pieces[1] + 1))
                sub[region] = 1 + _stuff_pieces(region, pieces, rng)
        elif rng.random() < noise.part_split:
            # Composite objects split into their boxes (seat, back, legs); one-box objects into faces.
            sub[region] = 1 + (box[region] if boxes_per_instance[i] > 1 else face[region])
    return sub


def _jitter(seg: np.ndarray, amplitude: float, rng: np.random.Generator) -> np.ndarray:
    """Resample the label image through a smooth random displacement field (nearest label)."""
    if amplitude <= 0:
        return seg
    h, w = seg.shape
    dv = smooth_field(seg.shape, rng, cell=12) * amplitude
    du = smooth_field(seg.shape, rng, cell=12) * amplitude
    v = np.clip(np.rint(np.arange(h)[:, None] + dv), 0, h - 1).astype(np.int64)
    u = np.clip(np.rint(np.arange(w)[None, :] + du), 0, w - 1).astype(np.int64)
    return seg[v, u]


def _gaps(seg: np.ndarray, width: int) -> np.ndarray:  # (H, W) bool
    """A band of ``width`` pixels along label boundaries."""
    edge = np.zeros(seg.shape, dtype=bool)
    if width <= 0:
        return edge
    edge[:, :-1] |= seg[:, :-1] != seg[:, 1:]
    edge[:-1, :] |= seg[:-1, :] != seg[1:, :]
    if width > 1:
        kernel = np.ones((2 * (width - 1) + 1,) * 2, dtype=np.uint8)
        edge = cv2.dilate(edge.astype(np.uint8), kernel) > 0
    return edge


def synthesize_masks(
    instance: np.ndarray,  # (H, W) int64, -1 = nothing
    box: np.ndarray,  # (H, W) int64 layout box per pixel
    face: np.ndarray,  # (H, W) int64 box face per pixel
    layout: Layout,
    noise: MaskNoise,
    rng: np.random.Generator,
) -> np.ndarray:  # (H, W) int32, 0 = no mask
    """One frame's SAM-like mask id map (steps 1-5 of the module docstring).

    Args:
        instance: Ground-truth instance per pixel.
        box: Layout box per pixel (parts of composite objects).
        face: Face of that box per pixel (parts of one-box objects).
        layout: The room (instance classes, contacts, boxes per instance).
        noise: Mask error rates.
        rng: Source of the errors.

    Returns:
        Mask ids 1..M in random order, 0 where no mask.
    """
    group = _merge_groups(instance, layout, noise, rng)
    sub = _split(instance, box, face, group, layout, noise, rng)
    key = np.where(instance >= 0, group[np.maximum(instance, 0)] * (int(sub.max()) + 1) + sub, -1)
    seg = np.unique(key, return_inverse=True)[1].reshape(key.shape) + 1
    seg[key < 0] = 0
    seg = _jitter(seg, noise.jitter_px, rng)
    seg[_gaps(seg, noise.gap_px)] = 0
    area = np.bincount(seg.ravel())
    drop = (area < noise.min_area * seg.size) | (rng.random(len(area)) < noise.miss)
    drop[0] = True
    keep = np.flatnonzero(~drop)
    relabel = np.zeros(len(area), dtype=np.int32)
    relabel[keep] = rng.permutation(len(keep)).astype(np.int32) + 1
    return relabel[seg]
