"""Collision-free placement of box models in a rectangular room (the mechanics behind ``layout.py``).

World frame: the room spans ``[0, Lx] x [0, Ly] x [0, H]``, z up, metres. Boxes are oriented by a yaw about z.
Walls are numbered 0: y = 0, 1: x = Lx, 2: y = Ly, 3: x = 0; an object against wall ``w`` has yaw ``w * 90``
degrees, so that its local +y (its front) points into the room.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from panogs_core.synthetic.shapes import Model

_EPS = 1e-6


@dataclass
class Group:
    """Models placed together (e.g. a table with its chairs), in one group-local frame.

    Attributes:
        models: The objects, parts in group-local coordinates.
        contacts: Index pairs of models that touch or nearly touch (candidates for merged 2D masks).
        keepout: Extra ``(K, 7)`` boxes that must stay free (e.g. a door's swing), not rendered.
    """

    models: list[Model]
    contacts: list[tuple[int, int]] = field(default_factory=list)
    keepout: np.ndarray = field(default_factory=lambda: np.zeros((0, 7)))

    def parts(self) -> np.ndarray:  # (P, 7)
        """All parts of all models, stacked."""
        return np.concatenate([m.parts for m in self.models])

    def bounds(self) -> np.ndarray:  # (3, 2)
        """Local bounds of all parts."""
        p = self.parts()
        return np.array([[p[:, 0].min(), p[:, 1].max()], [p[:, 2].min(), p[:, 3].max()],
                         [p[:, 4].min(), p[:, 5].max()]])  # fmt: skip


@dataclass(frozen=True)
class Boxes:
    """Oriented boxes in the world frame."""

    centers: np.ndarray  # (B, 3)
    half: np.ndarray  # (B, 3) half extents along the box's own axes
    yaw: np.ndarray  # (B,) radians about z


def rotation_z(yaw: np.ndarray) -> np.ndarray:  # (..., 3, 3)
    """Rotation matrices about z."""
    c, s = np.cos(yaw), np.sin(yaw)
    z, o = np.zeros_like(c), np.ones_like(c)
    return np.stack([np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)], -2)


def to_world(parts: np.ndarray, pose: np.ndarray) -> Boxes:
    """Local ``(P, 7)`` parts under a pose ``(x, y, z, yaw)`` as world boxes."""
    centre = np.stack([parts[:, 0] + parts[:, 1], parts[:, 2] + parts[:, 3], parts[:, 4] + parts[:, 5]], 1) / 2
    half = np.stack([parts[:, 1] - parts[:, 0], parts[:, 3] - parts[:, 2], parts[:, 5] - parts[:, 4]], 1) / 2
    rot = rotation_z(np.asarray(pose[3]))
    return Boxes(centre @ rot.T + pose[:3], half, np.full(len(parts), pose[3]))


def overlaps(a: Boxes, b: Boxes, clearance: float) -> bool:
    """True if any box of ``a`` comes closer than ``clearance`` to any box of ``b`` (touching is allowed).

    Separating-axis test for boxes that only rotate about z: the z intervals, then the four in-plane axes.
    """
    if len(a.yaw) == 0 or len(b.yaw) == 0:
        return False
    gap = clearance - _EPS
    dz = np.abs(a.centers[:, None, 2] - b.centers[None, :, 2])
    hit = dz < a.half[:, None, 2] + b.half[None, :, 2] + gap
    d = b.centers[None, :, :2] - a.centers[:, None, :2]  # (A, B, 2)
    yaw_a, yaw_b = np.broadcast_arrays(a.yaw[:, None], b.yaw[None, :])
    axes = [(np.cos(y), np.sin(y)) for y in (yaw_a, yaw_b)]
    axes += [(-ay, ax) for ax, ay in axes]
    for ax, ay in axes:
        ra = _radius(a.half[:, None], a.yaw[:, None], ax, ay)
        rb = _radius(b.half[None, :], b.yaw[None, :], ax, ay)
        hit &= np.abs(d[..., 0] * ax + d[..., 1] * ay) < ra + rb + gap
    return bool(hit.any())


def _radius(half: np.ndarray, yaw: np.ndarray, ax: np.ndarray, ay: np.ndarray) -> np.ndarray:
    """Half-length of the projection of oriented rectangles onto the axis (ax, ay)."""
    c, s = np.cos(yaw), np.sin(yaw)
    return half[..., 0] * np.abs(c * ax + s * ay) + half[..., 1] * np.abs(-s * ax + c * ay)


def inside_room(boxes: Boxes, room: np.ndarray, margin: float = 0.0) -> bool:
    """True if every box lies within the room (x, y inset by ``margin``; z between floor and ceiling)."""
    rot = rotation_z(boxes.yaw)[:, :2, :2]  # (B, 2, 2)
    signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]], dtype=np.float64)
    corners = boxes.centers[:, None, :2] + np.einsum("bij,bkj->bki", rot, signs[None] * boxes.half[:, None, :2])
    lo = margin - _EPS
    ok_xy = (
        (corners >= lo).all() and (corners[..., 0] <= room[0] - lo).all() and (corners[..., 1] <= room[1] - lo).all()
    )
    z0, z1 = boxes.centers[:, 2] - boxes.half[:, 2], boxes.centers[:, 2] + boxes.half[:, 2]
    return bool(ok_xy and (z0 >= -_EPS).all() and (z1 <= room[2] + _EPS).all())


def wall_pose(room: np.ndarray, wall: int, t: float, bounds: np.ndarray, lift: float = 0.0) -> np.ndarray:
    """Pose ``(x, y, z, yaw)`` putting a group's back (local min y) on a wall, its centre-x at ``t`` along it.

    Args:
        room: ``(Lx, Ly, H)``.
        wall: Wall index 0-3.
        t: Position along the wall (metres from the wall's start corner, walls run counter-clockwise).
        bounds: Local bounds ``(3, 2)`` of the group.
        lift: Height of the group's local z = 0 above the floor.
    """
    lx, ly = room[0], room[1]
    origin = np.array([[0.0, 0.0], [lx, 0.0], [lx, ly], [0.0, ly]])[wall]
    yaw = wall * np.pi / 2
    along = np.array([np.cos(yaw), np.sin(yaw)])
    normal = np.array([-np.sin(yaw), np.cos(yaw)])
    cx = (bounds[0, 0] + bounds[0, 1]) / 2
    xy = origin + (t - cx) * along - bounds[1, 0] * normal
    return np.array([xy[0], xy[1], lift, yaw])


def wall_length(room: np.ndarray, wall: int) -> float:
    """Length of a wall."""
    return float(room[0] if wall % 2 == 0 else room[1])


def wall_span(room: np.ndarray, wall: int, zone: tuple[float, float]) -> tuple[float, float] | None:
    """The interval of positions ``t`` along a wall that lies in a zone ``(x0, x1)``; None if none."""
    lx = room[0]
    if wall == 0:
        return zone
    if wall == 2:
        return (lx - zone[1], lx - zone[0])
    if (wall == 1 and zone[1] >= lx - _EPS) or (wall == 3 and zone[0] <= _EPS):
        return (0.0, float(room[1]))
    return None
