"""A tile as a bundle: the scene's bundle seen through one tile's primitives and frames, copying no file.

Stages 1-8 run on a tile unchanged: they see a :class:`TileBundle`, a :class:`Bundle` whose ``frames`` are the
tile's frames (the bundle reads them one at a time from the scene's own files, feature maps memory-mapped as
always) and whose geometry and per-vertex ground truth are the tile's vertices, in the scene's order.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from panogs_core.io.bundle import Bundle
from panogs_core.tiling.plan import TilePlan, TileSpec
from panogs_core.types import Geometry, GroundTruth


@dataclass(frozen=True)
class TileBundle(Bundle):
    """A bundle restricted to one tile: ``point_index`` (ascending) of the scene's vertices, and its frames."""

    point_index: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64), compare=False)
    halo_box: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)

    def read_geometry(self) -> Geometry | None:
        """The tile's vertices, in the scene's order."""
        whole = super().read_geometry()
        if whole is None:
            return None
        idx = self.point_index
        return Geometry(
            points=whole.points[idx],
            colors=None if whole.colors is None else whole.colors[idx],
            normals=None if whole.normals is None else whole.normals[idx],
        )

    def read_ground_truth(self) -> GroundTruth | None:
        """Per-vertex ground truth of the tile's vertices; ground truth with its own points: those in the tile's
        rectangle (core and halo)."""
        whole = super().read_ground_truth()
        if whole is None:
            return None
        if whole.points is None:
            idx = self.point_index
            return GroundTruth(semantic=whole.semantic[idx], instance=whole.instance[idx])
        x0, x1, y0, y1 = self.halo_box
        p = whole.points
        keep = (p[:, 0] >= x0) & (p[:, 0] < x1) & (p[:, 1] >= y0) & (p[:, 1] < y1)
        return GroundTruth(semantic=whole.semantic[keep], instance=whole.instance[keep], points=p[keep])


def tile_bundle(bundle: Bundle, plan: TilePlan, tile: TileSpec, points: np.ndarray) -> tuple[TileBundle, np.ndarray]:
    """The bundle of ``tile`` and the mask of which of its primitives are its core.

    ``points`` are the scene's primitives (the geometry's vertices), the plan's input.
    """
    index, core = plan.members(tile, points)
    wanted = set(tile.frame_ids)
    frames = tuple(f for f in bundle.frames if f.id in wanted)
    base = {f.name: getattr(bundle, f.name) for f in dataclasses.fields(Bundle)}
    base.update(frames=frames, name=f"{bundle.name}/{tile.name}")
    return TileBundle(**base, point_index=index, halo_box=tile.halo_box), core
