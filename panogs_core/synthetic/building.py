"""A synthetic building: furnished rooms on a grid, joined by doorways, for the tiled runs (docs/synthetic.md,
"The building preset").

Rooms are drawn as the zoned presets draw one (``layout.build_zoned_layout``, of the ``large`` kind by default) on
a ``nx`` x ``ny`` grid: every room of a column has the same length, every room of a row the same width, and the
wall slabs of two neighbours stand back to back. Each pair of neighbours gets one doorway (1 m wide, 2.1 m high)
cut through both walls, where neither room has furniture in front of it when such a place exists; a wall with a
doorway is three boxes (either side and the lintel) of the one wall instance. Every room keeps its own camera walk
(its frames see their room and, through the doorways, a little of the next) plus two key frames per doorway and
side that look through it.

Instances: the stuff of every room first (floor, ceiling, four walls per room, room by room), then the objects,
room by room; each room's floor, ceiling and walls are instances of their own, as in a single room.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from panogs_core.io.bundle.writer import BundleWriter
from panogs_core.progress import ProgressFn
from panogs_core.synthetic.catalog import label_embeddings
from panogs_core.synthetic.coverage import ensure_coverage
from panogs_core.synthetic.features import make_feature_model, synthesize_features
from panogs_core.synthetic.frames import SurfacePoints, subset, write_frames, write_static
from panogs_core.synthetic.layout import NUM_STUFF, Layout, build_zoned_layout
from panogs_core.synthetic.placement import Boxes
from panogs_core.synthetic.presets import Difficulty, SyntheticSpec, get_difficulty, get_preset
from panogs_core.synthetic.render import Render, make_raycaster
from panogs_core.synthetic.sampling import sample_surfaces
from panogs_core.synthetic.scene import DEPTH_SCALE, spec_camera
from panogs_core.synthetic.trajectory import look_pose, make_trajectory, push_clear

DOOR_WIDTH = 1.0  # m
DOOR_HEIGHT = 2.1  # m
_DOOR_MARGIN = 0.5  # m, least wall left either side of a doorway
_DOOR_CLEAR = 0.8  # m, depth in front of a doorway that no furniture may reach into
_DOOR_CANDIDATES = 24  # places tried along a wall
_THROUGH_DISTANCE = 1.8  # m, how far from a doorway its through-the-door key frames stand
_WALL_X = (3, 5)  # wall boxes at x = Lx and x = 0 (their long side along y)
_WALL_Y = (4, 2)  # wall boxes at y = Ly and y = 0 (their long side along x)


@dataclass(frozen=True)
class _Doorway:
    """A doorway through the wall ``wall`` of room ``room`` (room-local), spanning ``[lo, hi]`` along the wall."""

    room: int
    wall: int
    lo: float
    hi: float


def make_building(
    out_dir: str | Path,
    *,
    rooms: tuple[int, int] = (2, 2),
    room: str | SyntheticSpec = "large",
    difficulty: str | Difficulty = "default",
    seed: int = 0,
    feature_space: str | None = None,
    with_geometry: bool = True,
    name: str | None = None,
    on_progress: ProgressFn | None = None,
) -> Path:
    """Generate a building of ``rooms`` (along x, along y) rooms of the preset ``room`` and write it as a bundle.

    Each room gets the room preset's frames and surface points; the same arguments give the same bundle.

    Raises:
        ConfigError: an unknown preset or difficulty, or a realistic room preset (``scan``: a studio of its own).
        ValueError: fewer than one room along a side.
    """
    spec = get_preset(room)
    if spec.realistic:
        from panogs_core.errors import ConfigError

        raise ConfigError(f"building: room preset {spec.name!r} is realistic; expected a zoned one (e.g. large)")
    nx, ny = rooms
    if nx < 1 or ny < 1:
        raise ValueError(f"building: expected at least 1 x 1 rooms, got {nx} x {ny}")
    level = get_difficulty(difficulty)
    space = feature_space or spec.feature_space
    embeddings = label_embeddings(space)
    shared, feature_seed, frame_seed, *room_seeds = np.random.SeedSequence(seed).spawn(3 + nx * ny)
    rng = np.random.default_rng(shared)
    lengths = rng.uniform(*spec.room_length, nx)
    widths = rng.uniform(*spec.room_width, ny)
    height = float(rng.uniform(*spec.room_height))
    layouts, surfaces, poses, offsets = [], [], [], []
    camera = spec_camera(spec)
    for r in range(nx * ny):
        i, j = r % nx, r // nx
        room_spec = dataclasses.replace(spec, room_length=(lengths[i],) * 2, room_width=(widths[j],) * 2,
                                        room_height=(height, height))  # fmt: skip
        layout_rng, points_rng, trajectory_rng = (np.random.default_rng(s) for s in room_seeds[r].spawn(3))
        layout = build_zoned_layout(room_spec, layout_rng)
        thickness = 2 * float(layout.boxes.half[2, 1])  # the wall slabs' thickness
        offsets.append(np.array([sum(lengths[:i]) + 2 * thickness * i, sum(widths[:j]) + 2 * thickness * j, 0.0]))
        layouts.append(layout)
        surfaces.append(sample_surfaces(layout, spec.num_points, points_rng))
        room_poses = make_trajectory(layout, spec.num_frames, level.trajectory, trajectory_rng)
        poses.append(ensure_coverage(make_raycaster(layout), layout, camera, room_poses,
                                     np.arange(0, spec.num_frames, spec.key_frame_stride)))  # fmt: skip
    doorways = _place_doorways(layouts, (nx, ny), rng)
    building, surface = _join(layouts, surfaces, offsets, doorways)
    all_poses = np.concatenate([_through_door_poses(layouts, doorways, offsets, p, r) for r, p in enumerate(poses)])
    scene_name = name or f"synthetic-building-{nx}x{ny}-{spec.name}-{level.name}-{seed}"
    writer = BundleWriter(out_dir, name=scene_name, camera=camera, depth_scale=DEPTH_SCALE,
                          feature_dim=embeddings.shape[1], feature_space=space)  # fmt: skip
    model = make_feature_model(embeddings, building.instance_class, level.features, np.random.default_rng(feature_seed))
    shape = (spec.height // spec.feature_stride, spec.width // spec.feature_stride)

    def features(instance: np.ndarray, view: Render, pose: np.ndarray, frame_rng: np.random.Generator) -> np.ndarray:
        return synthesize_features(model, instance, shape, frame_rng)

    seeds = frame_seed.spawn(len(all_poses))
    # Through-the-door frames are key frames whatever the stride: the frames' own stride applies to the walks.
    every = dataclasses.replace(spec, key_frame_stride=1)
    observed = write_frames(writer, make_raycaster(building), building, features, all_poses, every, level, seeds,
                            surface, on_progress)  # fmt: skip
    write_static(writer, subset(surface, observed), embeddings, with_geometry)
    return writer.close()


def _place_doorways(layouts: list[Layout], grid: tuple[int, int], rng: np.random.Generator) -> list[_Doorway]:
    """One doorway between every two neighbours, through both their walls (room-local coordinates)."""
    nx, ny = grid
    out = []
    for r in range(nx * ny):
        i, j = r % nx, r // nx
        if i + 1 < nx:  # the wall at x = Lx of r and the wall at x = 0 of its neighbour, along y
            lo = _free_span(layouts[r], layouts[r + 1], _WALL_X, float(layouts[r].room[1]), rng)
            out += [_Doorway(r, _WALL_X[0], lo, lo + DOOR_WIDTH), _Doorway(r + 1, _WALL_X[1], lo, lo + DOOR_WIDTH)]
        if j + 1 < ny:  # the wall at y = Ly of r and the wall at y = 0 of the room above, along x
            lo = _free_span(layouts[r], layouts[r + nx], _WALL_Y, float(layouts[r].room[0]), rng)
            out += [_Doorway(r, _WALL_Y[0], lo, lo + DOOR_WIDTH), _Doorway(r + nx, _WALL_Y[1], lo, lo + DOOR_WIDTH)]
    return out


def _free_span(a: Layout, b: Layout, walls: tuple[int, int], length: float, rng: np.random.Generator) -> float:
    """Where along the shared wall a doorway starts: the first of some random places with no furniture in front
    of it in either room, else the first place tried (the doorway is then half blocked, as happens)."""
    tries = rng.uniform(_DOOR_MARGIN, length - _DOOR_MARGIN - DOOR_WIDTH, _DOOR_CANDIDATES)
    for lo in tries:
        if not _blocked(a, walls[0], lo) and not _blocked(b, walls[1], lo):
            return float(lo)
    return float(tries[0])


def _blocked(layout: Layout, wall: int, lo: float) -> bool:
    """Whether an object's bounding box reaches into the doorway's clearance in front of ``wall``."""
    b = layout.boxes
    objects = np.arange(NUM_STUFF, len(b.yaw))
    c, s = np.abs(np.cos(b.yaw[objects])), np.abs(np.sin(b.yaw[objects]))
    reach = np.stack(
        [c * b.half[objects, 0] + s * b.half[objects, 1], s * b.half[objects, 0] + c * b.half[objects, 1]], 1
    )
    centre = b.centers[objects, :2]
    along, across = (1, 0) if wall in _WALL_X else (0, 1)
    plane = 0.0 if wall in (_WALL_X[1], _WALL_Y[1]) else float(layout.room[across])
    near = np.abs(centre[:, across] - plane) - reach[:, across] < _DOOR_CLEAR
    overlap = (centre[:, along] + reach[:, along] > lo) & (centre[:, along] - reach[:, along] < lo + DOOR_WIDTH)
    return bool(np.any(near & overlap))


def _join(
    layouts: list[Layout], surfaces: list[SurfacePoints], offsets: list[np.ndarray], doorways: list[_Doorway]
) -> tuple[Layout, SurfacePoints]:
    """The building's layout (walls with doorways cut into pieces) and surface points, in world coordinates."""
    rooms = len(layouts)
    objects_before = np.cumsum([0] + [len(lay.instance_class) - NUM_STUFF for lay in layouts])
    centres, halves, yaws, box_instance, box_color, classes_stuff, classes_obj, contacts = ([] for _ in range(8))
    points, normals, colors, semantic, instance, box = ([] for _ in range(6))
    families: list[str] = []
    first_box = 0
    for r, (lay, surf, off) in enumerate(zip(layouts, surfaces, offsets)):
        inst_map = np.concatenate([
            NUM_STUFF * r + np.arange(NUM_STUFF),
            NUM_STUFF * rooms + objects_before[r] + np.arange(len(lay.instance_class) - NUM_STUFF),
        ])  # fmt: skip
        piece_of_box: dict[int, list[tuple[int, np.ndarray, np.ndarray]]] = {}
        local_ids: list[int] = []
        for k in range(len(lay.boxes.yaw)):
            door = next((d for d in doorways if d.room == r and d.wall == k), None)
            pieces = [(lay.boxes.centers[k], lay.boxes.half[k])] if door is None else _wall_pieces(lay, door)
            ids = []
            for centre, half in pieces:
                ids.append(first_box + len(local_ids))
                local_ids.append(k)
                centres.append(centre + off)
                halves.append(half)
                yaws.append(lay.boxes.yaw[k])
                box_instance.append(inst_map[lay.box_instance[k]])
                box_color.append(lay.box_color[k])
            piece_of_box[k] = [(i, c, h) for i, (c, h) in zip(ids, pieces)]
        keep, new_box = _assign_pieces(surf, piece_of_box)
        first_box += len(local_ids)
        points.append(surf.points[keep] + off.astype(np.float32))
        normals.append(surf.normals[keep])
        colors.append(surf.colors[keep])
        semantic.append(surf.semantic[keep])
        instance.append(inst_map[surf.instance[keep]])
        box.append(new_box)
        classes_stuff.append(lay.instance_class[:NUM_STUFF])
        classes_obj.append(lay.instance_class[NUM_STUFF:])
        contacts.append(inst_map[lay.contacts] if lay.contacts.size else lay.contacts)
        families.extend(lay.families)
    extent = np.max(np.array(centres) + np.array(halves), axis=0)
    building = Layout(
        room=np.array([extent[0], extent[1], float(layouts[0].room[2])]),
        boxes=Boxes(np.array(centres), np.array(halves), np.array(yaws)),
        box_instance=np.array(box_instance, np.int64),
        box_color=np.array(box_color, np.float32),
        instance_class=np.concatenate(classes_stuff + classes_obj).astype(np.int64),
        contacts=np.concatenate(contacts).reshape(-1, 2).astype(np.int64),
        families=tuple(families),
        num_stuff=NUM_STUFF * rooms,
    )
    surface = SurfacePoints(
        points=np.concatenate(points), normals=np.concatenate(normals), colors=np.concatenate(colors),
        semantic=np.concatenate(semantic), instance=np.concatenate(instance), box=np.concatenate(box),
    )  # fmt: skip
    return building, surface


def _wall_pieces(layout: Layout, door: _Doorway) -> list[tuple[np.ndarray, np.ndarray]]:
    """A wall slab with a doorway: the slab either side of it (full height) and the lintel above it."""
    centre, half = layout.boxes.centers[door.wall], layout.boxes.half[door.wall]
    along = 1 if door.wall in _WALL_X else 0
    lo_end, hi_end = centre[along] - half[along], centre[along] + half[along]
    bottom, top = centre[2] - half[2], centre[2] + half[2]
    pieces = []
    for a, b, z0, z1 in ((lo_end, door.lo, bottom, top), (door.hi, hi_end, bottom, top),
                         (door.lo, door.hi, DOOR_HEIGHT, top)):  # fmt: skip
        c, h = centre.copy(), half.copy()
        c[along], h[along] = (a + b) / 2, (b - a) / 2
        c[2], h[2] = (z0 + z1) / 2, (z1 - z0) / 2
        pieces.append((c, h))
    return pieces


def _assign_pieces(
    surface: SurfacePoints, piece_of_box: dict[int, list[tuple[int, np.ndarray, np.ndarray]]]
) -> tuple[np.ndarray, np.ndarray]:  # (P,) bool kept, (P',) int64 building box of each kept point
    """Each surface point's building box: its own box, or for a wall with a doorway the piece it lies on; points in
    a doorway's opening are dropped."""
    new_box = np.full(surface.points.shape[0], -1, np.int64)
    for k, pieces in piece_of_box.items():
        on_box = surface.box == k
        if len(pieces) == 1:
            new_box[on_box] = pieces[0][0]
            continue
        thin = int(np.argmin(pieces[0][2]))  # the slab's thickness: its points lie on its face, outside it
        pts = surface.points[on_box].astype(np.float64)
        for index, centre, half in pieces:
            inside = np.ones(pts.shape[0], bool)
            for axis in (a for a in range(3) if a != thin):
                inside &= np.abs(pts[:, axis] - centre[axis]) <= half[axis] + 1e-9
            new_box[np.flatnonzero(on_box)[inside]] = index
    keep = new_box >= 0
    return keep, new_box[keep]


def _through_door_poses(
    layouts: list[Layout], doorways: list[_Doorway], offsets: list[np.ndarray], walk: np.ndarray, r: int
) -> np.ndarray:  # (V_r, 4, 4) world poses of room r: its walk, then one key frame per doorway of it
    """Room ``r``'s walk moved into the building, and a view through each of its doorways from inside it."""
    lay = layouts[r]
    extra = []
    for door in (d for d in doorways if d.room == r):
        along, across = (1, 0) if door.wall in _WALL_X else (0, 1)
        plane = 0.0 if door.wall in (_WALL_X[1], _WALL_Y[1]) else float(lay.room[across])
        inward = 1.0 if plane == 0.0 else -1.0
        spot = np.zeros(2)
        spot[along] = (door.lo + door.hi) / 2
        spot[across] = plane + inward * _THROUGH_DISTANCE
        spot = push_clear(spot[None], lay)[0]
        target = np.zeros(2)
        target[along], target[across] = (door.lo + door.hi) / 2, plane
        to_door = target - spot
        extra.append(look_pose(np.array([spot[0], spot[1], 1.4]), float(np.arctan2(to_door[1], to_door[0])),
                               np.deg2rad(-8.0)))  # fmt: skip
    poses = np.concatenate([walk, np.array(extra).reshape(-1, 4, 4)])
    poses[:, :3, 3] += offsets[r]
    return poses
