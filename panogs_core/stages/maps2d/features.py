"""The torch half's language features: each mask's crops embedded by a CLIP image tower and painted on its cells.

For one image and its mask id map (docs/method.md §17; the OpenMask3D / ConceptFusion recipe):

1. each mask's box (in the image's pixels) gives one square crop per ``crop_margins`` value, centred on the box,
   of side ``longer box side * (1 + 2 * margin)``; what falls outside the image is the processor's mean colour
   (zero after normalisation), so the processor's centre crop of a square removes nothing;
2. the crops and the whole image (padded to a square the same way) are embedded by the image tower
   (``CLIPVisionModelWithProjection``, the projected embedding) and L2-normalised; a mask's feature is the
   normalised mean of its crops';
3. :func:`pooled_feature_map` writes them on a ``feature_long_side`` grid: each cell takes the feature of the mask
   at its centre (docs/scene_format.md §2.3), blended with the whole image's by ``global_mix``; cells no mask
   covers take the whole image's. Unit rows, float16.
"""

from __future__ import annotations

import numpy as np
import torch

from panogs_core.stages.maps2d.config import Maps2DConfig, scaled_size
from panogs_core.stages.maps2d.models import LoadedModel


def mask_boxes(ids: np.ndarray, count: int) -> np.ndarray:
    """``(count, 4)`` float boxes ``x0, y0, x1, y1`` (pixel edges, exclusive end) of ids 1..count in an id map;
    an id with no pixel gets an empty box at 0."""
    boxes = np.zeros((count, 4), dtype=np.float64)
    rows, cols = np.nonzero(ids)
    labels = ids[rows, cols].astype(np.int64) - 1
    inside = labels < count
    rows, cols, labels = rows[inside], cols[inside], labels[inside]
    if len(labels) == 0:
        return boxes
    big = np.iinfo(np.int64).max
    x0 = np.full(count, big)
    y0 = np.full(count, big)
    x1 = np.full(count, -1)
    y1 = np.full(count, -1)
    np.minimum.at(x0, labels, cols)
    np.minimum.at(y0, labels, rows)
    np.maximum.at(x1, labels, cols)
    np.maximum.at(y1, labels, rows)
    seen = x1 >= 0
    boxes[seen] = np.stack([x0[seen], y0[seen], x1[seen] + 1, y1[seen] + 1], axis=1)
    return boxes


def square_crop(image: np.ndarray, box: np.ndarray, margin: float, fill: np.ndarray) -> np.ndarray:
    """The square crop of ``image`` ``(H, W, 3)`` around ``box`` (x0, y0, x1, y1) with ``margin`` of its longer
    side on each side; outside the image, ``fill`` (uint8 RGB)."""
    height, width = image.shape[:2]
    side = max(1, round(max(box[2] - box[0], box[3] - box[1]) * (1 + 2 * margin)))
    cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
    x0, y0 = round(cx - side / 2), round(cy - side / 2)
    crop = np.broadcast_to(np.asarray(fill, dtype=np.uint8), (side, side, 3)).copy()
    sx0, sy0 = max(x0, 0), max(y0, 0)
    sx1, sy1 = min(x0 + side, width), min(y0 + side, height)
    if sx1 > sx0 and sy1 > sy0:
        crop[sy0 - y0 : sy1 - y0, sx0 - x0 : sx1 - x0] = image[sy0:sy1, sx0:sx1]
    return crop


def pooled_feature_map(
    ids: np.ndarray,
    mask_features: np.ndarray,
    image_feature: np.ndarray,
    size: tuple[int, int],
    global_mix: float,
) -> np.ndarray:
    """The feature map of one frame from its id map and the features of its masks and of the whole image.

    Args:
        ids: ``(Hm, Wm)`` id map, 0 = no mask, ids 1..K.
        mask_features: ``(K, D)`` unit rows, row k-1 for id k.
        image_feature: ``(D,)`` unit, the whole image's.
        size: ``(Hf, Wf)`` of the map.
        global_mix: weight of the whole image's feature in a mask's cells.

    Returns:
        ``(Hf, Wf, D)`` float16 with unit rows: cell (i, j) reads ``ids`` at its centre
        (docs/scene_format.md §2.3).
    """
    height, width = ids.shape
    rows = np.minimum(((np.arange(size[0]) + 0.5) * height / size[0]).astype(np.int64), height - 1)
    cols = np.minimum(((np.arange(size[1]) + 0.5) * width / size[1]).astype(np.int64), width - 1)
    cells = ids[rows[:, None], cols[None, :]].astype(np.int64)
    image_feature = image_feature.astype(np.float32)
    blended = (1 - global_mix) * mask_features.astype(np.float32) + global_mix * image_feature
    table = _unit(np.concatenate([image_feature[None], blended], axis=0))
    cells = np.where(cells <= len(mask_features), cells, 0)  # ids past the table: no feature of their own
    return table[cells].astype(np.float16)


def frame_features(clip: LoadedModel, image: np.ndarray, ids: np.ndarray, cfg: Maps2DConfig) -> np.ndarray:
    """``(Hf, Wf, D)`` float16 feature map of one RGB image ``(H, W, 3)`` uint8 and its id map ``(Hm, Wm)``."""
    height, width = image.shape[:2]
    count = int(ids.max()) if ids.size else 0
    boxes = mask_boxes(ids, count) * np.array([width / ids.shape[1], height / ids.shape[0]] * 2)
    fill = np.clip(np.rint(np.asarray(clip.processor.image_mean) * 255), 0, 255).astype(np.uint8)
    whole = np.array([0.0, 0.0, width, height])
    crops = [square_crop(image, whole, 0.0, fill)]
    owners = [-1]
    for k in range(count):
        if boxes[k, 2] <= boxes[k, 0]:
            continue  # an id with no pixel keeps the image's feature (never read: no cell holds it)
        for margin in cfg.crop_margins:
            crops.append(square_crop(image, boxes[k], margin, fill))
            owners.append(k)
    embedded = _embed(clip, crops, cfg.crops_per_batch)
    owner = np.asarray(owners)
    sums = np.zeros((count, embedded.shape[1]), dtype=np.float32)
    np.add.at(sums, owner[1:], embedded[1:])
    sums[np.linalg.norm(sums, axis=1) == 0] = embedded[0]
    size = scaled_size(ids.shape[0], ids.shape[1], cfg.feature_long_side)
    return pooled_feature_map(ids, _unit(sums), embedded[0], size, cfg.global_mix)


def _embed(clip: LoadedModel, crops: list[np.ndarray], batch: int) -> np.ndarray:
    """``(n, D)`` unit float32 image-tower features of RGB crops."""
    from PIL import Image

    out = []
    with torch.inference_mode():
        for start in range(0, len(crops), batch):
            images = [Image.fromarray(c) for c in crops[start : start + batch]]
            pixels = clip.processor(images=images, return_tensors="pt")["pixel_values"]
            feats = clip.model(pixel_values=pixels.to(clip.device, clip.dtype)).image_embeds
            out.append(feats.float().cpu().numpy())
    return _unit(np.concatenate(out, axis=0))


def _unit(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)
