"""Procedural furnished rooms: a rectangular room split into zones, each furnished by a layout family.

Families: ``living`` (sofa, dining or coffee table with chairs, shelves, sideboards), ``bedroom`` (bed with
night stands, wardrobe, desk), ``office`` (desks with chairs and hutches, shelves, filing cabinets, meeting
table), ``kitchen`` (counter run with sinks, refrigerator and wall cabinets, dining table), ``bathroom``
(toilet, bathtub, vanity). Every room gets doors, windows (some with curtains) and pictures on its walls.
Objects never interpenetrate (oriented-box separating-axis tests on every part); some touch on purpose
(chairs pulled up under tables, sinks on counters, hutches on desks, night stands against beds, curtains
beside windows, runs of bookshelves, rows of chairs along a wall, benches of desks pushed together) and are
listed as contacts. Same-class objects that touch are where only the 2D masks separate instances.

Stuff instances come first: 0 floor, 1 ceiling, 2-5 the walls y = 0, x = Lx, y = Ly, x = 0 (one instance per
wall piece); things follow from 6.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass

import numpy as np

from panogs_core.synthetic import groups, shapes
from panogs_core.synthetic.catalog import CLASS_COLORS, CLASS_ID
from panogs_core.synthetic.placement import (
    Boxes,
    Group,
    inside_room,
    overlaps,
    to_world,
    wall_length,
    wall_pose,
    wall_span,
)
from panogs_core.synthetic.presets import SyntheticSpec

FAMILIES = ("living", "bedroom", "office", "kitchen", "bathroom")
_FAMILY_WEIGHTS = np.array([0.28, 0.22, 0.22, 0.2, 0.08])
_WALL_T = 0.2  # thickness of the wall / floor / ceiling slabs (only their inner faces are ever seen)
_TRIES = 60
_WALKWAY = 0.35  # free-standing groups keep this much floor free around them, metres
_STUFF = ("floor", "ceiling", "wall", "wall", "wall", "wall")
NUM_STUFF = len(_STUFF)
Zone = tuple[float, float]  # x extent of a furnished zone, metres


@dataclass(frozen=True)
class Layout:
    """A furnished room as oriented boxes.

    Attributes:
        room: ``(3,)`` room size ``(Lx, Ly, H)``; the room spans ``[0, Lx] x [0, Ly] x [0, H]``.
        boxes: ``B`` world boxes; the first ``NUM_STUFF`` are floor, ceiling and the four walls.
        box_instance: ``(B,)`` int64 instance id of each box.
        box_color: ``(B, 3)`` float32 albedo in [0, 1].
        instance_class: ``(I,)`` int64 catalogue class of each instance.
        contacts: ``(E, 2)`` int64 instance pairs that touch or nearly touch.
        families: Family of each zone, along x.
        annotated: ``(I,)`` bool, False for instances the ground truth leaves unannotated (clutter outside
            the label set, the ceiling of a realistic scene); None = every instance is annotated.
        num_stuff: The stuff instances come first, this many of them (six in a room).
    """

    room: np.ndarray
    boxes: Boxes
    box_instance: np.ndarray
    box_color: np.ndarray
    instance_class: np.ndarray
    contacts: np.ndarray
    families: tuple[str, ...]
    annotated: np.ndarray | None = None
    num_stuff: int = NUM_STUFF  # instances 0..num_stuff-1 are stuff (a building: six per room, building.py)

    @property
    def box_class(self) -> np.ndarray:  # (B,) int64
        """Catalogue class of each box."""
        return self.instance_class[self.box_instance]


class RoomBuilder:
    """Accumulates placed groups; refuses a placement that leaves the room or collides."""

    def __init__(self, room: np.ndarray, rng: np.random.Generator) -> None:
        self.room, self.rng = room, rng
        self.boxes = _no_boxes()  # objects only: slabs are not obstacles (objects stand against them)
        self.keepout = _no_boxes()
        self.box_instance: list[np.ndarray] = []
        self.box_color: list[np.ndarray] = []
        self.instance_class: list[int] = [CLASS_ID[c] for c in _STUFF]
        self.contacts: list[tuple[int, int]] = []

    def try_add(self, group: Group, poses: Iterator[np.ndarray], clearance: float, margin: float = 0.0) -> bool:
        """Place ``group`` at the first pose that fits; False if none does."""
        parts = group.parts()
        for pose in poses:
            world = to_world(parts, pose)
            if not inside_room(world, self.room, margin):
                continue
            if overlaps(world, self.boxes, clearance) or overlaps(world, self.keepout, clearance):
                continue
            keep = to_world(group.keepout, pose)
            if overlaps(keep, self.boxes, 0.0):
                continue
            self._commit(group, world, keep)
            return True
        return False

    def _commit(self, group: Group, world: Boxes, keep: Boxes) -> None:
        first = len(self.instance_class)
        ids = np.concatenate([np.full(len(m.parts), first + i) for i, m in enumerate(group.models)])
        shade = np.concatenate([m.parts[:, 6] for m in group.models])
        colours = [self.colour(m.cls) for m in group.models]
        self._append(world, ids, [np.clip(colours[i - first] * s, 0, 1) for i, s in zip(ids, shade)])
        self.instance_class += [CLASS_ID[m.cls] for m in group.models]
        self.contacts += [(first + i, first + j) for i, j in group.contacts]
        self.keepout = _concat(self.keepout, keep)

    def _append(self, world: Boxes, ids: list[int] | np.ndarray, colours: list[np.ndarray]) -> None:
        self.boxes = _concat(self.boxes, world)
        self.box_instance.append(np.asarray(ids, dtype=np.int64))
        self.box_color.append(np.asarray(colours, dtype=np.float32).reshape(-1, 3))

    def colour(self, cls: str) -> np.ndarray:
        """Class colour with a per-instance tint, so instances of one class differ a little."""
        tint = self.rng.uniform(0.85, 1.12, 3) * self.rng.uniform(0.9, 1.08)
        return np.clip(CLASS_COLORS[CLASS_ID[cls]] * tint, 0.02, 1.0)


def _no_boxes() -> Boxes:
    return Boxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))


def _concat(a: Boxes, b: Boxes) -> Boxes:
    return Boxes(np.concatenate([a.centers, b.centers]), np.concatenate([a.half, b.half]),
                 np.concatenate([a.yaw, b.yaw]))  # fmt: skip


# -- pose samplers --


def wall_poses(b: RoomBuilder, group: Group, zone: Zone, corner: bool) -> Iterator[np.ndarray]:
    """Random poses with the group's back on a wall of the zone (at a corner of the wall if ``corner``)."""
    bounds = group.bounds()
    half_w = (bounds[0, 1] - bounds[0, 0]) / 2
    spans = [(w, s) for w in range(4) if (s := wall_span(b.room, w, zone)) is not None]
    for _ in range(_TRIES):
        wall, (t0, t1) = spans[b.rng.integers(len(spans))]
        lo, hi = max(t0, 0.0) + half_w, min(t1, wall_length(b.room, wall)) - half_w
        if hi < lo:
            continue
        t = (lo if b.rng.random() < 0.5 else hi) if corner else b.rng.uniform(lo, hi)
        yield wall_pose(b.room, wall, t, bounds)


def free_poses(b: RoomBuilder, zone: Zone) -> Iterator[np.ndarray]:
    """Random poses inside the zone, axis-aligned give or take 15 degrees."""
    for _ in range(_TRIES):
        x = b.rng.uniform(zone[0] + 0.8, max(zone[1] - 0.8, zone[0] + 0.81))
        y = b.rng.uniform(0.8, b.room[1] - 0.8)
        yaw = b.rng.integers(4) * np.pi / 2 + np.deg2rad(b.rng.uniform(-15, 15))
        yield np.array([x, y, 0.0, yaw])


def place_on_wall(b: RoomBuilder, group: Group, zone: Zone, corner: bool = False) -> bool:
    """Place a group against a wall of the zone (2 cm from other objects); False if it does not fit."""
    return b.try_add(group, wall_poses(b, group, zone, corner), clearance=0.02)


def place_free(b: RoomBuilder, group: Group, zone: Zone) -> bool:
    """Place a group on the open floor of the zone, keeping a walkway around it; False if it does not fit."""
    return b.try_add(group, free_poses(b, zone), clearance=_WALKWAY, margin=0.3)


# -- families --


def _shelf(rng: np.random.Generator, room_height: float, count: int = 1) -> Group:
    """One bookshelf, or a run of ``count`` of one height and depth standing side by side."""
    h, d = min(rng.uniform(1.5, 2.1), room_height - 0.15), rng.uniform(0.28, 0.4)
    shelves = [groups.single(shapes.bookshelf(rng, rng.uniform(0.6, 1.0 if count > 1 else 1.2), d, h))
               for _ in range(count)]  # fmt: skip
    return shelves[0] if count == 1 else groups.side_by_side(shelves, rng)


def _run_on_wall(b: RoomBuilder, make: Callable[[int], Group], count: int, zone: Zone) -> None:
    """Place a run of ``count`` touching objects on a wall; if it does not fit, a shorter run, down to one."""
    for n in range(count, 0, -1):
        if place_on_wall(b, make(n), zone):
            return


def _chairs(rng: np.random.Generator, count: int) -> Group:
    """Chairs standing side by side along a wall (a waiting area, the spare chairs of a meeting room)."""
    return groups.side_by_side([groups.single(shapes.chair(rng)) for _ in range(count)], rng)


def _desks(rng: np.random.Generator, count: int) -> Group:
    """Desks pushed together into a bench, each with its chair (and maybe a hutch)."""
    return groups.side_by_side([groups.desk(rng, hutch=rng.random() < 0.5) for _ in range(count)], rng)


def _cabinet(rng: np.random.Generator, room_height: float, kind: str) -> Group:
    """A ``sideboard`` (low, maybe with a picture on it), ``filing`` cabinet or ``wardrobe`` (tall)."""
    if kind == "sideboard":
        return groups.sideboard(rng)
    if kind == "filing":
        w, d, h = rng.uniform(0.45, 0.9), rng.uniform(0.45, 0.6), rng.uniform(0.7, 1.3)
    else:
        w, d, h = (
            rng.uniform(0.8, 1.4),
            rng.uniform(0.55, 0.62),
            min(rng.uniform(1.8, 2.2), room_height - 0.1),
        )
    return groups.single(shapes.cabinet(rng, w, d, h))


def _fill_living(b: RoomBuilder, zone: Zone, rng: np.random.Generator) -> None:
    # Free-standing groups first: they need the most floor, wall furniture fits around them.
    if rng.random() < 0.7:
        place_free(b, groups.dining(rng), zone)
    place_free(b, groups.dining(rng, coffee=True), zone)
    for _ in range(rng.integers(1, 3)):
        place_on_wall(b, groups.single(shapes.sofa(rng)), zone)
    for _ in range(rng.integers(1, 3)):
        _run_on_wall(b, lambda n: _shelf(rng, b.room[2], n), int(rng.integers(1, 4)), zone)
    for _ in range(rng.integers(1, 3)):
        place_on_wall(b, _cabinet(rng, b.room[2], "sideboard"), zone)
    _run_on_wall(b, lambda n: _chairs(rng, n), int(rng.integers(0, 4)), zone)


def _fill_bedroom(b: RoomBuilder, zone: Zone, rng: np.random.Generator) -> None:
    place_on_wall(b, groups.bed(rng), zone)
    if rng.random() < 0.8:
        place_on_wall(b, _cabinet(rng, b.room[2], "wardrobe"), zone)
    if rng.random() < 0.7:
        place_on_wall(b, groups.desk(rng, hutch=rng.random() < 0.4), zone)
    if rng.random() < 0.6:
        place_on_wall(b, _shelf(rng, b.room[2]), zone)
    if rng.random() < 0.5:
        place_on_wall(b, _cabinet(rng, b.room[2], "sideboard"), zone)


def _fill_office(b: RoomBuilder, zone: Zone, rng: np.random.Generator) -> None:
    if rng.random() < 0.6:
        place_free(b, groups.dining(rng), zone)
    for _ in range(rng.integers(1, 3)):
        _run_on_wall(b, lambda n: _desks(rng, n), int(rng.integers(1, 4)), zone)
    for _ in range(rng.integers(1, 3)):
        _run_on_wall(b, lambda n: _shelf(rng, b.room[2], n), int(rng.integers(1, 4)), zone)
    _run_on_wall(b, lambda n: _chairs(rng, n), int(rng.integers(0, 3)), zone)
    for _ in range(rng.integers(1, 3)):
        place_on_wall(b, _cabinet(rng, b.room[2], "filing"), zone)


def _fill_kitchen(b: RoomBuilder, zone: Zone, rng: np.random.Generator) -> None:
    place_free(b, groups.dining(rng), zone)
    place_on_wall(b, groups.kitchen(rng, b.room[2]), zone)
    if rng.random() < 0.6:
        place_on_wall(b, _cabinet(rng, b.room[2], "filing"), zone)
    if rng.random() < 0.4:
        place_on_wall(b, _shelf(rng, b.room[2]), zone)


def _fill_bathroom(b: RoomBuilder, zone: Zone, rng: np.random.Generator) -> None:
    if rng.random() < 0.8:
        place_on_wall(b, groups.single(shapes.bathtub(rng)), zone, corner=True)
    place_on_wall(b, groups.single(shapes.toilet(rng)), zone)
    place_on_wall(b, groups.vanity(rng), zone)
    if rng.random() < 0.6:
        place_on_wall(b, _cabinet(rng, b.room[2], "filing"), zone)


def _fill_extra(b: RoomBuilder, zone: Zone, rng: np.random.Generator) -> None:
    """More generic furniture for big zones (one item per ~8 m2 of floor beyond the first 12 m2)."""
    area = (zone[1] - zone[0]) * b.room[1]
    for _ in range(int(max(area - 12.0, 0.0) / 8.0)):
        pick = rng.integers(5)
        if pick == 0:
            place_free(b, groups.dining(rng, coffee=rng.random() < 0.3), zone)
        elif pick == 1:
            place_on_wall(b, _shelf(rng, b.room[2]), zone)
        elif pick == 2:
            place_on_wall(b, _cabinet(rng, b.room[2], str(rng.choice(["sideboard", "filing", "wardrobe"]))), zone)
        elif pick == 3:
            place_on_wall(b, groups.single(shapes.sofa(rng)), zone)
        else:
            place_on_wall(b, groups.desk(rng, hutch=rng.random() < 0.5), zone)


_FILLERS: dict[str, Callable[[RoomBuilder, Zone, np.random.Generator], None]] = {
    "living": _fill_living, "bedroom": _fill_bedroom, "office": _fill_office, "kitchen": _fill_kitchen,
    "bathroom": _fill_bathroom,
}  # fmt: skip


# -- the room --


def build_zoned_layout(spec: SyntheticSpec, rng: np.random.Generator) -> Layout:
    """Draw a furnished room of zones, one room family each (the non-realistic presets).

    Args:
        spec: Room size ranges and zone length.
        rng: Source of every random choice (the layout is a pure function of its state).

    Returns:
        The room as boxes with instance and class ids, colours and contacts.
    """
    room = np.array([rng.uniform(*spec.room_length), rng.uniform(*spec.room_width),
                     rng.uniform(*spec.room_height)])  # fmt: skip
    n_zones = max(1, round(room[0] / spec.zone_length))
    edges = np.linspace(0.0, room[0], n_zones + 1)
    zones = [(float(edges[i]), float(edges[i + 1])) for i in range(n_zones)]
    families = tuple(str(f) for f in rng.choice(FAMILIES, n_zones, replace=False, p=_FAMILY_WEIGHTS))
    b = RoomBuilder(room, rng)
    for _ in range(1 + (n_zones > 1)):
        place_on_wall(b, groups.door(rng), (0.0, float(room[0])))
    for zone in zones:
        for _ in range(rng.integers(1, 3)):
            place_on_wall(b, groups.window(rng, room[2]), zone)
    for zone, family in zip(zones, families):
        _FILLERS[family](b, zone, rng)
        _fill_extra(b, zone, rng)
    for zone in zones:
        for _ in range(rng.integers(1, 4)):
            place_on_wall(b, groups.single(shapes.picture(rng)), zone)
    return finish_layout(b, families)


def finish_layout(b: RoomBuilder, families: tuple[str, ...]) -> Layout:
    """Prepend the floor, ceiling and wall slabs to the placed objects."""
    lx, ly, h = b.room
    t = _WALL_T
    centres = np.array(
        [
            [lx / 2, ly / 2, -t / 2],
            [lx / 2, ly / 2, h + t / 2],
            [lx / 2, -t / 2, h / 2],
            [lx + t / 2, ly / 2, h / 2],
            [lx / 2, ly + t / 2, h / 2],
            [-t / 2, ly / 2, h / 2],
        ]
    )
    half = np.array([[lx / 2 + t, ly / 2 + t, t / 2], [lx / 2 + t, ly / 2 + t, t / 2],
                     [lx / 2 + t, t / 2, h / 2 + t], [t / 2, ly / 2 + t, h / 2 + t],
                     [lx / 2 + t, t / 2, h / 2 + t], [t / 2, ly / 2 + t, h / 2 + t]])  # fmt: skip
    wall_colour = b.colour("wall")
    colours = [b.colour("floor"), b.colour("ceiling")] + [
        np.clip(wall_colour * b.rng.uniform(0.95, 1.05), 0, 1) for _ in range(4)
    ]
    boxes = _concat(Boxes(centres, half, np.zeros(NUM_STUFF)), b.boxes)
    box_instance = np.concatenate([np.arange(NUM_STUFF), *b.box_instance]).astype(np.int64)
    box_color = np.concatenate([np.asarray(colours, dtype=np.float32), *b.box_color]).astype(np.float32)
    contacts = np.array(b.contacts, dtype=np.int64).reshape(-1, 2)
    return Layout(room=b.room.copy(), boxes=boxes, box_instance=box_instance, box_color=box_color,
                  instance_class=np.array(b.instance_class, dtype=np.int64), contacts=contacts,
                  families=families)  # fmt: skip
