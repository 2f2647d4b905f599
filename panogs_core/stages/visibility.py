"""Stage 2: which primitives each key frame sees, and at which pixel (projection + depth test).

docs/method.md §3.1 (the reference's ``fuse_feature.py``) and §5.1 (``get_camp_pixel``): a primitive p is seen by
view m when its projection lands inside the depth image and its camera depth agrees with the sensor depth there:

* ``X_c = inv(T_world_cam) [p, 1]``; only ``z > z_near`` is kept, so points behind the camera are out and can
  never wrap into the image (docs/method.md pitfall 9);
* pixel ``(u, v) = rint(K X_c / z)``, round half to even like ``torch.round``; in bounds when
  ``0 <= u <= W - 1`` and ``0 <= v <= H - 1`` (docs/method.md pitfall 8);
* depth test ``|z - D| <= depth_rtol * D + depth_atol`` with ``D`` the sensor depth at that pixel (the
  reference's ``np.isclose(z, D, rtol=0.07)``), at most ``depth_max_tol`` when set; ``D == 0`` (no depth) is
  never seen;
* a frame whose pose is not finite (ScanNet has ``-inf`` poses, docs/method.md pitfall 23) sees nothing.

The result is computed once and shared by fusion (stage 3) and the mask look-ups (``masks``).

DEPARTURE (memory, docs/method.md §3.1): frames streamed, only the seen (point, pixel) pairs kept in CSR form:
O(N + seen pairs), never the reference's dense N x M arrays.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import ConfigError, ShapeError
from panogs_core.io.bundle import Bundle
from panogs_core.io.npz import save_npz
from panogs_core.progress import ProgressFn, report
from panogs_core.threads import prefetched
from panogs_core.types import Camera, Frame

log = logging.getLogger(__name__)


@dataclass(frozen=True, kw_only=True)
class VisibilityConfig:
    """Settings of stage 2.

    Raises:
        ConfigError: naming the field, when a value is out of range.
    """

    # |z - D| <= rtol * D, relative; the reference's thres_vis_dis, docs/method.md §3.1 and pitfall 8
    depth_rtol: float = 0.07
    # m, absolute floor added to the tolerance. The reference's np.isclose uses 1e-8 m, i.e. nothing; 0 keeps
    # its behaviour. Real depth noise is relative (grows with depth), which rtol already covers: 7 cm at 1 m.
    depth_atol: float = 0.0
    # DEPARTURE (docs/method.md §3.1): m, the most the tolerance may reach (None: no cap, the reference). 7 % of
    # the depth is 0.4 m at 5.7 m, more than a wall: frames of the next room saw through it.
    depth_max_tol: float | None = 0.15
    z_near: float = 1e-6  # m, points at camera z <= z_near are out (behind the camera; reference clamps 1e-8)

    def __post_init__(self) -> None:
        if not (math.isfinite(self.depth_rtol) and 0 < self.depth_rtol < 1):
            raise ConfigError(f"visibility.depth_rtol: expected 0 < depth_rtol < 1, got {self.depth_rtol!r}")
        if not (math.isfinite(self.depth_atol) and self.depth_atol >= 0):
            raise ConfigError(f"visibility.depth_atol: expected a finite value >= 0, got {self.depth_atol!r}")
        if self.depth_max_tol is not None and not (math.isfinite(self.depth_max_tol) and self.depth_max_tol > 0):
            raise ConfigError(f"visibility.depth_max_tol: expected null or a value > 0, got {self.depth_max_tol!r}")
        if not (math.isfinite(self.z_near) and self.z_near > 0):
            raise ConfigError(f"visibility.z_near: expected a finite value > 0, got {self.z_near!r}")


@dataclass(frozen=True)
class Visibility:
    """Seen primitives per key frame, in CSR form (never a dense N x V array).

    Frame ``v`` sees ``point_index[offsets[v]:offsets[v + 1]]`` (ascending), at depth-image pixels
    ``(pixel_row, pixel_col)`` of the same slice.
    """

    frame_ids: tuple[str, ...]  # key frames, manifest order
    offsets: np.ndarray  # (V + 1,) int64
    point_index: np.ndarray  # (T,) int32
    pixel_row: np.ndarray  # (T,) int32, v (row) of the depth-image pixel
    pixel_col: np.ndarray  # (T,) int32, u (column)
    # (T,) float16 relative depth residual (z - D) / D of each seen pair, or None. Lets a later stage apply a
    # tighter, per-frame depth test than depth_rtol without projecting again (see affinity.observe_masks).
    depth_residual: np.ndarray | None = None

    def __post_init__(self) -> None:
        v = len(self.frame_ids)
        if self.offsets.shape != (v + 1,):
            raise ShapeError(f"Visibility.offsets: expected shape ({v + 1},), got {self.offsets.shape}")
        t = int(self.offsets[-1])
        names = ["point_index", "pixel_row", "pixel_col"]
        if self.depth_residual is not None:
            names.append("depth_residual")
        for name in names:
            if getattr(self, name).shape != (t,):
                raise ShapeError(f"Visibility.{name}: expected shape ({t},), got {getattr(self, name).shape}")

    @property
    def num_frames(self) -> int:
        """V, the number of key frames."""
        return len(self.frame_ids)

    def frame(self, v: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # 3 x (T_v,) int32
        """``(point_index, pixel_row, pixel_col)`` of key frame ``v`` (views, not copies)."""
        lo, hi = int(self.offsets[v]), int(self.offsets[v + 1])
        return self.point_index[lo:hi], self.pixel_row[lo:hi], self.pixel_col[lo:hi]

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` at exactly ``path`` (no pickles: frame ids as a unicode array)."""
        arrays: dict[str, Any] = {
            "frame_ids": np.array(self.frame_ids, dtype=str),
            "offsets": self.offsets,
            "point_index": self.point_index,
            "pixel_row": self.pixel_row,
            "pixel_col": self.pixel_col,
        }
        if self.depth_residual is not None:
            arrays["depth_residual"] = self.depth_residual
        save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | Path) -> Visibility:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as z:
            return cls(
                frame_ids=tuple(str(f) for f in z["frame_ids"]),
                offsets=z["offsets"],
                point_index=z["point_index"],
                pixel_row=z["pixel_row"],
                pixel_col=z["pixel_col"],
                depth_residual=z["depth_residual"] if "depth_residual" in z.files else None,
            )


def compute_visibility(
    bundle: Bundle,
    points: np.ndarray,  # (N, 3) float32, world, metres
    cfg: VisibilityConfig,
    *,
    frames: Sequence[Frame] | None = None,
    on_progress: ProgressFn | None = None,
) -> Visibility:
    """Project the primitives into every key frame and keep those that pass the depth test.

    Args:
        bundle: The opened bundle (camera, poses, depth).
        points: Primitive centres. ``(N, 3)`` float32, world frame, metres.
        cfg: Stage settings.
        frames: Key frames, in the order wanted; default: the scene's frames that have features or masks,
            in manifest order.
        on_progress: ``(done, total)`` once per frame.

    Returns:
        The CSR visibility over ``frames``.

    Raises:
        ShapeError: if ``points`` is not ``(N, 3)``, or a depth image is not the camera size.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] >= 2**31:
        raise ShapeError(f"points: expected (N, 3) with N < 2^31, got shape {points.shape}")
    points32 = np.ascontiguousarray(points, dtype=np.float32)  # (N, 3)
    if frames is None:
        frames = tuple(f for f in bundle.frames if f.features is not None or f.masks is not None)
    start = time.perf_counter()
    parts: list[tuple[np.ndarray, ...]] = []

    def part(frame: Frame) -> tuple[np.ndarray, ...]:  # run a few frames ahead on threads (decoding the depth)
        T_cam_world = _inverse_pose(frame.T_world_cam)
        if T_cam_world is None:
            return _empty_part()
        depth = bundle.read_depth(frame)  # (H, W) float32 metres
        return frame_visibility(points32, T_cam_world, bundle.camera, depth, cfg)

    for done, frame_part in enumerate(prefetched(part, frames), start=1):
        parts.append(frame_part)
        report(on_progress, done, len(frames))
    vis = _assemble(tuple(f.id for f in frames), parts)
    log.info(
        "visibility: %d points x %d frames -> %d seen pairs in %.2f s",
        points32.shape[0], len(frames), vis.point_index.shape[0], time.perf_counter() - start,
    )  # fmt: skip
    return vis


def frame_visibility(
    points: np.ndarray,  # (N, 3) float32, world
    T_cam_world: np.ndarray,  # (4, 4) float64, world-to-camera
    camera: Camera,
    depth: np.ndarray,  # (H, W) float32 metres, 0 = no depth
    cfg: VisibilityConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # 3 x (T_v,) int32, (T_v,) float16
    """Primitives seen by one frame: point index (ascending), pixel row and column, relative depth residual.

    Float32 arithmetic: coordinates of metres at float32 precision (1e-7 relative) move a projection by far
    less than a pixel, and halve the memory traffic of the per-point passes.

    Raises:
        ShapeError: if ``depth`` is not ``(camera.height, camera.width)``.
    """
    h, w = camera.height, camera.width
    if depth.shape != (h, w):
        raise ShapeError(f"depth: expected ({h}, {w}) (camera height, width), got {depth.shape}")
    rot = np.ascontiguousarray(T_cam_world[:3, :3], dtype=np.float32)  # (3, 3)
    trans = T_cam_world[:3, 3].astype(np.float32)  # (3,)
    # Depth first: the cheapest pass, and it discards points behind the camera before any division.
    # One matrix-vector product per camera axis: numpy's (N, 3) @ (3, k) for small k is ~50x slower.
    z_all = points @ rot[2] + trans[2]  # (N,)
    idx = np.flatnonzero(z_all > cfg.z_near)  # NaN compares False: non-finite points drop out here
    z = z_all[idx]
    front = points[idx]  # (n, 3)
    x, y = front @ rot[0] + trans[0], front @ rot[1] + trans[1]  # (n,) each
    u = np.rint(np.float32(camera.fx) * x / z + np.float32(camera.cx))  # round half to even
    v = np.rint(np.float32(camera.fy) * y / z + np.float32(camera.cy))
    inside = (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)  # on floats: no int overflow far off-image
    idx, z = idx[inside], z[inside]
    col, row = u[inside].astype(np.int32), v[inside].astype(np.int32)
    d = depth[row, col]  # sensor depth at the pixel
    # docs/method.md pitfall 8; D = 0 is never seen
    tolerance = cfg.depth_rtol * d + cfg.depth_atol
    if cfg.depth_max_tol is not None:
        tolerance = np.minimum(tolerance, np.float32(cfg.depth_max_tol))
    seen = (d > 0) & (np.abs(z - d) <= tolerance)
    residual = ((z[seen] - d[seen]) / d[seen]).astype(np.float16)  # |residual| <= rtol: float16 keeps 3 digits
    return idx[seen].astype(np.int32), row[seen], col[seen], residual


def _inverse_pose(T_world_cam: np.ndarray) -> np.ndarray | None:  # (4, 4) float64 T_cam_world, or None
    """World-to-camera matrix, or None when the pose is unusable (non-finite or singular: sees nothing)."""
    pose = np.asarray(T_world_cam, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        return None
    try:
        inverse = np.linalg.inv(pose)  # as the reference: inv(c2w), not the rigid shortcut
    except np.linalg.LinAlgError:
        return None
    return inverse if np.all(np.isfinite(inverse)) else None


def _empty_part() -> tuple[np.ndarray, ...]:
    empty = np.zeros(0, dtype=np.int32)
    return empty, empty, empty, np.zeros(0, dtype=np.float16)


def _assemble(frame_ids: tuple[str, ...], parts: list[tuple[np.ndarray, ...]]) -> Visibility:
    counts = np.array([p[0].shape[0] for p in parts], dtype=np.int64)  # (V,)
    offsets = np.concatenate([np.zeros(1, dtype=np.int64), np.cumsum(counts)])  # (V + 1,)
    if not parts:
        parts = [_empty_part()]

    def cat(i: int) -> np.ndarray:
        return np.concatenate([p[i] for p in parts]).astype(np.int32, copy=False)

    residual = np.concatenate([p[3] for p in parts]).astype(np.float16, copy=False)
    return Visibility(
        frame_ids=frame_ids, offsets=offsets, point_index=cat(0), pixel_row=cat(1), pixel_col=cat(2),
        depth_residual=residual,
    )  # fmt: skip
