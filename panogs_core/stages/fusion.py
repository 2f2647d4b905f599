"""Stage 3: multi-view fusion of the 2D language features onto the primitives, with a confidence for each.

docs/method.md §3.1 (``fuse_feature.py``). For every primitive p, over the feature frames that see it
(stage 2):

* the pixel (u, v) where p lands reads the feature-map cell
  ``(floor((v + 0.5) Hf / H), floor((u + 0.5) Wf / W))`` (docs/scene_format.md §2.3; nearest cell, no
  bilinear, as the reference's nearest-pixel lookup, docs/method.md pitfall 8);
* the cell's feature is unit-normalised (the reference fuses LSeg flip-sums; it notes that only the direction
  matters downstream, so unit pixels are harmless). A zero (or non-finite) feature means "no feature here": it
  adds nothing and does not count as an observation;
* ``F(p)`` = mean of those unit features; ``S(p)`` = how many there were; ``V(p)`` = sum over dimensions of
  their population variance. Unseen primitives get ``F = 0`` and weight 0 (docs/method.md pitfall 7);
* the confidence weight, by ``FusionConfig.confidence``:

  - ``"code"`` (DEFAULT): the official code, ``w = 10 S' / (V' + 1)`` with ``S' = S / (max S - min S)`` and
    ``V' = V / (max V - min V)`` over all primitives (division by the range, not min-max normalisation). It is
    the default because the published numbers were produced by it (docs/method.md pitfall 7), and because it
    stays bounded where the paper form does not (a primitive seen once has V = 0);
  - ``"paper"``: the paper's ``gamma = observations / sum of variances`` (PAPER != CODE in docs/method.md §3.1),
    with ``paper_variance_eps`` added to the variance so that V = 0 gives a finite weight;
  - ``"none"``: 1 for every seen primitive (an ablation).

The frames are streamed: one feature map is read (memory-mapped, in blocks of cells), the cells the frame's
primitives use are gathered and normalised, added into an (N, D) float32 sum, and the map is dropped. The rows of
the next frames are made on threads meanwhile (as many frames ahead as the process has threads), and added in
frame order: the sum is the sequential one, to the bit. Peak memory is the (N, D) sum plus a few frames' gathered
cells; nothing is ever N x V x D.

DEPARTURE (memory, docs/method.md §3.1): frames streamed, never every key frame's feature map at once.

Colours are fused the same way when the key frames have colour: mean RGB in [0, 1] over the seeing frames.
"""

from __future__ import annotations

import logging
import math
import queue
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
from scipy import sparse
from scipy.sparse._sparsetools import csr_matvecs as _csr_matvecs  # Y += A X, the kernel of ``csr @ dense``

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.io.bundle import Bundle
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.visibility import Visibility
from panogs_core.threads import decode_threads, prefetched, torch_threads
from panogs_core.types import Frame

log = logging.getLogger(__name__)

ConfidenceMode = Literal["code", "paper", "none"]
_CONFIDENCE_MODES = ("code", "paper", "none")
# Feature-map cells per block of :func:`_frame_rows`: a (1024, 512) float32 block is 2 MB, an L2 cache's worth.
_BLOCK = 1024


@dataclass(frozen=True, kw_only=True)
class FusionConfig:
    """Settings of stage 3.

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    confidence: ConfidenceMode = "code"  # weight form; "code" = official code (docs/method.md §3.1, pitfall 7)
    weight_scale: float = 10.0  # the 10 of w = 10 S' / (V' + 1); docs/method.md §3.1 (code form only)
    paper_variance_eps: float = 1e-2  # added to sum of variances in the paper form (V = 0 when seen once)
    min_feature_norm: float = 1e-6  # pixel features with a smaller L2 norm are "no feature" (not counted)
    fuse_colors: bool = True  # also average the key frames' RGB onto the primitives (for exports)
    # DEPARTURE (mask pooling, docs/method.md §3.1): a primitive inside a 2D mask reads (1 - a) f_cell + a f_mask,
    # f_mask the mask's pooled feature (``mask_pooled_features``); 0 = the reference's own cell.
    mask_pooling: float = 0.5

    def __post_init__(self) -> None:
        if self.confidence not in _CONFIDENCE_MODES:
            raise ConfigError(f"fusion.confidence: expected one of {_CONFIDENCE_MODES}, got {self.confidence!r}")
        if not (math.isfinite(self.weight_scale) and self.weight_scale > 0):
            raise ConfigError(f"fusion.weight_scale: expected a finite value > 0, got {self.weight_scale!r}")
        if not (math.isfinite(self.paper_variance_eps) and self.paper_variance_eps > 0):
            raise ConfigError(
                f"fusion.paper_variance_eps: expected a finite value > 0, got {self.paper_variance_eps!r}"
            )
        if not (math.isfinite(self.mask_pooling) and 0.0 <= self.mask_pooling <= 1.0):
            raise ConfigError(f"fusion.mask_pooling: expected a value in [0, 1], got {self.mask_pooling!r}")
        if not (math.isfinite(self.min_feature_norm) and self.min_feature_norm >= 0):
            raise ConfigError(f"fusion.min_feature_norm: expected a finite value >= 0, got {self.min_feature_norm!r}")


@dataclass(frozen=True)
class FusedFeatures:
    """Per-primitive fused 2D features, their confidence, and (optionally) fused colours."""

    features: np.ndarray  # (N, D) float32, mean of unit-normalised pixel features over seeing frames; 0 if unseen
    weights: np.ndarray  # (N,) float32, confidence >= 0; 0 where unseen
    seen_count: np.ndarray  # (N,) int32, number of feature frames that see the primitive
    colors: np.ndarray | None  # (N, 3) float32 in [0, 1], mean colour over seeing frames (None: no colour)

    def __post_init__(self) -> None:
        n = self.features.shape[0]
        if self.features.ndim != 2:
            raise ShapeError(f"FusedFeatures.features: expected (N, D), got {self.features.shape}")
        expected: dict[str, tuple[int, ...]] = {"weights": (n,), "seen_count": (n,)}
        if self.colors is not None:
            expected["colors"] = (n, 3)
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ShapeError(f"FusedFeatures.{name}: expected {shape}, got {getattr(self, name).shape}")

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path`` (no pickles); ``colors`` is omitted when None."""
        arrays: dict[str, Any] = {
            "features": self.features,
            "weights": self.weights,
            "seen_count": self.seen_count,
        }
        if self.colors is not None:
            arrays["colors"] = self.colors
        save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> FusedFeatures:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as z:
            return cls(
                features=z["features"],
                weights=z["weights"],
                seen_count=z["seen_count"],
                colors=z["colors"] if "colors" in z.files else None,
            )


def fuse_features(
    bundle: Bundle,
    visibility: Visibility,
    num_points: int,
    cfg: FusionConfig,
    *,
    on_progress: ProgressFn | None = None,
) -> FusedFeatures:
    """Average each primitive's unit pixel features over the feature frames that see it; weight by confidence.

    Args:
        bundle: The opened bundle (camera, feature maps, colour).
        visibility: Stage 2 output; its frames without a feature map contribute colour only.
        num_points: N, the number of primitives.
        cfg: Stage settings.
        on_progress: ``(done, total)`` once per visibility frame.

    Returns:
        Fused features (N, D) with D = ``scene.feature_dim``, weights, seen counts, colours.

    Raises:
        InputError: if a visibility frame id is not a frame of the scene.
        ShapeError: if the visibility indexes past ``num_points``, or a feature map or colour image has the
            wrong shape.
    """
    frames = _frames_by_id(bundle, visibility)
    if visibility.point_index.size and int(visibility.point_index.max()) >= num_points:
        raise ShapeError(f"visibility: point index {int(visibility.point_index.max())} >= num_points ({num_points})")
    start = time.perf_counter()
    features = _FeatureSum(num_points, bundle.feature_dim)
    colors = (
        _ColorSum(num_points, (bundle.camera.height, bundle.camera.width))
        if cfg.fuse_colors and any(f.color for f in frames)
        else None
    )

    workers = decode_threads()
    buffers: queue.SimpleQueue[_CellBuffers] = queue.SimpleQueue()  # one set per frame in flight
    for _ in range(workers + 1):
        buffers.put(_CellBuffers())

    def prepare(v: int) -> tuple[_FrameRows | None, np.ndarray | None]:  # the frame's rows, and colour if used
        """Everything of frame v that does not touch the sums: decoding, the unit rows (run on worker threads)."""
        frame, (point_index, row, col) = frames[v], visibility.frame(v)
        rows = None
        if frame.features is not None and point_index.size:
            pooled = frame.masks is not None and cfg.mask_pooling > 0.0
            masks = bundle.read_masks(frame) if pooled else None
            rows = _FrameRows.of(bundle, frame, point_index, row, col, cfg.min_feature_norm, masks, cfg.mask_pooling,
                                 buffers.get())  # fmt: skip
        coloured = colors is not None and frame.color is not None and point_index.size
        return rows, bundle.read_color(frame) if coloured else None

    # The frames' rows are made up to ``workers`` frames ahead on threads (OpenCV decodes, numpy, scipy and torch
    # compute without the GIL); the sums take them here, in frame order, so the result is the sequential one to
    # the bit. torch on one thread: its calls here are many and short (a block of cells, a chunk of rows), and
    # each of torch's parallel regions woke the pool's sleeping threads, which cost more than the split saved.
    with torch_threads(1):
        for v, (rows, color) in enumerate(prefetched(prepare, range(len(frames)), workers)):
            if rows is not None:
                features.add(rows)
                buffers.put(rows.buffers)
            if colors is not None and color is not None:
                colors.add(frames[v], color, *visibility.frame(v))
            report(on_progress, v + 1, len(frames))
    feat_sum, count = features.total, features.count  # (N, D) becomes the mean in place, (N,)
    feat_sum *= (1.0 / np.maximum(count, 1)).astype(np.float32)[:, None]  # sum -> mean; unseen rows stay 0
    weights = confidence_weights(feat_sum, count, cfg)
    log.info(
        "fusion: %d points x %d frames, %d seen, in %.2f s",
        num_points, len(frames), int(np.count_nonzero(count)), time.perf_counter() - start,
    )  # fmt: skip
    return FusedFeatures(
        features=feat_sum,
        weights=weights,
        seen_count=count,
        colors=None if colors is None else colors.mean(),
    )


def feature_cells(
    row: np.ndarray,  # (T,) int32, depth-image row v
    col: np.ndarray,  # (T,) int32, depth-image column u
    image_hw: tuple[int, int],
    feature_hw: tuple[int, int],
) -> np.ndarray:  # (T,) int64 flat cell index r * Wf + c
    """Feature-map cell of each pixel, ``(floor((v + 0.5) Hf / H), floor((u + 0.5) Wf / W))``.

    The rule of docs/scene_format.md §2.3.

    Exact integer arithmetic: ``floor((2v + 1) Hf / 2H)``, so no cell boundary is missed by rounding.

    Example:
        >>> feature_cells(np.array([0, 5]), np.array([0, 7]), (6, 8), (3, 4)).tolist()
        [0, 11]
    """
    h, w = image_hw
    hf, wf = feature_hw
    r = np.minimum(((2 * row.astype(np.int64) + 1) * hf) // (2 * h), hf - 1)
    c = np.minimum(((2 * col.astype(np.int64) + 1) * wf) // (2 * w), wf - 1)
    return r * wf + c


def confidence_weights(
    features: np.ndarray,  # (N, D) float32, mean of unit features (0 where unseen)
    count: np.ndarray,  # (N,) int, observations
    cfg: FusionConfig,
) -> np.ndarray:  # (N,) float32 >= 0, 0 where unseen
    """Confidence of each fused feature (docs/method.md §3.1; forms described in the module docstring).

    The sum over dimensions of the population variance of unit vectors f_m with mean F is
    ``sum_d (mean_m f_md^2 - F_d^2) = mean_m |f_m|^2 - |F|^2 = 1 - |F|^2``, so it needs no second accumulator.

    Example:
        >>> f = np.array([[1.0, 0.0], [0.6, 0.0], [0.0, 0.0]], np.float32)  # 3rd primitive unseen
        >>> confidence_weights(f, np.array([2, 4, 0]), FusionConfig()).round(3).tolist()
        [5.0, 5.0, 0.0]
    """
    seen = count > 0
    sq_norm = np.einsum("nd,nd->n", features, features).astype(np.float64)  # (N,) |F|^2 (float32 sum: ~1e-7)
    variance = np.where(seen, np.clip(1.0 - sq_norm, 0.0, 1.0), 0.0)  # (N,) unseen: 0, as the reference
    obs = count.astype(np.float64)  # (N,)
    if cfg.confidence == "code":
        weights = cfg.weight_scale * (obs / _range(obs)) / (variance / _range(variance) + 1.0)
    elif cfg.confidence == "paper":
        weights = obs / (variance + cfg.paper_variance_eps)
    else:
        weights = np.ones_like(obs)
    return np.where(seen, weights, 0.0).astype(np.float32)


def _range(x: np.ndarray) -> float:
    """``max - min`` of x, the reference's divisor.

    DEPARTURE (docs/method.md §3.1): where every value is equal the reference divides by zero; the maximum (1 when
    that is 0 too) is used instead.
    """
    lo, hi = (float(x.min()), float(x.max())) if x.size else (0.0, 0.0)
    if hi - lo > 0:
        return hi - lo
    return hi if hi > 0 else 1.0


def _frames_by_id(bundle: Bundle, visibility: Visibility) -> list[Frame]:
    by_id = {f.id: f for f in bundle.frames}
    missing = [fid for fid in visibility.frame_ids if fid not in by_id]
    if missing:
        raise InputError(f"visibility: frame ids not in the scene: {missing[:5]}")
    return [by_id[fid] for fid in visibility.frame_ids]


class _FeatureSum:
    """Running per-primitive sum of unit pixel features and observation count.

    Each frame's unit rows (:class:`_FrameRows`) are added to their primitives in one pass by scipy's CSR kernel
    (``csr_matvecs``, which accumulates into its output and releases the interpreter lock): a matrix with one entry
    of 1 per primitive the frame sees, times the frame's rows. Each primitive gets one ``sum += row`` per frame, in
    frame order, as with an indexed add: the sums are the same to the bit. It replaced torch's ``index_select`` into
    a buffer then ``index_add_`` from it, which read and wrote every added row twice (docs/benchmarks.md, "Fusion and
    primitives speed").
    """

    def __init__(self, num_points: int, dim: int) -> None:
        self.total = np.zeros((num_points, dim), dtype=np.float32)  # (N, D)
        self.count = np.zeros(num_points, dtype=np.int32)  # (N,)
        self._row_starts = np.zeros(num_points + 1, dtype=np.int64)  # (N + 1,) the CSR rows of a frame, reused
        self._ones = np.ones(0, dtype=np.float32)  # the matrix's entries, grown as needed

    def add(self, frame: _FrameRows) -> None:
        """Add one frame's unit rows to the primitives that read them."""
        num_points, dim = self.total.shape
        if frame.table.shape[1] != dim:
            raise ShapeError(f"features: expected {dim} dimensions, got {frame.table.shape[1]}")
        targets, rows = frame.targets, frame.rows
        self.count[targets] += 1  # indices are unique within a frame, so fancy-index += is exact
        if targets.size > 1 and not (targets[1:] > targets[:-1]).all():  # CSR entries go in row order
            order = np.argsort(targets)
            targets, rows = targets[order], rows[order]
        starts = self._row_starts
        starts.fill(0)
        starts[targets + 1] = 1
        np.cumsum(starts, out=starts)  # row t holds entry starts[t] (one entry) or none
        if self._ones.size < targets.size:
            self._ones = np.ones(targets.size, dtype=np.float32)
        table = np.ascontiguousarray(frame.table)
        _csr_matvecs(num_points, table.shape[0], dim, starts, rows, self._ones[: targets.size], table.reshape(-1),
                     self.total.reshape(-1))  # fmt: skip


@dataclass(frozen=True)
class _FrameRows:
    """One frame's unit pixel features: ``table`` rows (in ``buffers``, valid until they are reused) and, for each
    primitive with a feature, its index and its row."""

    table: np.ndarray  # (U, D) float32 unit rows, zero where no feature
    targets: np.ndarray  # (T,) int64 primitive indices, unique
    rows: np.ndarray  # (T,) int64 row of each
    buffers: _CellBuffers

    @classmethod
    def of(
        cls,
        bundle: Bundle,
        frame: Frame,
        point_index: np.ndarray,  # (T_v,) int32, unique within the frame
        row: np.ndarray,  # (T_v,) int32
        col: np.ndarray,  # (T_v,) int32
        min_norm: float,
        masks: np.ndarray | None,  # (Hm, Wm) the frame's mask ids, or None: no mask pooling
        mask_pooling: float,
        buffers: _CellBuffers,
    ) -> _FrameRows:
        """Read the frame's feature map (memory-mapped, dropped on return) into unit rows in ``buffers``."""
        fmap = bundle.read_features(frame)  # (Hf, Wf, D), memory-mapped
        d = bundle.feature_dim
        if fmap.ndim != 3 or fmap.shape[2] != d:
            raise ShapeError(f"features of frame {frame.id}: expected (Hf, Wf, {d}), got {fmap.shape}")
        image_hw = (bundle.camera.height, bundle.camera.width)
        src = feature_cells(row, col, image_hw, fmap.shape[:2])  # (T_v,) cell of each primitive
        if masks is not None and mask_pooling > 0.0:
            mask_pixel = feature_cells(row, col, image_hw, masks.shape)  # (T_v,) the mask pixel of each primitive
            table, index = _frame_rows(fmap, src, min_norm, buffers, (masks, mask_pixel, mask_pooling))
        else:
            table, index = _frame_rows(fmap, src, min_norm, buffers)
        valid = _unit_rows_(table, min_norm)  # a zero feature is no observation
        keep = np.flatnonzero(valid[index])
        return cls(table=table, targets=point_index[keep].astype(np.int64), rows=index[keep], buffers=buffers)


class _CellBuffers:
    """A block of a feature map's float32 rows, the rows of a frame and the mask pixels' cells, kept from frame to
    frame.

    A fresh 40 MB array per frame (a 160 x 120 x 512 map) cost more in page faults than the conversion itself
    (docs/benchmarks.md, "Speed at ScanNet size"); the rows' temporaries did the same on a smaller scale. One set
    per frame in flight: where a frame's primitives fill most of its map (a small room seen whole, frame after
    frame), its rows are about as many as the map's cells, so the set holds one row buffer, grown by a quarter.
    """

    def __init__(self) -> None:
        self._block: np.ndarray | None = None  # (_BLOCK, D) float32
        self._rows: np.ndarray | None = None  # (capacity, D) float32
        self._pixel_cells: dict[tuple[tuple[int, int], tuple[int, int]], tuple[np.ndarray, np.ndarray]] = {}

    def rows(self, count: int, dim: int) -> np.ndarray:  # (count, D) float32 view
        """A row buffer of ``count`` rows, valid until the next call."""
        if self._rows is None or self._rows.shape[0] < count or self._rows.shape[1] != dim:
            grown = self._rows.shape[0] + self._rows.shape[0] // 4 if self._rows is not None else 0
            self._rows = np.empty((max(count, grown), dim), dtype=np.float32)
        return self._rows[:count]

    def pixel_cells(self, mask_hw: tuple[int, int], feature_hw: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """:func:`mask_pixel_cells` of these sizes, computed once (every frame of a bundle has the same)."""
        key = (mask_hw, feature_hw)
        if key not in self._pixel_cells:
            self._pixel_cells[key] = mask_pixel_cells(mask_hw, feature_hw)
        return self._pixel_cells[key]

    def block(self, rows: np.ndarray) -> np.ndarray:  # (B, D) float32, valid until the next call
        """Rows of a map (as stored) as float32, in the kept buffer of ``_BLOCK`` rows (a private copy)."""
        return _to_float32(rows, self.scratch(len(rows), rows.shape[1]))

    def scratch(self, count: int, dim: int) -> np.ndarray:  # (count, D) float32, count <= _BLOCK
        """The kept buffer of ``_BLOCK`` rows (what :meth:`block` writes), valid until the next call."""
        if self._block is None or self._block.shape[1] != dim:
            self._block = np.empty((_BLOCK, dim), dtype=np.float32)
        return self._block[:count]


def _to_float32(rows: np.ndarray, out: np.ndarray) -> np.ndarray:
    """Copy (R, D) rows as stored into the float32 ``out`` (same shape) and return it."""
    import torch

    if rows.dtype == np.dtype(np.float16):  # torch converts float16 several times faster than numpy
        # Straight from the memory-mapped file: a float16 copy first cost as much again (its page faults).
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="The given NumPy array is not writable")
            source = torch.from_numpy(np.asarray(rows))  # read-only map: torch only reads it
        torch.from_numpy(out).copy_(source)
    else:
        np.copyto(out, rows, casting="unsafe")
    return out


def _cells_and_inverse_norms(fmap: np.ndarray, min_norm: float) -> tuple[np.ndarray, np.ndarray]:
    """Every cell of a feature map as a float32 row (a private copy), and ``1 / |f_c|`` (0 where the cell holds no
    feature): ``(C, D)`` and ``(C,)``, the whole map at once (the frame loop reads it by blocks, :func:`_frame_rows`).

    The rows stay as read: the unit scale is folded into whatever reads them (the pooling weights).
    """
    hf, wf, d = fmap.shape
    cells = _to_float32(fmap.reshape(hf * wf, d), np.empty((hf * wf, d), dtype=np.float32))
    return cells, _inverse_norms_(cells, min_norm)


def _frame_rows(
    fmap: np.ndarray,  # (Hf, Wf, D) feature map as stored (float16 or float32, memory-mapped)
    src: np.ndarray,  # (T_v,) int64 cell of each primitive
    min_norm: float,
    buffers: _CellBuffers,
    masks: tuple[np.ndarray, np.ndarray, float] | None = None,  # (Hm, Wm) ids, (T_v,) mask pixels, pooling weight
) -> tuple[np.ndarray, np.ndarray]:  # (U, D) float32 rows (not yet unit), (T_v,) int64 each primitive's row
    """One row per cell in use (per (cell, mask) pair with ``masks``): the unit cell, blended towards the mask's
    pooled feature.

    The blend of cell c with mask m is ``(1 - weight) f_c / |f_c| + weight pool_m`` (made unit by the caller); the
    pairs without a mask (m = 0) and masks without a pooled feature have ``pool_m = 0``: the plain unit cell. Rows
    are per pair, not per primitive: many primitives share a cell when the maps are coarse. The rows are written
    into ``buffers`` (valid until its next use).

    The map is read in blocks of ``_BLOCK`` cells that stay in the L2 cache: each block is converted to float32,
    its norms taken, its share of the masks' pooled features added and its rows in use copied out, so that the
    (C, D) float32 map is never written whole and read back three times (the conversion, the norms and the pooling
    each streamed 40 MB per 160 x 120 x 512 map). Every row and every pooled feature is summed in the same order
    as from the whole map: the results are identical to the bit.
    """
    import torch

    hf, wf, d = fmap.shape
    num_cells = hf * wf
    flat = fmap.reshape(num_cells, d)
    if masks is None:
        cell, index = np.unique(src, return_inverse=True)  # the cells in use, and each primitive's
        mask, weight, pooling = None, 0.0, None
    else:
        mask_ids, mask_pixel, weight = masks
        dense, mask_values = _dense_mask_ids(mask_ids)  # (Hm Wm,) ids renumbered 0..M (0 stays "no mask")
        num_masks = len(mask_values)
        pair, index = np.unique(src * num_masks + dense[mask_pixel], return_inverse=True)  # (U,), (T_v,)
        cell, mask = pair // num_masks, pair % num_masks
        pooling = _BlockPooling(dense, num_masks, buffers.pixel_cells(mask_ids.shape, (hf, wf)), d)
    table = buffers.rows(len(cell), d)  # (U, D)
    table_t = torch.from_numpy(table)
    starts = range(0, num_cells, _BLOCK)
    bounds = np.searchsorted(cell, [*starts, num_cells])  # the rows of each block's cells (cell is sorted)
    for b, c0 in enumerate(starts):
        block = buffers.block(flat[c0 : c0 + _BLOCK])  # (B, D) float32
        inv_norm = _inverse_norms_(block, min_norm)  # (B,) 1 / |f_c|, 0 (and the row zeroed) where no feature
        if pooling is not None:
            pooling.add(b, block, inv_norm)
        lo, hi = int(bounds[b]), int(bounds[b + 1])
        if hi > lo:
            local = cell[lo:hi] - c0
            # torch's gather into a kept buffer: numpy's np.take(out=) took twice as long as a fresh cells[cell].
            torch.index_select(torch.from_numpy(block), 0, torch.from_numpy(local), out=table_t[lo:hi])
            table[lo:hi] *= ((1.0 - weight) * inv_norm[local])[:, None]
    if pooling is not None and mask is not None:
        pooled = pooling.pooled(min_norm)  # (M + 1, D), row 0 zero
        scaled_pool = torch.from_numpy(weight * pooled)  # (weight pool)[m] is weight (pool[m]), exactly
        mask_t = torch.from_numpy(mask)
        for lo in range(0, len(mask), _BLOCK):  # through the block buffer: no second (U, D) buffer a frame
            ids = mask_t[lo : lo + _BLOCK]
            part = torch.index_select(scaled_pool, 0, ids, out=torch.from_numpy(buffers.scratch(len(ids), d)))
            table[lo : lo + len(ids)] += part.numpy()
    return table, index.reshape(-1)


def _inverse_norms_(cells: np.ndarray, min_norm: float) -> np.ndarray:  # (C,) float32
    """``1 / |f_c|`` of each float32 row, 0 where the row holds no feature; such rows are zeroed in place (a
    non-finite cell would turn its products into NaN)."""
    with np.errstate(invalid="ignore", over="ignore"):
        norm = np.sqrt(np.einsum("cd,cd->c", cells, cells))  # (C,)
    valid = np.isfinite(norm) & (norm > min_norm)
    inv_norm = np.zeros(len(norm), dtype=np.float32)
    inv_norm[valid] = 1.0 / norm[valid]
    if not valid.all():
        cells[~valid] = 0.0
    return inv_norm


class _BlockPooling:
    """The masks' pooled features (:func:`_pool_cells`) summed block by block of cells, as the blocks are read.

    The (mask, cell) terms are grouped by block, then by mask, then by cell; each block's terms are one small CSR
    product added into the (M + 1, D) sum by scipy's own kernel (``csr_matvecs``, which accumulates), so every
    mask's sum runs over its cells in the same order as the one product over the whole map.
    """

    def __init__(
        self,
        dense: np.ndarray,  # (Hm Wm,) int64 dense mask number of every mask pixel
        num_masks: int,  # M + 1
        pixel_cells: tuple[np.ndarray, np.ndarray],  # mask_pixel_cells(mask_hw, feature_hw)
        dim: int,
    ) -> None:
        cell, pixels_in_cell = pixel_cells  # (Hm Wm,), (C,)
        num_cells = len(pixels_in_cell)
        n_mc = np.bincount(dense * num_cells + cell, minlength=num_masks * num_cells)  # (M + 1) C pixel counts
        pair = np.flatnonzero(n_mc[num_cells:]) + num_cells  # sorted by mask, then cell; no mask pools nothing
        mask_of, cell_of = pair // num_cells, pair % num_cells
        num_blocks = -(-num_cells // _BLOCK)
        key = (cell_of // _BLOCK) * num_masks + mask_of  # (block, mask)
        order = np.argsort(key, kind="stable")  # within a (block, mask): cells in order
        self._cell = (cell_of[order] % _BLOCK).astype(np.int32)  # the cell within its block
        self._base = n_mc[pair[order]].astype(np.float64) ** 2 / pixels_in_cell[cell_of[order]]  # weight / inv_norm
        self._indptr = np.zeros(num_blocks * num_masks + 1, dtype=np.int32)
        np.cumsum(np.bincount(key, minlength=num_blocks * num_masks), out=self._indptr[1:])
        self._num_masks = num_masks
        self._sum = np.zeros((num_masks, dim), dtype=np.float32)  # (M + 1, D)

    def add(self, b: int, block: np.ndarray, inv_norm: np.ndarray) -> None:
        """Add block ``b``'s terms: ``block`` (B, D) float32 cells as read, ``inv_norm`` (B,) their 1 / |f_c|."""
        m = self._num_masks
        indptr = self._indptr[b * m : (b + 1) * m + 1]
        lo, hi = int(indptr[0]), int(indptr[-1])
        if hi == lo:
            return
        cell = self._cell[lo:hi]
        weight = (self._base[lo:hi] * inv_norm[cell]).astype(np.float32)
        _csr_matvecs(m, len(block), block.shape[1], indptr - lo, cell, weight, block.reshape(-1), self._sum.reshape(-1))

    def pooled(self, min_norm: float) -> np.ndarray:  # (M + 1, D) float32 unit rows (zero: no feature)
        _unit_rows_(self._sum, min_norm)
        return self._sum


def mask_pooled_features(
    fmap: np.ndarray,  # (Hf, Wf, D) feature map
    masks: np.ndarray,  # (Hm, Wm) int mask ids >= 0, 0 = no mask
    min_norm: float = 1e-6,
) -> tuple[np.ndarray, np.ndarray]:  # (M + 1, D) float32 unit rows indexed by mask id, (M + 1,) bool
    """Mean unit feature of each 2D mask, over the feature cells it covers, weighted towards pure cells.

    Cell c contributes to mask m with weight ``n_mc^2 / n_c`` (``n_mc`` pixels of m in c, ``n_c`` pixels of
    c): the pixel count times the share of the cell the mask holds, so a cell that straddles a border counts
    little for the mask that only grazes it. Mask pixel (i, j) lies in the feature cell of its centre, by the
    sampling rule of docs/scene_format.md. Row 0 (no mask) and masks without a feature are zero and marked False.

    Example:
        >>> fmap = np.array([[[1.0, 0.0], [0.0, 1.0]]])  # one row of two cells
        >>> masks = np.array([[1, 1, 1, 2]])  # mask 1 covers cell 0 and half of cell 1
        >>> pooled, has = mask_pooled_features(fmap, masks)
        >>> pooled.astype(float).round(3).tolist(), has.tolist()
        ([[0.0, 0.0], [0.97, 0.243], [0.0, 1.0]], [False, True, True])
    """
    fmap = np.asarray(fmap)
    cells, inv_norm = _cells_and_inverse_norms(fmap, min_norm)
    dense, mask_values = _dense_mask_ids(masks)
    pooled = _pool_cells(cells, inv_norm, dense, len(mask_values), mask_pixel_cells(masks.shape, fmap.shape[:2]))
    has = np.linalg.norm(pooled, axis=1) > 0.5  # unit rows, or zero
    top = int(mask_values[-1])
    by_id = np.zeros((top + 1, fmap.shape[2]), dtype=np.float32)
    by_id[mask_values] = pooled
    has_by_id = np.zeros(top + 1, dtype=bool)
    has_by_id[mask_values] = has
    return by_id, has_by_id


def _dense_mask_ids(masks: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # (Hm Wm,) int64 in 0..M, (M + 1,) ids
    """Mask ids renumbered 0..M in id order (0, "no mask", stays 0), and the id of each new number.

    Ids are sparse in general (a 16-bit PNG may use 7 and 60000): tables indexed by the dense number stay
    (M + 1) rows long. A look-up table over 0..max id (at most 65536 entries for a PNG) avoids a sort.
    """
    ids = masks.reshape(-1).astype(np.int64)
    present = np.bincount(ids, minlength=1) > 0  # (max id + 1,)
    present[0] = True
    number = np.cumsum(present) - 1  # id -> dense number
    return number[ids], np.flatnonzero(present)


def mask_pixel_cells(
    mask_hw: tuple[int, int], feature_hw: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:  # (Hm Wm,) int64 flat feature cell of each mask pixel, (C,) pixels per cell
    """The feature cell every mask pixel lies in (by the sampling rule of docs/scene_format.md), and how many
    mask pixels each cell holds.

    Example:
        >>> cell, count = mask_pixel_cells((2, 4), (1, 2))
        >>> cell.tolist(), count.tolist()
        ([0, 0, 1, 1, 0, 0, 1, 1], [4, 4])
    """
    hf, wf = feature_hw
    hm, wm = mask_hw
    # The cell rows and columns of the pixel rows and columns (separable).
    row_cell = feature_cells(np.arange(hm), np.zeros(hm, np.int64), (hm, wm), (hf, wf)) // wf  # (Hm,)
    col_cell = feature_cells(np.zeros(wm, np.int64), np.arange(wm), (hm, wm), (hf, wf))  # (Wm,)
    cell = (row_cell[:, None] * wf + col_cell[None, :]).reshape(-1)  # (Hm Wm,)
    return cell, np.bincount(cell, minlength=hf * wf)


def _pool_cells(
    cells: np.ndarray,  # (C, D) float32 cells as read
    inv_norm: np.ndarray,  # (C,) 1 / |f_c|, 0 where no feature
    dense: np.ndarray,  # (Hm Wm,) int64 dense mask number of every mask pixel
    num_masks: int,  # M + 1
    pixel_cells: tuple[np.ndarray, np.ndarray],  # mask_pixel_cells(mask_hw, feature_hw)
    min_norm: float = 1e-6,
) -> np.ndarray:  # (M + 1, D) float32: unit rows, zero for "no mask" (row 0) and masks without a feature
    """Weighted mean of the unit cells under each mask (weights of :func:`mask_pooled_features`).

    One sparse (M + 1) x C product with one term per (mask, cell) pair that shares a pixel, about one per cell,
    each weight times the cell's ``1 / |f_c|``. Torch's CPU ``index_add_`` of the same terms adds them one row at a
    time and was most of the stage at ScanNet size (docs/benchmarks.md, "Speed at ScanNet size").
    """
    cell, pixels_in_cell = pixel_cells  # (Hm Wm,), (C,)
    num_cells = len(pixels_in_cell)
    n_mc = np.bincount(dense * num_cells + cell, minlength=num_masks * num_cells)  # (M + 1) C pixel counts
    pair = np.flatnonzero(n_mc[num_cells:]) + num_cells  # sorted by mask, then cell; no mask pools nothing
    mask_of, cell_of = pair // num_cells, pair % num_cells
    weight = (n_mc[pair].astype(np.float64) ** 2 / pixels_in_cell[cell_of] * inv_norm[cell_of]).astype(np.float32)
    indptr = np.searchsorted(mask_of, np.arange(num_masks + 1))  # (M + 1 + 1,) rows of the sorted pairs
    pooling = sparse.csr_matrix((weight, cell_of, indptr), shape=(num_masks, num_cells))
    pooled = np.ascontiguousarray(pooling @ cells, dtype=np.float32)  # (M + 1, D)
    _unit_rows_(pooled, min_norm)
    return pooled


def _unit_rows_(rows: np.ndarray, min_norm: float) -> np.ndarray:  # (U,) bool: rows that are a feature
    """Scale each row of a (U, D) float32 array to unit length in place; zero the rows that are no feature."""
    norm = np.sqrt(np.einsum("ud,ud->u", rows, rows))  # (U,) no (U, D) temporary
    valid = np.isfinite(norm) & (norm > min_norm)
    scale = np.zeros(len(norm), dtype=np.float32)
    scale[valid] = 1.0 / norm[valid]
    rows *= scale[:, None]
    if not valid.all():
        rows[~valid] = 0.0  # NaN * 0 is NaN: clear invalid rows explicitly
    return valid


class _ColorSum:
    """Running per-primitive RGB sum and count over the key frames that have colour."""

    def __init__(self, num_points: int, image_hw: tuple[int, int]) -> None:
        self.total = np.zeros((num_points, 3), dtype=np.float32)  # (N, 3)
        self.count = np.zeros(num_points, dtype=np.int32)  # (N,)
        self._image_hw = image_hw

    def add(self, frame: Frame, image: np.ndarray, point_index: np.ndarray, row: np.ndarray, col: np.ndarray) -> None:
        """Add one frame's colours: ``image`` (H, W, 3) uint8 RGB at the camera size, as ``Bundle.read_color``."""
        expected = (*self._image_hw, 3)
        if image.shape != expected:
            raise ShapeError(f"colour of frame {frame.id}: expected {expected}, got {image.shape}")
        self.total[point_index] += image[row, col].astype(np.float32) / 255.0
        self.count[point_index] += 1

    def mean(self) -> np.ndarray:  # (N, 3) float32 in [0, 1]; 0 where no colour frame sees the primitive
        return self.total / np.maximum(self.count, 1)[:, None].astype(np.float32)
