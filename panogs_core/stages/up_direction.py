"""The run's up direction in world coordinates: the bundle's ``up`` when the capture knew gravity, else an estimate.

The estimate takes the cameras first: a person holds a camera roughly level, so the mean of the frames' "up" axes
(minus the y axis of each OpenCV camera, docs/conventions.md) is within some tens of degrees of gravity, however
the capture tool chose its world axes. The floors, table tops and ceilings then sharpen it: among the primitives'
normals (not oriented) those within ``CONE_DEG`` of that guess are horizontal surfaces, and the axis their
directions spread least about (the principal axis of their scatter) is the plane normal. Walls, 90 degrees away,
stay out of the cone as long as the cameras' mean up is within 45 degrees of gravity. The camera guess picks the
normal's sign (floors face the cameras' up) and stands alone when too few normals are horizontal.

An estimate within ``SNAP_DEG`` of a world axis is that axis: most tools write a gravity-aligned world (z-up
reconstructions, y-up ARKit), and the floor fit's own noise is of that order (0.33 degrees off z on the tiny
synthetic room, whose world is exactly z-up), so an axis that close is the capture's up, not a coincidence.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CONE_DEG = (45.0, 20.0)  # normals within this of the current guess count as horizontal surfaces, one pass each
MIN_SHARE = 0.02  # fewer horizontal normals than this share of all: keep the cameras' guess
SNAP_DEG = 2.0  # an estimate this close to a world axis is taken as that axis (module docstring)


@dataclass(frozen=True)
class UpDirection:
    """Up in world coordinates and where it came from.

    Attributes:
        up: Unit vector ``(3,)``.
        source: ``bundle`` (``scene.json`` ``up``), ``floor`` (the horizontal surfaces' normal) or ``cameras``
            (the frames' mean up).
    """

    up: tuple[float, float, float]
    source: str

    def to_json(self) -> dict[str, object]:
        return {"up": list(self.up), "source": self.source}


def camera_up(poses: list[np.ndarray]) -> np.ndarray:  # (3,) unit
    """The mean of the cameras' up axes (minus the y column of each camera-to-world rotation); +z when they cancel.

    Example:
        >>> level = np.eye(4); level[:3, :3] = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]  # looking along +y, z up
        >>> camera_up([level]).round(6).tolist() == [0.0, 0.0, 1.0]
        True
    """
    if not poses:
        return np.array([0.0, 0.0, 1.0])
    mean = -np.mean([np.asarray(T, np.float64)[:3, 1] for T in poses], axis=0)
    norm = float(np.linalg.norm(mean))
    return mean / norm if norm > 1e-6 else np.array([0.0, 0.0, 1.0])


def floor_normal(normals: np.ndarray, guess: np.ndarray) -> np.ndarray | None:  # (3,) unit, or None
    """The horizontal surfaces' normal near ``guess`` (module docstring), signed like ``guess``; None when too few
    normals are near it.

    Args:
        normals: ``(N, 3)`` unit normals, sign arbitrary.
        guess: ``(3,)`` unit vector.
    """
    n = np.asarray(normals, np.float64)
    n = n[np.all(np.isfinite(n), axis=1)]
    lengths = np.linalg.norm(n, axis=1)
    n = n[lengths > 0.5] / lengths[lengths > 0.5, None]
    if len(n) == 0:
        return None
    axis = np.asarray(guess, np.float64)
    for cone in CONE_DEG:
        near = n[np.abs(n @ axis) >= np.cos(np.radians(cone))]
        if len(near) < MIN_SHARE * len(n) or len(near) < 3:
            return None
        _, vectors = np.linalg.eigh(near.T @ near)
        axis = vectors[:, -1]  # the direction the horizontal normals agree on
        if axis @ guess < 0:
            axis = -axis
    return axis / np.linalg.norm(axis)


def run_up(bundle_up: tuple[float, float, float] | None, poses: list[np.ndarray], normals: np.ndarray) -> UpDirection:
    """The bundle's up when it has one, else the floor's normal, else the cameras' mean up."""
    if bundle_up is not None:
        v = np.asarray(bundle_up, np.float64)
        return UpDirection(_triple(v / np.linalg.norm(v)), "bundle")
    guess = camera_up(poses)
    floor = floor_normal(normals, guess)
    if floor is None:
        return UpDirection(_triple(snap_to_axis(guess)), "cameras")
    return UpDirection(_triple(snap_to_axis(floor)), "floor")


def snap_to_axis(v: np.ndarray) -> np.ndarray:  # (3,) unit
    """``v`` (unit), or the signed world axis within ``SNAP_DEG`` of it.

    Example:
        >>> snap_to_axis(np.array([0.01, 0.0, 0.99995])).tolist()
        [0.0, 0.0, 1.0]
    """
    axis = int(np.argmax(np.abs(v)))
    if abs(v[axis]) < np.cos(np.radians(SNAP_DEG)):
        return v
    out = np.zeros(3)
    out[axis] = np.sign(v[axis])
    return out


def _triple(v: np.ndarray) -> tuple[float, float, float]:
    x, y, z = (round(float(c), 6) for c in v)
    return (x, y, z)
