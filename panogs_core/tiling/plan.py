"""The tiling plan: XY tiles of a scene's primitives, each a bounded core with a halo, and the frames that see it.

docs/method.md §16. The planner reads the geometry's vertices (the primitives of the geometry path, 1:1), the
poses, the intrinsics and the depth images, never a feature map or a mask. It works on a grid of XY cells
``cell_m`` wide (the halo a whole number of cells): every vertical column of cells, all floors of it, goes to one
tile, and a tile's core is a rectangle of cells, so the cores partition the primitives exactly and a halo (the
core's rectangle grown by ``halo_m``) is a union of cells too.

Cost model: a tile costs ``fixed_bytes + bytes_per_primitive_frame x primitives x frames`` (primitives of core and
halo; frames that see at least ``min_frame_points`` of them), the cost driver measured on a ScanNet-size room
(docs/benchmarks.md, "Tiling"). The k-d split halves the most expensive region along its longer side, at the
cell boundary that balances the core primitives, until every tile fits ``memory_target_bytes``. ``auto`` leaves a
scene whole when its worst case fits ``whole_limit_bytes`` (by default half of this machine's memory, and never
less than the tile target): a room that an untiled run handles keeps the untiled run's results, and only a scene
that would not fit is tiled.

Memory: the points (N x 3 float32), one frame's projection and, per frame, the primitive count of each cell it
sees (a few hundred cells): nothing N x V, no feature map.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import ConfigError, InputError
from panogs_core.io.bundle import Bundle
from panogs_core.progress import ProgressFn, report
from panogs_core.stages.visibility import VisibilityConfig, frame_visibility
from panogs_core.tiling.choice import TILES_AUTO, TILES_OFF
from panogs_core.types import Frame


@dataclass(frozen=True, kw_only=True)
class TilingConfig:
    """Settings of the planner.

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    # m, halo around a core. Ours: the design started from 1 m; a primitive no key frame saw takes its class from
    # the seen primitives of its segment or nearest along the graph, and within 1 m of a seam those lay beyond a
    # 1 m halo (docs/method.md §16.3). 2 m: the large room's 2 x 2 tiles within the design's targets, 1.5 m not.
    halo_m: float = 2.0
    cell_m: float = 0.25  # m, planner grid; halo_m must be a whole number of cells (ours: 8 cells per halo)
    # bytes, what one tile may use; ours: the per-tile target of a building job (docs/method.md §16)
    memory_target_bytes: float = 3.0e9
    # bytes, the most an untiled run may be estimated at for ``auto`` to leave the scene whole; None: half of this
    # machine's physical memory (ours: tiling changes results a little, docs/benchmarks.md "Tiling", so a scene is
    # tiled only where one process could not hold it), at least memory_target_bytes
    whole_limit_bytes: float | None = None
    fixed_bytes: float = 0.8e9  # bytes, a run's fixed cost at ScanNet size (docs/benchmarks.md, "Tiling")
    bytes_per_primitive_frame: float = 74.0  # bytes (docs/benchmarks.md, "Tiling")
    # A frame joins a tile when it sees this many of the tile's primitives (ours: a frame that shows 50 points of
    # a tile, a few hundred pixels at 2 cm spacing, adds nothing the other frames do not).
    min_frame_points: int = 50
    # Points projected per frame by the planner: every k-th vertex, k = ceil(N / this), counts scaled by k (ours:
    # bounds the planner's pass over the frames to ~200k projections each, about the visibility of one room).
    sample_points: int = 200_000
    visibility: VisibilityConfig = field(default_factory=VisibilityConfig)

    def __post_init__(self) -> None:
        for name in ("halo_m", "cell_m", "memory_target_bytes", "bytes_per_primitive_frame"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"tiling.{name}: expected a finite value > 0, got {value!r}")
        limit = self.whole_limit_bytes
        if limit is not None and not (math.isfinite(limit) and limit > 0):
            raise ConfigError(f"tiling.whole_limit_bytes: expected a finite value > 0 or null, got {limit!r}")
        if not (math.isfinite(self.fixed_bytes) and 0 <= self.fixed_bytes < self.memory_target_bytes):
            raise ConfigError(
                f"tiling.fixed_bytes: expected 0 <= fixed_bytes < memory_target_bytes ({self.memory_target_bytes}), "
                f"got {self.fixed_bytes!r}"
            )
        cells = self.halo_m / self.cell_m
        if abs(cells - round(cells)) > 1e-6:
            raise ConfigError(f"tiling.halo_m: expected a whole number of cells of {self.cell_m} m, got {self.halo_m}")
        for name in ("min_frame_points", "sample_points"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ConfigError(f"tiling.{name}: expected an integer >= 1, got {value!r}")

    @property
    def halo_cells(self) -> int:
        return round(self.halo_m / self.cell_m)

    def whole_limit(self) -> float:
        """Bytes up to which ``auto`` runs a scene untiled: ``whole_limit_bytes``, or half the machine's memory."""
        limit = self.whole_limit_bytes if self.whole_limit_bytes is not None else physical_memory_bytes() / 2
        return max(limit, self.memory_target_bytes)


def physical_memory_bytes() -> float:
    """This machine's physical memory (``sysconf``); 0 where the system does not say."""
    try:
        return float(os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (AttributeError, ValueError, OSError):
        return 0.0


@dataclass(frozen=True)
class TileSpec:
    """One tile: its core and halo as rectangles of the planner's grid, and what it holds."""

    index: int
    core_cells: tuple[int, int, int, int]  # (i0, i1, j0, j1): cells i0 <= i < i1 along x, j0 <= j < j1 along y
    core_box: tuple[float, float, float, float]  # (x0, x1, y0, y1) metres, the core rectangle
    halo_box: tuple[float, float, float, float]  # the core rectangle grown by the halo
    core_points: int
    halo_points: int
    frame_ids: tuple[str, ...]
    estimated_bytes: float

    @property
    def name(self) -> str:
        """``tile-<index>-<digest>``: the digest of its rectangles and frames, so a changed plan never reuses a
        tile folder's checkpoints made for another tile."""
        text = json.dumps([self.core_cells, self.halo_box, list(self.frame_ids)])
        return f"tile-{self.index:03d}-{hashlib.sha256(text.encode()).hexdigest()[:10]}"

    def to_json(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "name": self.name,
            "core_box": [round(v, 4) for v in self.core_box],
            "halo_box": [round(v, 4) for v in self.halo_box],
            "core_primitives": self.core_points,
            "halo_primitives": self.halo_points,
            "frames": len(self.frame_ids),
            "estimated_mb": round(self.estimated_bytes / 2**20, 1),
        }


@dataclass(frozen=True)
class TilePlan:
    """The tiles of a scene (one tile covering everything when the scene is not tiled)."""

    origin: tuple[float, float]  # (x, y) metres of cell (0, 0)'s lower corner
    cell_m: float
    halo_cells: int
    grid: tuple[int, int]  # cells along x, y
    tiles: tuple[TileSpec, ...]
    tiled: bool  # False: run untiled (the scene fits, or tiling was off)
    reason: str  # why it is (not) tiled, for report.json
    whole_estimated_bytes: float

    def cells_of(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:  # 2 x (N,) int64
        """Grid cell (i, j) of each point, clipped into the grid."""
        i = np.floor((points[:, 0].astype(np.float64) - self.origin[0]) / self.cell_m).astype(np.int64)
        j = np.floor((points[:, 1].astype(np.float64) - self.origin[1]) / self.cell_m).astype(np.int64)
        return np.clip(i, 0, self.grid[0] - 1), np.clip(j, 0, self.grid[1] - 1)

    def core_of(self, points: np.ndarray) -> np.ndarray:  # (N,) int64 tile index whose core holds each point
        """The tile whose core holds each point (every point has exactly one)."""
        i, j = self.cells_of(points)
        owner = np.full(self.grid, -1, np.int64)
        for tile in self.tiles:
            i0, i1, j0, j1 = tile.core_cells
            owner[i0:i1, j0:j1] = tile.index
        return owner[i, j]

    def members(self, tile: TileSpec, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Indices (ascending) of the points of ``tile`` (core and halo), and a mask of which are its core."""
        i, j = self.cells_of(points)
        i0, i1, j0, j1 = tile.core_cells
        h = self.halo_cells
        region = (i >= i0 - h) & (i < i1 + h) & (j >= j0 - h) & (j < j1 + h)
        index = np.flatnonzero(region)
        core = (i[index] >= i0) & (i[index] < i1) & (j[index] >= j0) & (j[index] < j1)
        return index, core

    def to_json(self) -> dict[str, Any]:
        return {
            "tiled": self.tiled,
            "reason": self.reason,
            "cell_m": self.cell_m,
            "halo_m": self.halo_cells * self.cell_m,
            "whole_estimated_mb": round(self.whole_estimated_bytes / 2**20, 1),
            "tiles": [t.to_json() for t in self.tiles],
        }

    def save(self, path: Path) -> None:
        """The whole plan as JSON (``tiles/plan.json``): what a worker needs to rebuild any tile's bundle
        (:func:`panogs_core.tiling.view.tile_bundle`) from the scene's bundle, without planning again."""
        doc = {
            "origin": list(self.origin), "cell_m": self.cell_m, "halo_cells": self.halo_cells, "grid": list(self.grid),
            "tiled": self.tiled, "reason": self.reason, "whole_estimated_bytes": self.whole_estimated_bytes,
            "tiles": [dataclasses.asdict(t) for t in self.tiles],
        }  # fmt: skip
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps(doc, indent=1))
        tmp.replace(path)

    @classmethod
    def load(cls, path: Path) -> TilePlan:
        """Read what :meth:`save` wrote."""
        doc = json.loads(path.read_text())
        tiles = tuple(
            TileSpec(
                index=int(t["index"]), core_cells=tuple(int(v) for v in t["core_cells"]),  # type: ignore[arg-type]
                core_box=tuple(float(v) for v in t["core_box"]),  # type: ignore[arg-type]
                halo_box=tuple(float(v) for v in t["halo_box"]),  # type: ignore[arg-type]
                core_points=int(t["core_points"]), halo_points=int(t["halo_points"]),
                frame_ids=tuple(str(f) for f in t["frame_ids"]), estimated_bytes=float(t["estimated_bytes"]),
            )
            for t in doc["tiles"]
        )  # fmt: skip
        return cls(
            origin=(float(doc["origin"][0]), float(doc["origin"][1])), cell_m=float(doc["cell_m"]),
            halo_cells=int(doc["halo_cells"]), grid=(int(doc["grid"][0]), int(doc["grid"][1])), tiles=tiles,
            tiled=bool(doc["tiled"]), reason=str(doc["reason"]),
            whole_estimated_bytes=float(doc["whole_estimated_bytes"]),
        )  # fmt: skip


def key_frames(bundle: Bundle) -> tuple[Frame, ...]:
    """The frames the visibility stage projects into: those with features or masks, manifest order."""
    return tuple(f for f in bundle.frames if f.features is not None or f.masks is not None)


class _CellCounts:
    """Primitives per grid cell (with a summed-area table), and per frame the seen primitives of each cell."""

    def __init__(self, counts: np.ndarray, frame_cells: list[np.ndarray], frame_counts: list[np.ndarray]) -> None:
        self.counts = counts  # (nx, ny) int64
        self.table = np.zeros((counts.shape[0] + 1, counts.shape[1] + 1), np.int64)
        self.table[1:, 1:] = counts.cumsum(0).cumsum(1)
        sizes = [len(c) for c in frame_cells]
        self.frame_of = np.repeat(np.arange(len(frame_cells)), sizes)  # (S,) sparse entries
        flat = np.concatenate(frame_cells) if frame_cells else np.zeros(0, np.int64)
        self.cell_i, self.cell_j = np.divmod(flat, counts.shape[1])
        self.seen = np.concatenate(frame_counts) if frame_counts else np.zeros(0, np.float64)
        self.num_frames = len(frame_cells)

    def points_in(self, i0: int, i1: int, j0: int, j1: int) -> int:
        i0, j0 = max(i0, 0), max(j0, 0)
        i1, j1 = min(i1, self.counts.shape[0]), min(j1, self.counts.shape[1])
        if i0 >= i1 or j0 >= j1:
            return 0
        t = self.table
        return int(t[i1, j1] - t[i0, j1] - t[i1, j0] + t[i0, j0])

    def frames_seeing(self, i0: int, i1: int, j0: int, j1: int, min_points: int) -> np.ndarray:  # frame indices
        inside = (self.cell_i >= i0) & (self.cell_i < i1) & (self.cell_j >= j0) & (self.cell_j < j1)
        per_frame = np.bincount(self.frame_of[inside], weights=self.seen[inside], minlength=self.num_frames)
        return np.flatnonzero(per_frame >= min_points)


def plan_tiles(
    bundle: Bundle,
    cfg: TilingConfig,
    tiles: str | tuple[int, int] = TILES_AUTO,
    *,
    points: np.ndarray | None = None,
    on_progress: ProgressFn | None = None,
) -> TilePlan:
    """Plan the tiles of a scene.

    Args:
        bundle: The opened bundle; its ``geometry.ply`` vertices are the primitives (the geometry path).
        cfg: Planner settings.
        tiles: ``auto`` (untiled when the scene fits ``cfg.whole_limit()``; else split until every tile fits
            ``cfg.memory_target_bytes``),
            ``off`` (one untiled tile), or ``(nx, ny)`` (forced: nx columns of equal primitive count, each cut into
            ny tiles of equal count).
        points: The primitives' centres when already read (else read from the geometry).
        on_progress: ``(done, total)`` per frame of the planner's pass.

    Raises:
        InputError: tiling was asked for (``auto`` on a scene over the budget, or ``(nx, ny)``) but the bundle has
            no geometry: the TSDF path's primitives do not exist before stage 1 runs.
    """
    if points is None:
        geometry = bundle.read_geometry()
        if geometry is None:
            if tiles == TILES_AUTO or tiles == TILES_OFF:
                return _untiled(bundle, 0, "no geometry.ply: the primitives come from the TSDF, planned whole")
            raise InputError("--tiles NxM needs geometry.ply: the TSDF path's primitives exist only after stage 1")
        points = geometry.points
    points = np.asarray(points, np.float32)
    frames = key_frames(bundle)
    if tiles == TILES_OFF:
        return _untiled(bundle, points.shape[0], "tiling off")
    # Every key frame sees the whole scene at worst: a scene that fits so is planned without a pass over its frames.
    whole_bytes = cfg.fixed_bytes + cfg.bytes_per_primitive_frame * points.shape[0] * len(frames)
    if tiles == TILES_AUTO and whole_bytes <= cfg.whole_limit():
        reason = f"fits whole (estimated {whole_bytes / 1e9:.1f} GB, limit {cfg.whole_limit() / 1e9:.1f} GB)"
        return _untiled(bundle, points.shape[0], reason, whole_bytes)
    lo = points[:, :2].min(axis=0).astype(np.float64)
    extent = np.floor((points[:, :2].max(axis=0) - lo) / cfg.cell_m).astype(np.int64) + 1
    grid = (int(extent[0]), int(extent[1]))
    counts = _cell_counts(bundle, points, frames, lo, grid, cfg, on_progress)
    h = cfg.halo_cells

    def estimate(i0: int, i1: int, j0: int, j1: int) -> tuple[float, np.ndarray]:
        box = (i0 - h, i1 + h, j0 - h, j1 + h)
        seeing = counts.frames_seeing(*box, cfg.min_frame_points)
        return cfg.fixed_bytes + cfg.bytes_per_primitive_frame * counts.points_in(*box) * len(seeing), seeing

    whole = (0, grid[0], 0, grid[1])
    if tiles == TILES_AUTO:
        regions = _kd_split(whole, counts, lambda r: estimate(*r)[0] > cfg.memory_target_bytes)
        reason = "auto: split until every tile fits the memory target"
    else:
        assert not isinstance(tiles, str)
        regions = _grid_split(whole, counts, tiles)
        reason = f"forced {tiles[0]}x{tiles[1]}"
    specs: list[TileSpec] = []
    for rect in regions:
        core = counts.points_in(*rect)
        if core == 0:
            continue  # a rectangle with no primitive: nothing to run
        bytes_, seeing = estimate(*rect)
        i0, i1, j0, j1 = rect
        specs.append(
            TileSpec(
                index=len(specs),
                core_cells=rect,
                core_box=_box(lo, cfg.cell_m, rect),
                halo_box=_box(lo, cfg.cell_m, (i0 - h, i1 + h, j0 - h, j1 + h)),
                core_points=core,
                halo_points=counts.points_in(i0 - h, i1 + h, j0 - h, j1 + h) - core,
                frame_ids=tuple(frames[k].id for k in seeing),
                estimated_bytes=bytes_,
            )
        )
    return TilePlan(
        origin=(float(lo[0]), float(lo[1])),
        cell_m=cfg.cell_m,
        halo_cells=h,
        grid=grid,
        tiles=tuple(specs),
        tiled=len(specs) > 1,
        reason=reason if len(specs) > 1 else f"{reason}: one tile",
        whole_estimated_bytes=whole_bytes,
    )


def _untiled(bundle: Bundle, num_points: int, reason: str, whole_bytes: float = 0.0) -> TilePlan:
    frames = tuple(f.id for f in key_frames(bundle))
    tile = TileSpec(0, (0, 1, 0, 1), (-math.inf, math.inf, -math.inf, math.inf),
                    (-math.inf, math.inf, -math.inf, math.inf), num_points, 0, frames, whole_bytes)  # fmt: skip
    return TilePlan((0.0, 0.0), 1.0, 0, (1, 1), (tile,), False, reason, whole_bytes)


def _box(lo: np.ndarray, cell: float, rect: tuple[int, int, int, int]) -> tuple[float, float, float, float]:
    i0, i1, j0, j1 = rect
    return (float(lo[0] + i0 * cell), float(lo[0] + i1 * cell), float(lo[1] + j0 * cell), float(lo[1] + j1 * cell))


def _cell_counts(
    bundle: Bundle,
    points: np.ndarray,
    frames: Sequence[Frame],
    lo: np.ndarray,
    grid: tuple[int, int],
    cfg: TilingConfig,
    on_progress: ProgressFn | None,
) -> _CellCounts:
    """Primitives per cell, and for every key frame the (sampled, rescaled) count of seen primitives per cell."""
    i = np.clip(np.floor((points[:, 0] - lo[0]) / cfg.cell_m).astype(np.int64), 0, grid[0] - 1)
    j = np.clip(np.floor((points[:, 1] - lo[1]) / cfg.cell_m).astype(np.int64), 0, grid[1] - 1)
    flat = i * grid[1] + j
    counts = np.bincount(flat, minlength=grid[0] * grid[1]).reshape(grid)
    stride = max(1, math.ceil(points.shape[0] / cfg.sample_points))
    sample = np.ascontiguousarray(points[::stride])
    sample_cell = flat[::stride]
    frame_cells, frame_counts = [], []
    for done, frame in enumerate(frames, start=1):
        T_cam_world = _world_to_camera(frame.T_world_cam)
        if T_cam_world is None:
            seen = np.zeros(0, np.int64)
        else:
            seen = frame_visibility(sample, T_cam_world, bundle.camera, bundle.read_depth(frame), cfg.visibility)[0]
        cells, per_cell = np.unique(sample_cell[seen], return_counts=True)
        frame_cells.append(cells)
        frame_counts.append(per_cell.astype(np.float64) * stride)
        report(on_progress, done, len(frames))
    return _CellCounts(counts, frame_cells, frame_counts)


def _world_to_camera(T_world_cam: np.ndarray) -> np.ndarray | None:  # (4, 4) float64, or None
    """The inverse pose, or None where the pose is unusable (the visibility stage's rule: such a frame sees
    nothing)."""
    pose = np.asarray(T_world_cam, np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        return None
    try:
        inverse = np.linalg.inv(pose)
    except np.linalg.LinAlgError:
        return None
    return inverse if np.all(np.isfinite(inverse)) else None


Rect = tuple[int, int, int, int]


def _split_at(rect: Rect, counts: _CellCounts, axis: int, share: float) -> tuple[Rect, Rect] | None:
    """Cut ``rect`` across ``axis`` at the cell boundary nearest ``share`` of its primitives; None if it is one
    cell thick along that axis."""
    i0, i1, j0, j1 = rect
    a0, a1 = (i0, i1) if axis == 0 else (j0, j1)
    if a1 - a0 < 2:
        return None
    block = counts.counts[i0:i1, j0:j1]
    marginal = block.sum(axis=1 - axis).cumsum()  # primitives up to and including each slab
    total = marginal[-1]
    cut = int(np.argmin(np.abs(marginal[:-1] - share * total))) + 1 + a0  # in (a0, a1)
    if axis == 0:
        return (i0, cut, j0, j1), (cut, i1, j0, j1)
    return (i0, i1, j0, cut), (i0, i1, cut, j1)


def _kd_split(whole: Rect, counts: _CellCounts, too_big: Any) -> list[Rect]:
    """Cut every region that is too big across its longer side into the fewest parts of equal primitive count that
    each fit (up to ``_MAX_PARTS``; else in two, and the halves go on), until none is too big; regions in a
    deterministic order (depth first, lower part first).

    The fewest parts, not halves: a region a little over the budget halved twice makes four tiles at a quarter of
    it, whose halos (a fixed band) then weigh more than their cores; fewer, larger cores leave fewer seams
    (docs/method.md §16.1).
    """
    out: list[Rect] = []
    stack = [whole]
    while stack:
        rect = stack.pop()
        parts = None
        if too_big(rect):
            longer = 0 if rect[1] - rect[0] >= rect[3] - rect[2] else 1
            parts = _fewest_parts(rect, counts, longer, too_big) or _fewest_parts(rect, counts, 1 - longer, too_big)
        if parts is None:
            out.append(rect)
        else:
            stack.extend(reversed(parts))
    return out


_MAX_PARTS = 8  # parts of one cut tried before a region is halved and its halves cut again


def _fewest_parts(rect: Rect, counts: _CellCounts, axis: int, too_big: Any) -> list[Rect] | None:
    """The fewest parts (2 to _MAX_PARTS) of equal primitive count across ``axis`` that all fit; the two halves
    when none does; None when ``rect`` is one cell thick along ``axis``."""
    halves = None
    for k in range(2, _MAX_PARTS + 1):
        parts = _equal_parts(rect, counts, axis, k)
        if len(parts) < k:
            break  # too thin for k parts
        if k == 2:
            halves = parts
        if not any(too_big(p) for p in parts):
            return parts
    return halves


def _grid_split(whole: Rect, counts: _CellCounts, shape: tuple[int, int]) -> list[Rect]:
    """``nx`` columns of equal primitive count, each cut into ``ny`` tiles of equal count."""
    columns = _equal_parts(whole, counts, 0, shape[0])
    return [tile for column in columns for tile in _equal_parts(column, counts, 1, shape[1])]


def _equal_parts(rect: Rect, counts: _CellCounts, axis: int, parts: int) -> list[Rect]:
    out: list[Rect] = []
    rest = rect
    for k in range(parts, 1, -1):
        halves = _split_at(rest, counts, axis, 1.0 / k)
        if halves is None:
            break
        out.append(halves[0])
        rest = halves[1]
    out.append(rest)
    return out
