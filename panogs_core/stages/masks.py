"""The mask look-ups: which 2D mask id every key frame sees under every primitive it sees.

Runs once, after the visibility of stage 2 and before the graph cut of stage 5 (which cuts segments the masks
keep dividing); the clustering of stage 7 measures its affinities on the same observations. A stage of its own
so that neither of them owns the look-up and its checkpoint depends only on the visibility and the two settings
below.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn, report

if TYPE_CHECKING:
    from panogs_core.io.bundle import Bundle
    from panogs_core.stages.visibility import Visibility


@dataclass(frozen=True, kw_only=True)
class MaskLookupConfig:
    """Settings of the mask look-ups (the YAML keys ``affinity.mask_depth_mad`` / ``affinity.mask_depth_floor``).

    Attributes:
        depth_mad: A seen primitive reads its mask id only if its relative depth residual is within this many
            robust standard deviations (1.4826 MAD) of the frame's median residual; 0 turns the filter off.
        depth_floor: The smallest tolerance of that test, relative depth.
    """

    depth_mad: float = 0.0
    depth_floor: float = 0.01

    def __post_init__(self) -> None:
        if not math.isfinite(self.depth_mad) or self.depth_mad < 0:
            raise ConfigError(f"affinity.mask_depth_mad: expected a number >= 0, found {self.depth_mad}")
        if not math.isfinite(self.depth_floor) or self.depth_floor <= 0:
            raise ConfigError(f"affinity.mask_depth_floor: expected a number > 0, found {self.depth_floor}")


@dataclass(frozen=True)
class MaskObservations:
    """Per mask frame, the primitives seen AND inside a mask, with their mask id (docs/method.md §5.1, label > 0).

    Frame v holds ``point_index[offsets[v]:offsets[v + 1]]`` and ``label[offsets[v]:offsets[v + 1]]``.
    """

    offsets: np.ndarray  # (V + 1,) int64
    point_index: np.ndarray  # (T,) int32
    label: np.ndarray  # (T,) int32, > 0, ids meaningful only within one frame

    def __post_init__(self) -> None:
        offsets, index, label = self.offsets, self.point_index, self.label
        if offsets.ndim != 1 or offsets.size < 1 or index.ndim != 1 or label.shape != index.shape:
            raise ShapeError(
                f"MaskObservations: expected offsets (V + 1,), point_index (T,), label (T,); found "
                f"{offsets.shape}, {index.shape}, {label.shape}"
            )
        if offsets[0] != 0 or offsets[-1] != index.size or np.any(np.diff(offsets) < 0):
            raise ShapeError(f"MaskObservations: offsets must rise from 0 to T = {index.size}")

    @property
    def num_frames(self) -> int:
        """V, the number of mask frames."""
        return int(self.offsets.size - 1)

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path``."""
        save_npz(path, offsets=self.offsets, point_index=self.point_index, label=self.label)

    @classmethod
    def load(cls, path: str | Path) -> MaskObservations:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as data:
            return cls(
                offsets=data["offsets"].astype(np.int64),
                point_index=data["point_index"].astype(np.int32),
                label=data["label"].astype(np.int32),
            )


def observe_masks(
    bundle: Bundle,
    visibility: Visibility,
    cfg: MaskLookupConfig | None = None,
    *,
    on_progress: ProgressFn | None = None,
) -> MaskObservations:
    """Look up the mask id under every primitive that a mask frame sees; keep those inside a mask.

    Streams the frames of ``visibility`` that have a mask, one at a time (docs/method.md §5.1). The mask may have
    any size: camera pixel (u, v) reads mask cell ``(floor((v + 0.5) Hm / H), floor((u + 0.5) Wm / W))``.

    Args:
        bundle: The bundle; ``read_masks(frame)`` gives an ``(Hm, Wm)`` int32 id map, 0 = no mask.
        visibility: Stage 2 output; its ``frame_ids`` name scene frames.
        cfg: The depth filter (used when ``visibility`` has depth residuals); default
            :class:`MaskLookupConfig` (off).
        on_progress: Called ``(done, total)`` after each mask frame.

    Returns:
        One entry per mask frame of ``visibility`` (frames without a mask are left out), in its order.

    Raises:
        InputError: if ``visibility`` names a frame the scene does not have.
        ShapeError: if a mask is not a 2D array.
    """
    cfg = cfg if cfg is not None else MaskLookupConfig()
    by_id = {frame.id: frame for frame in bundle.frames}
    missing = [fid for fid in visibility.frame_ids if fid not in by_id]
    if missing:
        raise InputError(f"observe_masks: visibility names frame(s) {missing[:5]} that the scene does not have")
    views = [v for v, fid in enumerate(visibility.frame_ids) if by_id[fid].masks is not None]
    height, width = bundle.camera.height, bundle.camera.width
    index_parts: list[np.ndarray] = []
    label_parts: list[np.ndarray] = []
    for done, v in enumerate(views, start=1):
        frame = by_id[visibility.frame_ids[v]]
        point_index, row, col = visibility.frame(v)
        label = _mask_lookup(np.asarray(bundle.read_masks(frame)), row, col, height, width, frame.id)
        inside = (label > 0) & _depth_consistent(visibility, v, cfg)
        index_parts.append(np.asarray(point_index, dtype=np.int32)[inside])
        label_parts.append(label[inside])
        report(on_progress, done, len(views))
    sizes = np.array([part.size for part in index_parts], dtype=np.int64)
    empty = np.zeros(0, dtype=np.int32)
    return MaskObservations(
        offsets=np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64),
        point_index=np.concatenate(index_parts) if index_parts else empty,
        label=np.concatenate(label_parts) if label_parts else empty,
    )


def _depth_consistent(visibility: Visibility, v: int, cfg: MaskLookupConfig) -> np.ndarray | bool:  # (T_v,) bool
    """Seen pairs of frame ``v`` whose depth residual is within the frame's own noise (``depth_mad``)."""
    if visibility.depth_residual is None or cfg.depth_mad <= 0:
        return True
    lo, hi = int(visibility.offsets[v]), int(visibility.offsets[v + 1])
    residual = visibility.depth_residual[lo:hi].astype(np.float32)
    if residual.size == 0:
        return True
    centre = float(np.median(residual))
    spread = 1.4826 * float(np.median(np.abs(residual - centre)))  # robust standard deviation
    tolerance = max(cfg.depth_mad * spread, cfg.depth_floor)
    return np.abs(residual - centre) <= tolerance


def _mask_lookup(
    mask: np.ndarray,  # (Hm, Wm) int, 0 = no mask
    row: np.ndarray,  # (T_v,) int, camera pixel row
    col: np.ndarray,  # (T_v,) int, camera pixel column
    height: int,
    width: int,
    frame_id: str,
) -> np.ndarray:  # (T_v,) int32
    if mask.ndim != 2:
        raise ShapeError(f"observe_masks: frame {frame_id!r}: expected a (Hm, Wm) mask, found {mask.shape}")
    rows_m, cols_m = mask.shape
    # floor((v + 0.5) Hm / H) in exact integer arithmetic; the clip only guards pixels outside the image.
    r = (2 * np.asarray(row, dtype=np.int64) + 1) * rows_m // (2 * height)
    c = (2 * np.asarray(col, dtype=np.int64) + 1) * cols_m // (2 * width)
    np.clip(r, 0, rows_m - 1, out=r)
    np.clip(c, 0, cols_m - 1, out=c)
    return mask[r, c].astype(np.int32, copy=False)
