"""Points on every visible surface of a layout, with ground-truth class and instance per point.

Faces are filled with a jittered grid, so the spacing is roughly uniform and the count per face proportional
to its area. Points on faces that lie against another box (a cabinet's back on the wall, the floor under it, a
sink's bottom on the counter) are removed: they can never be seen. Points hidden from every camera position
but not covered (e.g. under a low table) stay, as on a real mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from panogs_core.synthetic.layout import NUM_STUFF, Layout
from panogs_core.synthetic.placement import rotation_z

_CONTACT_EPS = 1e-3  # a point this close to (or inside) another box counts as covered, metres
_JITTER = 0.35  # grid jitter, as a fraction of a cell


@dataclass(frozen=True)
class SurfacePoints:
    """Surface samples of a layout."""

    points: np.ndarray  # (N, 3) float32, world, metres
    normals: np.ndarray  # (N, 3) float32, unit, pointing out of the surface
    colors: np.ndarray  # (N, 3) float32 in [0, 1], albedo
    semantic: np.ndarray  # (N,) int64 catalogue class
    instance: np.ndarray  # (N,) int64 layout instance
    box: np.ndarray  # (N,) int64 layout box


@dataclass(frozen=True)
class _Faces:
    origin: np.ndarray  # (F, 3) a corner of the face
    u: np.ndarray  # (F, 3) edge vector
    v: np.ndarray  # (F, 3) edge vector
    normal: np.ndarray  # (F, 3)
    box: np.ndarray  # (F,)


def _faces(layout: Layout) -> _Faces:
    """All six faces of every object box, and the inner face (the room side) of every slab."""
    b = layout.boxes
    rot = rotation_z(b.yaw)  # (B, 3, 3), columns are the box axes
    origin, u, v, normal, box = [], [], [], [], []
    for axis in range(3):
        i, j = [a for a in range(3) if a != axis]
        for sign in (-1.0, 1.0):
            n = sign * rot[:, :, axis]
            ei, ej = rot[:, :, i] * b.half[:, i : i + 1], rot[:, :, j] * b.half[:, j : j + 1]
            origin.append(b.centers + n * b.half[:, axis : axis + 1] - ei - ej)
            u.append(2 * ei)
            v.append(2 * ej)
            normal.append(n)
            box.append(np.arange(len(b.yaw)))
    faces = _Faces(*(np.concatenate(x) for x in (origin, u, v, normal, box)))
    keep = faces.box >= NUM_STUFF
    stuff = _slab_faces(layout.room)
    return _Faces(*(np.concatenate([getattr(stuff, k), getattr(faces, k)[keep]]) for k in _Faces.__annotations__))


def _slab_faces(room: np.ndarray) -> _Faces:
    """Inner faces of floor, ceiling and walls 0-3, exactly the room's extent (boxes 0-5)."""
    lx, ly, h = room
    ex, ey, ez = np.array([lx, 0, 0]), np.array([0, ly, 0]), np.array([0, 0, h])
    z = np.zeros(3)
    origin = np.array([z, ez, z, ex, ey, z])
    u = np.array([ex, ex, ex, ey, ex, ey])
    v = np.array([ey, ey, ez, ez, ez, ez])
    normal = np.array([[0, 0, 1], [0, 0, -1], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [1, 0, 0]], dtype=np.float64)
    return _Faces(origin, u, v, normal, np.arange(NUM_STUFF))


def _grid_points(faces: _Faces, spacing: float, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Jittered grid on each face: ``(P, 3)`` points and ``(P,)`` face index."""
    nu = np.maximum(np.rint(np.linalg.norm(faces.u, axis=1) / spacing), 1).astype(np.int64)
    nv = np.maximum(np.rint(np.linalg.norm(faces.v, axis=1) / spacing), 1).astype(np.int64)
    counts = nu * nv
    face = np.repeat(np.arange(len(counts)), counts)
    local = np.arange(len(face)) - np.repeat(np.cumsum(counts) - counts, counts)
    iu, iv = local // nv[face], local % nv[face]
    a = (iu + 0.5 + rng.uniform(-_JITTER, _JITTER, len(face))) / nu[face]
    b = (iv + 0.5 + rng.uniform(-_JITTER, _JITTER, len(face))) / nv[face]
    pts = faces.origin[face] + a[:, None] * faces.u[face] + b[:, None] * faces.v[face]
    return pts, face


def covered(points: np.ndarray, own_box: np.ndarray, layout: Layout) -> np.ndarray:  # (P,) bool
    """True where a point lies inside (or on) a box other than its own."""
    b = layout.boxes
    order = np.argsort(points[:, 0], kind="stable")
    xs = points[order, 0]
    reach = np.abs(np.cos(b.yaw)) * b.half[:, 0] + np.abs(np.sin(b.yaw)) * b.half[:, 1] + _CONTACT_EPS
    out = np.zeros(len(points), dtype=bool)
    for k in range(len(b.yaw)):
        lo, hi = np.searchsorted(xs, [b.centers[k, 0] - reach[k], b.centers[k, 0] + reach[k]])
        idx = order[lo:hi]
        idx = idx[own_box[idx] != k]
        rel = points[idx] - b.centers[k]
        c, s = np.cos(b.yaw[k]), np.sin(b.yaw[k])
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1], rel[:, 2]], 1)
        out[idx[(np.abs(local) <= b.half[k] + _CONTACT_EPS).all(axis=1)]] = True
    return out


def sample_surfaces(layout: Layout, num_points: int, rng: np.random.Generator) -> SurfacePoints:
    """Sample about ``num_points`` points on the visible surfaces of a layout.

    The spacing is set from the uncovered area, measured on a coarse first pass, so that the final count
    lands near ``num_points`` whatever the room.

    Args:
        layout: The room.
        num_points: Target number of points.
        rng: Source of the grid jitter.

    Returns:
        Points with normals, albedo colours and ground-truth labels.
    """
    faces = _faces(layout)
    area = float(np.sum(np.linalg.norm(faces.u, axis=1) * np.linalg.norm(faces.v, axis=1)))
    coarse = np.sqrt(area / num_points) * 2.0
    pts, face = _grid_points(faces, coarse, rng)
    visible = 1.0 - covered(pts, faces.box[face], layout).mean()
    spacing = float(np.sqrt(area * visible / num_points))
    pts, face = _grid_points(faces, spacing, rng)
    keep = ~covered(pts, faces.box[face], layout)
    pts, face = pts[keep], face[keep]
    box = faces.box[face]
    return SurfacePoints(
        points=pts.astype(np.float32),
        normals=faces.normal[face].astype(np.float32),
        colors=layout.box_color[box],
        semantic=layout.box_class[box],
        instance=layout.box_instance[box],
        box=box,
    )
