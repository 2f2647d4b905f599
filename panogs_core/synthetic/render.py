"""Ray-cast a layout into a pinhole camera: depth, colour, and per-pixel box / face ids.

Uses ``open3d.t.geometry.RaycastingScene`` on one triangle mesh that holds every box as 12 triangles
(box-major, then face, then two triangles), so a hit's triangle index gives its box and face without a lookup
table. Rays are built with a z component of 1 in the camera frame, which makes ``t_hit`` the z depth directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import open3d as o3d

from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.placement import rotation_z
from panogs_core.types import Camera

_SUN = np.array([0.35, 0.55, 0.76]) / np.linalg.norm([0.35, 0.55, 0.76])
# Corner k of a box has signs (bit0, bit1, bit2) -> (x, y, z); faces ordered axis-major, negative side first.
_CORNERS = np.array([[(k >> 0) & 1, (k >> 1) & 1, (k >> 2) & 1] for k in range(8)], dtype=np.float64) * 2 - 1
_FACE_QUADS = np.array([
    [0, 4, 6, 2], [1, 3, 7, 5],  # x-, x+
    [0, 1, 5, 4], [2, 6, 7, 3],  # y-, y+
    [0, 2, 3, 1], [4, 5, 7, 6],  # z-, z+
])  # fmt: skip


@dataclass(frozen=True)
class Render:
    """One rendered view."""

    depth: np.ndarray  # (H, W) float32 z depth in metres, 0 where nothing was hit
    box: np.ndarray  # (H, W) int64 layout box, -1 where nothing was hit
    face: np.ndarray  # (H, W) int64 face 0-5 of that box (axis-major, negative side first)
    color: np.ndarray  # (H, W, 3) float32 shaded albedo in [0, 1]


def box_mesh(layout: Layout) -> tuple[np.ndarray, np.ndarray]:
    """Vertices ``(8B, 3)`` float32 and triangles ``(12B, 3)`` uint32 of all boxes of a layout."""
    b = layout.boxes
    rot = rotation_z(b.yaw)  # (B, 3, 3)
    local = _CORNERS[None] * b.half[:, None, :]  # (B, 8, 3)
    verts = np.einsum("bij,bkj->bki", rot, local) + b.centers[:, None, :]
    quads = _FACE_QUADS[None] + 8 * np.arange(len(b.yaw))[:, None, None]  # (B, 6, 4)
    tris = np.stack([quads[..., [0, 1, 2]], quads[..., [0, 2, 3]]], axis=2)  # (B, 6, 2, 3)
    return verts.reshape(-1, 3).astype(np.float32), tris.reshape(-1, 3).astype(np.uint32)


def make_raycaster(layout: Layout) -> o3d.t.geometry.RaycastingScene:
    """A ray-casting scene holding every box of the layout as one mesh."""
    verts, tris = box_mesh(layout)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(verts)),
        o3d.core.Tensor.from_numpy(np.ascontiguousarray(tris)),
    )
    return scene


def camera_rays(camera: Camera, T_world_cam: np.ndarray) -> np.ndarray:  # (H, W, 6) float32
    """Ray origins and directions in the world; directions have camera-frame z = 1 (OpenCV axes)."""
    u, v = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    dirs_cam = np.stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones_like(u, float)], -1)
    dirs = dirs_cam @ T_world_cam[:3, :3].T
    origins = np.broadcast_to(T_world_cam[:3, 3], dirs.shape)
    return np.concatenate([origins, dirs], -1).astype(np.float32)


def render_view(
    scene: o3d.t.geometry.RaycastingScene,
    layout: Layout,
    camera: Camera,
    T_world_cam: np.ndarray,
    shade: bool = True,
) -> Render:
    """Render one view.

    Args:
        scene: From :func:`make_raycaster` on the same layout.
        layout: The room (for colours and box orientations).
        camera: Pinhole model.
        T_world_cam: ``(4, 4)`` camera-to-world pose, OpenCV axes.
        shade: Compute the colour image (False leaves it black: about half the time of a view, for views
            that only decide visibility).

    Returns:
        Clean depth, box and face ids, and a shaded colour image.
    """
    rays = camera_rays(camera, T_world_cam)
    hits = scene.cast_rays(o3d.core.Tensor.from_numpy(np.ascontiguousarray(rays)))
    t_hit = hits["t_hit"].numpy()
    tri = hits["primitive_ids"].numpy().astype(np.int64)
    hit = np.isfinite(t_hit)
    box = np.where(hit, tri // 12, -1)
    face = np.where(hit, (tri % 12) // 2, 0)
    depth = np.where(hit, t_hit, 0.0).astype(np.float32)
    if not shade:
        return Render(depth, box, face, np.zeros((*depth.shape, 3), dtype=np.float32))
    return Render(depth, box, face, _shade(layout, box, face, rays[..., 3:], hit))


def face_normals(layout: Layout, box: np.ndarray, face: np.ndarray) -> np.ndarray:  # (..., 3)
    """World normal of face ``face`` of box ``box`` (pointing out of the box)."""
    yaw = layout.boxes.yaw[np.maximum(box, 0)]
    axis, sign = face // 2, np.where(face % 2 == 1, 1.0, -1.0)
    c, s = np.cos(yaw), np.sin(yaw)
    n = np.zeros((*box.shape, 3))
    n[..., 0] = np.where(axis == 0, c, np.where(axis == 1, -s, 0.0))
    n[..., 1] = np.where(axis == 0, s, np.where(axis == 1, c, 0.0))
    n[..., 2] = np.where(axis == 2, 1.0, 0.0)
    return n * sign[..., None]


def _shade(layout: Layout, box: np.ndarray, face: np.ndarray, dirs: np.ndarray, hit: np.ndarray) -> np.ndarray:
    """Albedo times ambient + sun + head-light terms (enough shading for faces to read apart)."""
    n = face_normals(layout, box, face)
    view = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    light = 0.35 + 0.4 * np.clip(n @ _SUN, 0, None) + 0.3 * np.abs(np.sum(n * view, -1))
    albedo = layout.box_color[np.maximum(box, 0)]
    return np.where(hit[..., None], np.clip(albedo * light[..., None], 0, 1), 0.0).astype(np.float32)
