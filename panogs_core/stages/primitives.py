"""Stage 1: the scene's 3D primitives (Gaussian centres, colours, normals, scales, opacities).

docs/method.md §2 (``run_recon.py`` with ``fix_ply``): one Gaussian per vertex of the scene mesh, in
file order, never densified or pruned. Here:

* **geometry path** (the scene has ``geometry.ply``): its vertices, in file order, are the primitives, 1:1
  and without de-duplication (docs/method.md pitfall 1: predictions are compared with per-vertex ground truth by
  index); colours come from the file when it has them. Normals in the file are not used: the reference
  estimates them from the points (docs/method.md §4.1).
* **TSDF path** (no geometry): the depth frames are fused into a truncated signed distance volume (open3d
  ``t.geometry.VoxelBlockGrid``; the legacy ``ScalableTSDFVolume`` extracts nothing in open3d 0.20), its zero
  crossing is extracted as a coloured point cloud, voxel-downsampled to ``target_spacing`` and capped at
  ``max_primitives``. The reference never does this (it always starts from the ground-truth mesh); a service
  needs it for captures that come without a mesh.

In both paths the normals are open3d's ``estimate_normals`` (hybrid radius 0.1 m, 30 neighbours), NOT oriented
(docs/method.md §4.1, pitfall 10), made by :mod:`panogs_core.point_normals` without importing open3d, and the
Gaussians are initialised as in docs/method.md §2: isotropic log scale from the mean squared distance to the 3
nearest neighbours, opacity 0.5 (logit 0).

The photometric 3DGS refinement (L1 + D-SSIM against the colour frames; docs/method.md §2, §9) is the next
stage, :mod:`panogs_core.gaussians`, with the centres kept on the vertices by default (reference ``fix_ply``;
the reference's refinement nudges them mm to a few cm): downstream stages read the centres from here.
"""

from __future__ import annotations

import logging
import math
import sys
import types
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from panogs_core.errors import ConfigError, InputError, ShapeError
from panogs_core.io.bundle import Bundle
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn, report
from panogs_core.types import Frame

if TYPE_CHECKING:  # scipy loads with the stage's work, not with its settings (the API reads those)
    from scipy.spatial import cKDTree

log = logging.getLogger(__name__)

# ``import open3d`` also imports ``open3d.visualization.draw_plotly``, a browser viewer built on plotly and dash
# (which bring IPython, requests, werkzeug, pydantic): 0.5 s of the 0.8 s open3d import, and of a ScanNet-size
# ``panogs run`` (``python -X importtime``), for a viewer panogs never opens. :func:`_open3d` stands a stub in
# for that one module before open3d loads.
_PLOTLY_VIEWER = "open3d.visualization.draw_plotly"


def _open3d() -> Any:  # the open3d module
    """``import open3d``, without its plotly/dash viewer when open3d is not loaded yet (its functions then raise)."""
    if "open3d" not in sys.modules and _PLOTLY_VIEWER not in sys.modules:
        stub = types.ModuleType(_PLOTLY_VIEWER, "Stand-in for open3d's plotly viewer, not loaded by panogs.")

        def not_loaded(*args: object, **kwargs: object) -> None:
            raise RuntimeError(f"{_PLOTLY_VIEWER} was not loaded: panogs imports open3d without it")

        for name in ("get_plotly_fig", "draw_plotly", "draw_plotly_server"):
            setattr(stub, name, not_loaded)
        sys.modules[_PLOTLY_VIEWER] = stub
    import open3d

    return open3d


# Fallback for normals open3d cannot estimate (a point with fewer than 3 neighbours in the radius).
_DEFAULT_NORMAL = np.array([0.0, 0.0, 1.0], dtype=np.float32)
# At most this many frames are read to size the TSDF hash map before integration (the map grows if needed).
_SIZING_FRAMES = 16
# Blocks for open3d's initial hash map: the sizing estimate times this margin.
_BLOCK_MARGIN = 1.5
# Attempts at integration with a doubled block count, should the voxel block grid refuse to grow.
_TSDF_ATTEMPTS = 3


@dataclass(frozen=True, kw_only=True)
class PrimitivesConfig:
    """Settings of stage 1. Gaussian and normal defaults are the reference's; the TSDF ones are ours.

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    # --- Gaussian initialisation (docs/method.md §2, MonoGS ``fix_ply`` init, simple-knn ``distCUDA2``)
    point_size: float = 0.05  # factor on the mean squared 3-NN distance (m^2) before sqrt; docs/method.md §2
    scale_neighbors: int = 3  # neighbours (self excluded) whose squared distances are averaged; docs/method.md §2
    min_sq_distance: float = 1e-7  # m^2, floor on that mean (duplicate points); docs/method.md §2
    # --- normals (docs/method.md §4.1, pitfall 10): open3d hybrid search, not oriented
    normal_radius: float = 0.1  # m
    normal_max_nn: int = 30  # neighbours
    # --- which path
    use_geometry: bool = True  # geometry.ply vertices when present (docs/method.md §2, pitfall 1); False: TSDF
    # --- TSDF path (not in the reference; sized for ScanNet-like real captures)
    voxel_size: float = 0.02  # m, TSDF voxel edge (ScanNet vh_clean_2 meshes have ~2 cm vertex spacing)
    trunc_voxels: float = 4.0  # truncation distance in voxels (0.08 m at 2 cm: above real depth noise at 4 m)
    block_resolution: int = 16  # voxels per block edge of open3d's voxel block grid
    depth_min: float = 0.1  # m, nearer depth is dropped (sensor minimum range, invalid near readings)
    depth_max: float = 4.5  # m, farther depth is dropped (structured-light noise grows with depth^2)
    frame_stride: int = 1  # integrate every n-th frame of the manifest
    # Integration weight a voxel needs to be extracted. 2.0 dropped most surfaces of a sparse capture (tiny
    # synthetic scene, 12 frames: no ceiling, 29 % of the true surface > 5 cm from any primitive, mIoU 0.49);
    # 0.5 keeps every observed surface (0.4 % > 5 cm; mIoU 0.83, PRQ(S) 0.83 after ground-truth transfer).
    min_weight: float = 0.5
    # m, voxel-downsampling cell of the extracted cloud. DEPARTURE (TSDF spacing, docs/method.md §2): 4 cm, as
    # sparse as the ScanNet meshes the method's point-count constants were set on; at 2 cm slivers survive.
    target_spacing: float = 0.04
    # cap on N for the TSDF path (the geometry path is never capped: docs/method.md pitfall 1)
    max_primitives: int = 200_000
    spacing_growth: float = 1.2  # factor on the spacing per retry while the cloud is above max_primitives

    def __post_init__(self) -> None:
        positive = {
            "point_size": self.point_size,
            "min_sq_distance": self.min_sq_distance,
            "normal_radius": self.normal_radius,
            "voxel_size": self.voxel_size,
            "trunc_voxels": self.trunc_voxels,
            "depth_max": self.depth_max,
            "target_spacing": self.target_spacing,
        }
        for name, value in positive.items():
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"primitives.{name}: expected a finite value > 0, got {value!r}")
        at_least_one = {
            "scale_neighbors": self.scale_neighbors,
            "normal_max_nn": self.normal_max_nn,
            "block_resolution": self.block_resolution,
            "frame_stride": self.frame_stride,
            "max_primitives": self.max_primitives,
        }
        for name, count in at_least_one.items():
            if not (isinstance(count, int) and count >= 1):
                raise ConfigError(f"primitives.{name}: expected an integer >= 1, got {count!r}")
        if not (math.isfinite(self.depth_min) and 0 <= self.depth_min < self.depth_max):
            raise ConfigError(
                f"primitives.depth_min: expected 0 <= depth_min < depth_max ({self.depth_max}), got {self.depth_min!r}"
            )
        if not (math.isfinite(self.min_weight) and self.min_weight >= 0):
            raise ConfigError(f"primitives.min_weight: expected a finite value >= 0, got {self.min_weight!r}")
        if not (math.isfinite(self.spacing_growth) and self.spacing_growth > 1):
            raise ConfigError(f"primitives.spacing_growth: expected a value > 1, got {self.spacing_growth!r}")


@dataclass(frozen=True)
class Primitives:
    """The scene's primitives: 3D Gaussians of which downstream stages use the centres (and normals)."""

    points: np.ndarray  # (N, 3) float32, world, metres
    normals: np.ndarray  # (N, 3) float32, unit, NOT oriented (docs/method.md §4.1)
    colors: np.ndarray | None  # (N, 3) float32 in [0, 1]
    scales: np.ndarray  # (N, 3) float32, log scale (3DGS convention, isotropic, docs/method.md §2)
    opacities: np.ndarray  # (N,) float32, logit (3DGS convention; 0.0 = opacity 0.5)
    source: str  # "geometry" | "tsdf"

    def __post_init__(self) -> None:
        n = self.points.shape[0]
        expected: dict[str, tuple[int, ...]] = {
            "points": (n, 3),
            "normals": (n, 3),
            "scales": (n, 3),
            "opacities": (n,),
        }
        if self.colors is not None:
            expected["colors"] = (n, 3)
        for name, shape in expected.items():
            got = getattr(self, name).shape
            if got != shape:
                raise ShapeError(f"Primitives.{name}: expected shape {shape}, got {got}")
        if self.source not in ("geometry", "tsdf"):
            raise InputError(f"Primitives.source: expected 'geometry' or 'tsdf', got {self.source!r}")

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path`` (no pickles); ``colors`` is omitted when None."""
        arrays: dict[str, Any] = {
            "points": self.points,
            "normals": self.normals,
            "scales": self.scales,
            "opacities": self.opacities,
            "source": np.array(self.source),
        }
        if self.colors is not None:
            arrays["colors"] = self.colors
        save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Primitives:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as z:
            return cls(
                points=z["points"],
                normals=z["normals"],
                colors=z["colors"] if "colors" in z.files else None,
                scales=z["scales"],
                opacities=z["opacities"],
                source=str(z["source"]),
            )


def build_primitives(bundle: Bundle, cfg: PrimitivesConfig, *, on_progress: ProgressFn | None = None) -> Primitives:
    """Build the primitives of a scene: ``geometry.ply`` vertices, or a TSDF reconstruction of the depth.

    Args:
        bundle: The opened bundle.
        cfg: Stage settings.
        on_progress: ``(done, total)`` per integrated frame (once for the geometry path).

    Returns:
        The primitives. With geometry: N = number of vertices, in file order.

    Raises:
        InputError: if the geometry has no vertices, or the TSDF extracts no surface.
    """
    geometry = bundle.read_geometry() if (cfg.use_geometry and bundle.has_geometry) else None
    if geometry is not None:
        points = np.ascontiguousarray(geometry.points, dtype=np.float32)  # (N, 3)
        if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] == 0:
            raise InputError(f"geometry.ply: expected (N >= 1, 3) vertices, got shape {points.shape}")
        colors = None if geometry.colors is None else _clip_colors(geometry.colors)
        source = "geometry"
        report(on_progress, 1, 1)
    else:
        points, colors = _tsdf_points(bundle, cfg, on_progress)
        source = "tsdf"
    from scipy.spatial import cKDTree

    tree = cKDTree(np.asarray(points, dtype=np.float64))  # the normals' and the scales' neighbours
    normals = estimate_normals(points, cfg.normal_radius, cfg.normal_max_nn, tree)
    scales = gaussian_log_scales(points, cfg.scale_neighbors, cfg.min_sq_distance, cfg.point_size, tree)
    opacities = np.zeros(points.shape[0], dtype=np.float32)  # logit(0.5) = 0; docs/method.md §2
    log.info("primitives: %d from %s", points.shape[0], source)
    return Primitives(points=points, normals=normals, colors=colors, scales=scales, opacities=opacities, source=source)


def gaussian_log_scales(
    points: np.ndarray,  # (N, 3) float32
    neighbors: int = 3,
    min_sq_distance: float = 1e-7,
    point_size: float = 0.05,
    tree: cKDTree | None = None,  # a tree of ``points`` as float64, when the caller has one
) -> np.ndarray:  # (N, 3) float32
    """Isotropic 3DGS log scales as in the reference initialisation (section 2).

    ``log(sqrt(max(mean_k |p - p_k|^2, min_sq_distance) * point_size))`` over the ``neighbors`` nearest other
    points (simple-knn ``distCUDA2`` with k = 3), repeated over the 3 axes.

    Args:
        points: Centres. ``(N, 3)``.
        neighbors: Nearest neighbours averaged, self excluded.
        min_sq_distance: Floor on the mean squared distance, m^2 (duplicates give 0).
        point_size: Factor on the squared distance (reference ``point_size`` 0.05).

    Returns:
        Log scales. ``(N, 3)`` float32, the same value on the 3 axes.

    Example:
        >>> s = gaussian_log_scales(np.array([[0, 0, 0], [1, 0, 0]], np.float32), neighbors=1)
        >>> bool(np.allclose(np.exp(s), np.sqrt(0.05)))
        True
    """
    n = points.shape[0]
    k = min(neighbors, n - 1)
    if k >= 1:
        from scipy.spatial import cKDTree

        tree = cKDTree(np.asarray(points, dtype=np.float64)) if tree is None else tree
        dist, _ = tree.query(points, k=k + 1, workers=-1)  # (N, k + 1); column 0: the point itself (or a duplicate)
        mean_sq = np.mean(np.square(dist[:, 1:]), axis=1)  # (N,)
    else:
        mean_sq = np.zeros(n)  # a lone point has no neighbour: the floor applies
    log_scale = np.log(np.sqrt(np.maximum(mean_sq, min_sq_distance) * point_size))  # (N,)
    return np.repeat(log_scale[:, None], 3, axis=1).astype(np.float32)


def estimate_normals(
    points: np.ndarray,  # (N, 3)
    radius: float,
    max_nn: int,
    tree: cKDTree | None = None,  # a tree of ``points`` as float64, when the caller has one
) -> np.ndarray:  # (N, 3) float32
    """Unit normals by open3d's hybrid-search PCA, deliberately NOT oriented (docs/method.md §4.1, pitfall 10).

    open3d's construction, signs included (:func:`panogs_core.point_normals.pca_normals`). Points it cannot fit
    (fewer than 3 neighbours in ``radius``) get ``(0, 0, 1)``: every row is unit.
    """
    from panogs_core.point_normals import pca_normals

    normals = pca_normals(points, radius, max_nn, tree)  # (N, 3) float64
    norm = np.linalg.norm(normals, axis=1, keepdims=True)  # (N, 1)
    good = np.isfinite(norm[:, 0]) & (norm[:, 0] > 1e-6)
    out = np.empty_like(normals, dtype=np.float32)
    out[good] = normals[good] / norm[good]
    out[~good] = _DEFAULT_NORMAL
    return out


def _clip_colors(colors: np.ndarray) -> np.ndarray:  # (N, 3) float32 in [0, 1]
    return np.clip(np.nan_to_num(np.asarray(colors, dtype=np.float32)), 0.0, 1.0)


# -------------------------------------------------------------------------------------------------- TSDF path


def _tsdf_frames(bundle: Bundle, cfg: PrimitivesConfig) -> list[Frame]:
    """Frames to integrate: every ``frame_stride``-th frame with a finite pose."""
    frames = [f for f in bundle.frames[:: cfg.frame_stride] if np.all(np.isfinite(f.T_world_cam))]
    if not frames:
        raise InputError("primitives: no frame with a finite pose to reconstruct the scene from")
    return frames


def _tsdf_points(
    bundle: Bundle, cfg: PrimitivesConfig, on_progress: ProgressFn | None
) -> tuple[np.ndarray, np.ndarray | None]:  # (N, 3) float32, (N, 3) float32 or None
    """Fuse the depth frames into a TSDF, extract its surface points, downsample under the cap."""
    frames = _tsdf_frames(bundle, cfg)
    # Colour is all or nothing: a grid with a colour channel needs a colour image for every integration.
    with_color = all(f.color is not None for f in frames)
    block_count = _estimate_block_count(bundle, frames, cfg)
    for attempt in range(_TSDF_ATTEMPTS):
        try:
            grid = _integrate(bundle, frames, cfg, with_color, block_count, on_progress)
            break
        except RuntimeError as exc:  # open3d reports a full hash map as a RuntimeError
            if attempt == _TSDF_ATTEMPTS - 1:
                raise
            log.warning("TSDF with %d blocks failed (%s); retrying with twice as many", block_count, exc)
            block_count *= 2
    no_surface = InputError(
        "primitives: the TSDF of the depth frames has no surface "
        "(check depth_scale, depth_max, min_weight and the poses)"
    )
    try:
        cloud = grid.extract_point_cloud(weight_threshold=cfg.min_weight)
    except RuntimeError as exc:  # open3d 0.20 raises (instead of returning nothing) on some empty grids
        raise no_surface from exc
    if "positions" not in cloud.point or len(cloud.point.positions) == 0:
        raise no_surface
    points = cloud.point.positions.numpy().astype(np.float64)  # (M, 3)
    colors = cloud.point.colors.numpy().astype(np.float64) if with_color else None  # (M, 3)
    del grid, cloud
    points_ds, colors_ds = _downsample_under_cap(points, colors, cfg)
    return points_ds.astype(np.float32), None if colors_ds is None else _clip_colors(colors_ds)


def _o3d_depth(bundle: Bundle, frame: Frame, cfg: PrimitivesConfig) -> Any:
    """The frame's depth as an open3d float image in metres, or None when no pixel is in range.

    Readings outside ``[depth_min, depth_max]`` or non-finite become 0 (no depth). A frame without one valid
    reading is skipped: open3d refuses to integrate a depth image that touches no block.
    """
    o3d = _open3d()

    depth = np.array(bundle.read_depth(frame), dtype=np.float32)  # (H, W) copy: we edit it
    valid = np.isfinite(depth) & (depth >= cfg.depth_min) & (depth <= cfg.depth_max)
    if not valid.any():
        return None
    depth[~valid] = 0.0
    return o3d.t.geometry.Image(_tensor(depth))


def _tensor(array: np.ndarray) -> Any:
    """An open3d tensor over a C-contiguous copy-free view of ``array`` (open3d keeps the array alive)."""
    return _open3d().core.Tensor.from_numpy(np.ascontiguousarray(array))


def _extrinsic(frame: Frame) -> Any:
    return _tensor(np.linalg.inv(np.asarray(frame.T_world_cam, dtype=np.float64)))  # (4, 4) T_cam_world


def _new_grid(cfg: PrimitivesConfig, with_color: bool, block_count: int) -> Any:
    o3d = _open3d()
    o3c = o3d.core

    names, dtypes, channels = ["tsdf", "weight"], [o3c.float32, o3c.float32], [o3c.SizeVector([1])] * 2
    if with_color:
        names.append("color")
        dtypes.append(o3c.float32)
        channels.append(o3c.SizeVector([3]))
    return o3d.t.geometry.VoxelBlockGrid(
        names, dtypes, channels, cfg.voxel_size, cfg.block_resolution, block_count, o3c.Device("CPU:0")
    )


def _estimate_block_count(bundle: Bundle, frames: list[Frame], cfg: PrimitivesConfig) -> int:
    """Blocks the scene needs: union of the blocks touched by up to 16 evenly spread frames, with a margin.

    A sample is enough because open3d's CPU hash map grows on demand (and a refusal is retried with twice the
    blocks); the estimate only avoids repeated re-hashing, and a first allocation far too large for a small
    scene (each block holds block_resolution^3 voxels, 80 kB at 16^3 with colour).
    """
    probe = _new_grid(cfg, False, 64)
    intrinsic = _tensor(bundle.camera.K)
    picks = np.unique(np.linspace(0, len(frames) - 1, min(_SIZING_FRAMES, len(frames))).round().astype(int))
    seen: set[tuple[int, int, int]] = set()
    for i in picks:
        depth = _o3d_depth(bundle, frames[i], cfg)
        if depth is None:
            continue
        coords = probe.compute_unique_block_coordinates(
            depth, intrinsic, _extrinsic(frames[i]), 1.0, cfg.depth_max, cfg.trunc_voxels
        )
        seen.update(map(tuple, coords.numpy().tolist()))
    return max(256, int(len(seen) * _BLOCK_MARGIN))


def _integrate(
    bundle: Bundle,
    frames: list[Frame],
    cfg: PrimitivesConfig,
    with_color: bool,
    block_count: int,
    on_progress: ProgressFn | None,
) -> Any:
    """Integrate every frame into a new voxel block grid and return it.

    Raises:
        InputError: if no frame has a depth reading in range.
    """
    grid = _new_grid(cfg, with_color, block_count)
    integrated = 0
    for done, frame in enumerate(frames, start=1):
        integrated += _integrate_frame(grid, bundle, frame, cfg, with_color)
        report(on_progress, done, len(frames))
    if integrated == 0:
        raise InputError(
            f"primitives: no frame has a depth reading in [depth_min, depth_max] = "
            f"[{cfg.depth_min}, {cfg.depth_max}] m, so there is no surface (check depth_scale and poses)"
        )
    return grid


def _integrate_frame(grid: Any, bundle: Bundle, frame: Frame, cfg: PrimitivesConfig, with_color: bool) -> bool:
    """Integrate one frame (depth, and colour when the grid has it); False when it has no valid depth."""
    o3d = _open3d()

    depth = _o3d_depth(bundle, frame, cfg)
    if depth is None:
        return False
    extrinsic = _extrinsic(frame)
    coords = grid.compute_unique_block_coordinates(
        depth, _tensor(bundle.camera.K), extrinsic, 1.0, cfg.depth_max, cfg.trunc_voxels
    )
    # open3d's integration truncates a voxel's projected pixel coordinates (floor, not round): with pixel
    # centres at integer coordinates (docs/conventions.md) it reads the pixel half a pixel up-left, which biases
    # the surface (measured 2-4 mm at 320 x 240, 1-2 cm at 80 x 60). Shifting the principal point by +0.5 px
    # turns the truncation into a nearest-pixel lookup (bias measured < 0.3 mm).
    lookup = _tensor(bundle.camera.K + np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0]]))
    color = bundle.read_color(frame) if with_color else None
    if color is not None:
        color_img = o3d.t.geometry.Image(_tensor(np.asarray(color, dtype=np.float32) / 255.0))
        grid.integrate(coords, depth, color_img, lookup, lookup, extrinsic, 1.0, cfg.depth_max, cfg.trunc_voxels)
    else:
        grid.integrate(coords, depth, lookup, extrinsic, 1.0, cfg.depth_max, cfg.trunc_voxels)
    return True


def _downsample_under_cap(
    points: np.ndarray,  # (M, 3) float64
    colors: np.ndarray | None,  # (M, 3) float64
    cfg: PrimitivesConfig,
) -> tuple[np.ndarray, np.ndarray | None]:  # (N, 3), (N, 3) or None
    """Voxel-downsample (cell means) at ``target_spacing``, growing the cell until N <= ``max_primitives``.

    Deterministic: open3d's voxel-block grid extracts its surface in hash-map order, which changes from run to
    run, and so did open3d's downsampling and every stage after it (PRQ(T) 0.76 and 0.66 for two runs of one
    scene). Here the points are put in coordinate order first and the cells come out in key order.
    """
    order = np.lexsort((points[:, 2], points[:, 1], points[:, 0]))
    points = points[order]
    colors = None if colors is None else colors[order]
    spacing = cfg.target_spacing
    while True:
        # Extracted points sit on the TSDF voxel lattice in two of their coordinates; cells offset by half a
        # voxel keep their boundaries off that lattice, where rounding would split a row of points in two
        # (absolute cells gave 97.7k primitives for a room that open3d's downsampling made 76.0k, this 72.7k).
        cell = voxel_cells(points, spacing, offset=cfg.voxel_size / 2)
        n = int(cell.max()) + 1
        if n <= cfg.max_primitives:
            break
        spacing *= cfg.spacing_growth
    log.info("primitives: %d TSDF points -> %d at %.3f m spacing", points.shape[0], n, spacing)
    counts = np.bincount(cell, minlength=n)[:, None].astype(np.float64)
    means = np.stack([np.bincount(cell, weights=points[:, k], minlength=n) for k in range(3)], 1) / counts
    if colors is None:
        return means, None
    return means, np.stack([np.bincount(cell, weights=colors[:, k], minlength=n) for k in range(3)], 1) / counts


def voxel_cells(points: np.ndarray, spacing: float, offset: float = 0.0) -> np.ndarray:  # (M,) int64, key order
    """Cell of each point on a grid of ``spacing`` metres whose first cell starts ``offset`` metres below the
    points' minimum, cells numbered densely by ascending (x, y, z) cell index.

    Example:
        >>> voxel_cells(np.array([[0.05, 0, 0], [0.01, 0, 0], [0.25, 0, 0]]), 0.1).tolist()
        [0, 0, 1]
    """
    index = np.floor((points - points.min(axis=0) + offset) / spacing).astype(np.int64)
    span = index.max(axis=0) + 1
    key = (index[:, 0] * span[1] + index[:, 1]) * span[2] + index[:, 2]
    return np.unique(key, return_inverse=True)[1].reshape(-1).astype(np.int64)
