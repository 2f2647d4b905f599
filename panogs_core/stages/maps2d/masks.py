"""The torch half's masks: Segment Anything in automatic mode, painted into one id map per frame.

For one image (docs/method.md §17):

1. the image encoder runs once (``SamModel.get_image_embeddings``), the processor having resized the long side to
   the model's input and padded it;
2. a regular grid of ``points_per_side**2`` single-point prompts goes through the prompt encoder and mask decoder
   in batches (:func:`prompts_per_call`), three masks per point (``multimask_output``), each with the model's
   predicted IoU;
3. a candidate is kept when its predicted IoU reaches ``pred_iou_thresh``, its stability score (the IoU of the
   mask thresholded at logit ``+offset`` and at ``-offset``) reaches ``stability_score_thresh`` and its area
   reaches ``min_mask_fraction`` of the image, all measured on the decoder's low-resolution logits cropped to the
   image (SAM measures after upsampling: the same ratios up to boundary pixels);
4. greedy NMS on the masks' IoU (:func:`mask_nms`), best predicted IoU first, then the ``max_masks`` best;
5. the kept logits are upsampled bilinearly to the mask map's size and thresholded at 0, then painted
   (:func:`paint_masks`): larger masks first, so a part inside an object stays visible over it.

DEPARTURE (docs/method.md §17): NMS on mask IoU, not box IoU; painting by area, not by predicted IoU; at most
``max_masks`` masks.
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F

from panogs_core.stages.maps2d.config import Maps2DConfig, scaled_size
from panogs_core.stages.maps2d.models import LoadedModel


def point_grid(points_per_side: int) -> np.ndarray:
    """``(n*n, 2)`` prompt points (x, y) in [0, 1]: cell centres of an ``n x n`` grid, row by row (SAM's grid)."""
    offset = 0.5 / points_per_side
    side = np.linspace(offset, 1 - offset, points_per_side)
    xs, ys = np.meshgrid(side, side)
    return np.stack([xs.ravel(), ys.ravel()], axis=1)


def stability_scores(logits: torch.Tensor, offset: float) -> torch.Tensor:
    """``(M,)`` IoU of each mask's logits ``(M, h, w)`` thresholded at ``+offset`` and ``-offset`` (1 when both
    are empty: nothing there to be unstable)."""
    inner = (logits > offset).flatten(1).sum(1)
    outer = (logits > -offset).flatten(1).sum(1)
    return torch.where(outer > 0, inner.float() / outer.clamp(min=1).float(), torch.ones_like(inner, dtype=torch.float))


def mask_nms(masks: torch.Tensor, scores: torch.Tensor, iou_thresh: float) -> torch.Tensor:
    """Greedy non-maximum suppression on mask IoU.

    Args:
        masks: ``(M, P)`` bool, each row one mask's pixels.
        scores: ``(M,)`` higher is better.
        iou_thresh: a mask whose IoU with a better kept mask exceeds this is dropped.

    Returns:
        ``(K,)`` int64 indices of the kept masks, best score first (ties: lower index first).
    """
    if masks.shape[0] == 0:
        return torch.zeros(0, dtype=torch.long, device=masks.device)
    order = torch.sort(scores, descending=True, stable=True).indices
    ordered = masks[order]
    # float32 counts are exact up to 2**24 pixels per mask, far above a low-resolution mask's size.
    flat = ordered.to(torch.float32)
    inter = flat @ flat.T
    area = flat.sum(1)
    union = area[:, None] + area[None, :] - inter
    iou = torch.where(union > 0, inter / union.clamp(min=1), torch.zeros_like(inter))
    above = (iou > iou_thresh).cpu().numpy()
    suppressed = np.zeros(len(order), dtype=bool)
    keep: list[int] = []
    for i in range(len(order)):  # M is at most max_candidates: a Python loop over rows of a precomputed matrix
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= above[i]
    return order[torch.as_tensor(keep, dtype=torch.long, device=order.device)]


def paint_masks(masks: np.ndarray, scores: np.ndarray) -> np.ndarray:
    """One id map from overlapping binary masks: 0 = no mask, ids 1..K.

    Masks are painted largest first (ties: lower score first, then input order), each over the ones before, so a
    small mask inside a larger one keeps its pixels and the larger one keeps the rest. Masks left with no visible
    pixel are dropped and the ids are renumbered 1..K in painting order.

    Args:
        masks: ``(M, H, W)`` bool.
        scores: ``(M,)`` the masks' predicted IoU.

    Returns:
        ``(H, W)`` uint16 id map.
    """
    count = masks.shape[0]
    out = np.zeros(masks.shape[1:], dtype=np.int64)
    if count == 0:
        return out.astype(np.uint16)
    areas = masks.reshape(count, -1).sum(1)
    order = np.lexsort((np.arange(count), scores, -areas))  # last key first: area desc, score asc, index
    for rank, m in enumerate(order, start=1):
        out[masks[m]] = rank
    visible = np.unique(out[out > 0])
    relabel = np.zeros(count + 1, dtype=np.int64)
    relabel[visible] = np.arange(1, len(visible) + 1)
    return relabel[out].astype(np.uint16)


def automatic_masks(sam: LoadedModel, image: np.ndarray, cfg: Maps2DConfig) -> np.ndarray:
    """The mask id map of one RGB image ``(H, W, 3)`` uint8: ``(Hm, Wm)`` uint16, long side ``mask_long_side``."""
    from PIL import Image

    height, width = image.shape[:2]
    inputs = sam.processor(images=Image.fromarray(image), return_tensors="pt")
    pixels = inputs["pixel_values"].to(sam.device, sam.dtype)
    resized_h, resized_w = (int(v) for v in inputs["reshaped_input_sizes"][0])
    pad_h, pad_w = pixels.shape[-2:]
    with torch.inference_mode():
        embeddings = sam.model.get_image_embeddings(pixels)
        logits, scores = _candidates(sam, embeddings, (resized_h, resized_w), (pad_h, pad_w), cfg)
        keep = mask_nms((logits > 0).flatten(1), scores, cfg.nms_iou_thresh)[: cfg.max_masks]
        out_h, out_w = scaled_size(height, width, cfg.mask_long_side)
        kept = logits[keep].float()
        binary = torch.zeros((len(keep), out_h, out_w), dtype=torch.bool, device=logits.device)
        for start in range(0, len(keep), 32):  # 32 maps of 640x480 float32: 40 MB at a time
            chunk = F.interpolate(kept[start : start + 32, None], (out_h, out_w), mode="bilinear", align_corners=False)
            binary[start : start + 32] = chunk[:, 0] > 0
    return paint_masks(binary.cpu().numpy(), scores[keep].float().cpu().numpy())


def _candidates(
    sam: LoadedModel,
    embeddings: torch.Tensor,
    resized: tuple[int, int],
    padded: tuple[int, int],
    cfg: Maps2DConfig,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Low-resolution logits ``(M, h, w)`` (cropped to the image) and predicted IoU ``(M,)`` of the masks that
    pass the score, stability and area filters, at most ``max_candidates`` of them (best predicted IoU)."""
    grid = torch.as_tensor(point_grid(grid_side(cfg, sam.device)), dtype=torch.float32)
    grid = grid * torch.tensor([resized[1], resized[0]], dtype=torch.float32)  # (x, y) in the model's input pixels
    kept_logits: list[torch.Tensor] = []
    kept_scores: list[torch.Tensor] = []
    pending = 0
    batch_size = prompts_per_call(cfg, sam.device)
    for start in range(0, len(grid), batch_size):
        points = grid[start : start + batch_size]
        batch = len(points)
        out = sam.model(
            image_embeddings=embeddings,
            input_points=points.view(1, batch, 1, 2).to(sam.device, sam.dtype),
            input_labels=torch.ones((1, batch, 1), dtype=torch.long, device=sam.device),
            multimask_output=True,
        )
        low = out.pred_masks[0].flatten(0, 1)  # (batch * 3, h, w) over the padded input
        iou = out.iou_scores[0].flatten().float()
        low_h = round(low.shape[-2] * resized[0] / padded[0])
        low_w = round(low.shape[-1] * resized[1] / padded[1])
        low = low[:, :low_h, :low_w].float()
        stable = stability_scores(low, cfg.stability_score_offset)
        area = (low > 0).flatten(1).float().mean(1)
        ok = (iou >= cfg.pred_iou_thresh) & (stable >= cfg.stability_score_thresh)
        ok &= (area >= cfg.min_mask_fraction) & (area > 0)
        kept_logits.append(low[ok].to(torch.float16))
        kept_scores.append(iou[ok])
        pending += int(ok.sum())
        if pending > 2 * cfg.max_candidates:  # compact now and then, not per call: small calls on a CPU
            kept_logits, kept_scores = _best(kept_logits, kept_scores, cfg.max_candidates)
            pending = len(kept_scores[0])
    kept_logits, kept_scores = _best(kept_logits, kept_scores, cfg.max_candidates)
    return kept_logits[0], kept_scores[0]


CPU_POINTS_PER_SIDE = 8  # the CPU default grid (docs/method.md §17, "CPU costs and the CPU default")
GPU_POINTS_PER_SIDE = 32  # SAM's automatic mode


def grid_side(cfg: Maps2DConfig, device: torch.device) -> int:
    """Prompt points per image side: ``points_per_side``, or by device when None: 8 on a CPU (the decoder's cost is
    linear in the points: 0.27 CPU s each there, docs/benchmarks.md), 32 (SAM's) on a GPU."""
    if cfg.points_per_side is not None:
        return cfg.points_per_side
    return GPU_POINTS_PER_SIDE if device.type == "cuda" else CPU_POINTS_PER_SIDE


def prompts_per_call(cfg: Maps2DConfig, device: torch.device) -> int:
    """Prompt points per decoder call: ``points_per_batch``, or by device when None (docs/method.md §17): 4 on a
    CPU, where the decoder's per-prompt tensors (4,096 image tokens x 256 channels each) then stay in the caches
    (docs/benchmarks.md, "2D maps stage costs"), 64 (SAM's) on a GPU."""
    if cfg.points_per_batch is not None:
        return cfg.points_per_batch
    return 64 if device.type == "cuda" else 4


def _best(
    logits: list[torch.Tensor], scores: list[torch.Tensor], count: int
) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The ``count`` candidates of best predicted IoU, in their order (bounds memory and the NMS's M x M matrix)."""
    merged_logits, merged_scores = torch.cat(logits), torch.cat(scores)
    if len(merged_scores) > count:
        top = torch.topk(merged_scores, count).indices.sort().values
        merged_logits, merged_scores = merged_logits[top], merged_scores[top]
    return [merged_logits], [merged_scores]
