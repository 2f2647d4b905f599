"""A furnished studio like a scanned apartment (realistic specs, preset ``scan``; docs/synthetic.md).

A ``bathroom`` room (``SyntheticSpec.room_kind``) is one small zone instead: a door, a high window, a bathtub with
a shower curtain, a toilet, a vanity with a mirror cabinet above and a second sink, a linen cabinet, a shelf and a
hamper cabinet, as many as fit, with towels and bottles as clutter.

The room is cut along its long side into three zones in random order: ``service`` (a kitchen run of base
cabinets under a counter top with a sink on it, wall cabinets above and a refrigerator at its end; a toilet and
a vanity cabinet with a sink), ``living`` (a sofa pulled a little off the wall with a coffee table in front, a
dining table, a TV stand, a low shelf) and ``sleeping`` (a bed with night stands, a wardrobe, a desk). Every
room gets one or two doors and one or two windows hung with wide floor-length curtains.

Unlike the other presets the room holds much that is outside the label set, as a real capture does: boxes,
bins, bags, lamps, pillows, a TV and posters stand on the floor, the furniture tops and the walls. They are in
the geometry and in the images (their masks are like any object's) but their ground truth is unannotated (-1),
as is the ceiling (ScanNet's 20 classes have none). The resulting class shares are long-tailed: wall, floor,
cabinets (several instances), curtains and the sofa are big; counter, sink, toilet and window are small.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import replace

import numpy as np

from panogs_core.synthetic import groups, shapes
from panogs_core.synthetic.catalog import CLASS_ID
from panogs_core.synthetic.layout import (
    Layout,
    RoomBuilder,
    Zone,
    finish_layout,
    free_poses,
    place_free,
    place_on_wall,
    wall_poses,
)
from panogs_core.synthetic.placement import Group
from panogs_core.synthetic.presets import SyntheticSpec
from panogs_core.synthetic.shapes import Model

_ZONES = ("service", "living", "sleeping")
_CEILING = 1  # instance id of the ceiling (layout.py: 0 floor, 1 ceiling, 2-5 walls)
# Classes whose text embedding a clutter object's feature leans to (a box looks like a cabinet to a 2D model,
# a TV like a picture ...); the feature model adds a random direction on top (features.py).
_CLUTTER_LOOKS = ("cabinet", "table", "chair", "picture", "bookshelf", "sofa", "door", "sink", "bed", "window")
_SUPPORT_TOP = (0.3, 2.3)  # heights of furniture tops that get clutter on them, metres
_SUPPORT_AREA = 0.06  # smallest top (m2) that gets clutter


class _ScanBuilder(RoomBuilder):
    """The layout builder, also keeping track of the unannotated (clutter) instances."""

    def __init__(self, room: np.ndarray, rng: np.random.Generator) -> None:
        super().__init__(room, rng)
        self.unannotated: set[int] = {_CEILING}

    def add_clutter(self, group: Group, poses: Iterator[np.ndarray], clearance: float) -> bool:
        """Place a group of clutter (unannotated, with colours of no class); False if it does not fit."""
        first = len(self.instance_class)
        if not self.try_add(group, poses, clearance):
            return False
        self.unannotated.update(range(first, len(self.instance_class)))
        self.box_color[-1] = self.rng.uniform(0.08, 0.95, self.box_color[-1].shape).astype(np.float32)
        return True


def _off_wall(poses: Iterator[np.ndarray], gap: float) -> Iterator[np.ndarray]:
    """Wall poses moved ``gap`` metres into the room (a sofa not pushed fully back)."""
    for pose in poses:
        yaw = pose[3]
        yield pose + np.array([-np.sin(yaw) * gap, np.cos(yaw) * gap, 0.0, 0.0])


# -- models --


def _basin(rng: np.random.Generator) -> Model:
    """An open sink basin (bottom, four low rims) and a faucet at the back; back at y = 0, bottom at z = 0."""
    w, d, h, t = rng.uniform(0.42, 0.6), rng.uniform(0.36, 0.45), rng.uniform(0.05, 0.08), 0.03
    parts = [
        [-w / 2, w / 2, 0.06, d, 0.0, 0.015, 0.9],
        [-w / 2, w / 2, 0.06, 0.06 + t, 0.015, h, 1.0],
        [-w / 2, w / 2, d - t, d, 0.015, h, 1.0],
        [-w / 2, -w / 2 + t, 0.06 + t, d - t, 0.015, h, 1.0],
        [w / 2 - t, w / 2, 0.06 + t, d - t, 0.015, h, 1.0],
        [-0.02, 0.02, 0.0, 0.06, 0.0, 0.22, 0.7],
    ]
    return Model("sink", np.array(parts))


def _window(rng: np.random.Generator, room_height: float) -> tuple[Model, float]:
    """Two glass panes and a mullion flush with the wall (back at y = 0), and its width."""
    w = rng.uniform(1.0, 1.8)
    z0 = rng.uniform(0.75, 0.95)
    z1 = min(z0 + rng.uniform(1.2, 1.5), room_height - 0.25)
    parts = [
        [-w / 2, -0.02, 0.0, 0.02, z0, z1, 1.0],
        [0.02, w / 2, 0.0, 0.02, z0, z1, 1.0],
        [-0.02, 0.02, 0.0, 0.04, z0, z1, 0.6],
    ]
    return Model("window", np.array(parts)), w


def _high_window(rng: np.random.Generator, room_height: float) -> Group:
    """A thin window strip flush with the wall, set high (1.5-2.1 m): a thin object in a wall above most key views
    (the camera at 1.45 m looks down), glimpsed by some dense poses."""
    w = rng.uniform(0.9, 1.6)
    z0 = rng.uniform(1.5, 1.65)
    z1 = min(z0 + rng.uniform(0.3, 0.45), room_height - 0.1)
    return groups.single(Model("window", np.array([[-w / 2, w / 2, 0.0, 0.02, z0, z1, 1.0]])))


def _lamp(rng: np.random.Generator) -> Model:
    """A floor lamp: base, pole and shade (clutter)."""
    h = rng.uniform(1.2, 1.6)
    return Model(
        "chair",
        np.array([
            [-0.15, 0.15, 0.0, 0.3, 0.0, 0.04, 0.8],
            [-0.02, 0.02, 0.13, 0.17, 0.04, h, 0.6],
            [-0.18, 0.18, -0.03, 0.33, h, h + 0.25, 1.2],
        ]),
    )  # fmt: skip


def _fronted(w: float, d: float, h: float, doors: int) -> Model:
    """A cabinet body with ``doors`` door panels on its front (back at y = 0, on the floor)."""
    parts = [[-w / 2, w / 2, 0.0, d - 0.02, 0.0, h, 1.0]]
    edges = np.linspace(-w / 2, w / 2, doors + 1)
    parts += [[edges[i] + 0.01, edges[i + 1] - 0.01, d - 0.02, d, 0.03, h - 0.03, 1.12] for i in range(doors)]
    return Model("cabinet", np.array(parts))


# -- groups --


def _curtained_window(rng: np.random.Generator, room_height: float, curtains: bool) -> Group:
    """A window, with a wide floor-length curtain on each side overlapping its edges if ``curtains``."""
    pane, w = _window(rng, room_height)
    models, contacts = [pane], []
    if curtains:
        top, bottom = room_height - rng.uniform(0.03, 0.1), rng.uniform(0.02, 0.06)
        for sign in (-1.0, 1.0):
            cw = rng.uniform(0.7, 1.2)
            inner = w / 2 - rng.uniform(0.1, 0.3)  # the curtain hangs over the window's edge
            x0, x1 = (inner, inner + cw) if sign > 0 else (-inner - cw, -inner)
            models.append(Model("curtain", np.array([[x0, x1, 0.06, 0.12, bottom, top, 1.0]])))
            contacts.append((0, len(models) - 1))
    return Group(models, contacts)


def _kitchen_run(rng: np.random.Generator, room_height: float, n_base: int) -> Group:
    """Base cabinets under one counter top with a sink on it, wall cabinets above, maybe a refrigerator."""
    h, d = rng.uniform(0.86, 0.92), rng.uniform(0.58, 0.64)
    length = n_base * rng.uniform(0.6, 0.8)
    # one cabinet instance for the whole run of doors, as real annotations label a kitchen's base cabinets
    models = [_fronted(length, d - 0.02, h - 0.04, n_base * 2)]
    contacts = []
    top = len(models)
    models.append(Model("counter", np.array([[-length / 2, length / 2, 0.0, d + 0.02, h - 0.04, h, 1.1]])))
    contacts.append((0, top))
    models.append(_basin(rng).moved(dx=rng.uniform(-0.25, 0.25) * length, dy=0.04, dz=h))
    contacts.append((top, len(models) - 1))
    first = len(models)
    models += groups._wall_cabinets(rng, length, 0.0, room_height)
    contacts += [(k - 1, k) for k in range(first + 1, len(models))]
    if rng.random() < 0.9:
        fridge = shapes.refrigerator(rng, room_height)
        fw = fridge.bounds[0, 1] - fridge.bounds[0, 0]
        side = 1 if rng.random() < 0.5 else -1
        models.append(fridge.moved(dx=side * (length / 2 + rng.uniform(0.0, 0.02) + fw / 2), dy=-fridge.bounds[1, 0]))
        contacts.append((0, len(models) - 1))
    return Group(models, contacts)


def _vanity(rng: np.random.Generator) -> Group:
    """A bathroom cabinet with a sink on it."""
    w, d, h = rng.uniform(0.6, 0.9), rng.uniform(0.42, 0.5), rng.uniform(0.78, 0.86)
    body = shapes.cabinet(rng, w, d, h).moved(dy=d / 2)
    return Group([body, _basin(rng).moved(dy=0.02, dz=h)], [(0, 1)])


def _sectional(rng: np.random.Generator) -> Model:
    """A corner sofa: a sofa with a chaise (a seat block reaching forward) at one end (its last part)."""
    sofa = shapes.sofa(rng)
    (x0, x1), (_, y1), seat = sofa.bounds[0], sofa.bounds[1], sofa.parts[0, 5]
    w, reach = rng.uniform(0.75, 0.9), rng.uniform(0.6, 0.9)
    left = rng.random() < 0.5
    chaise = [x0, x0 + w, y1, y1 + reach, 0.0, seat, 1.0] if left else [x1 - w, x1, y1, y1 + reach, 0.0, seat, 1.0]
    return Model("sofa", np.vstack([sofa.parts, chaise]))


def _sofa_corner(rng: np.random.Generator) -> Group:
    """A corner sofa with a coffee table 0.35-0.5 m in front of the seats beside the chaise."""
    sofa = _sectional(rng)
    x0, x1 = sofa.bounds[0]
    chaise = sofa.parts[-1]
    free = (chaise[1], x1) if chaise[0] <= x0 else (x0, chaise[0])  # the seats not in front of the chaise
    width = min(rng.uniform(0.8, 1.2), free[1] - free[0] - 0.1)
    if width < 0.5:  # a short sofa: no room for a table beside the chaise
        return Group([sofa])
    table = shapes.table(rng, width, rng.uniform(0.5, 0.7), rng.uniform(0.4, 0.46))
    front = chaise[2]  # the sofa's front, where the chaise starts
    table = table.moved(dx=(free[0] + free[1]) / 2, dy=front + rng.uniform(0.35, 0.5) - table.bounds[1, 0])
    return Group([sofa, table])


def _armchair(rng: np.random.Generator) -> Model:
    """A short sofa (one or two seats)."""
    sofa = shapes.sofa(rng)
    scale = rng.uniform(1.0, 1.4) / (sofa.bounds[0, 1] - sofa.bounds[0, 0])
    parts = sofa.parts.copy()
    parts[:, 0:2] *= scale  # narrower: the arms get thinner with it, which a box model does not mind
    return Model("sofa", parts)


def _tv_stand(rng: np.random.Generator) -> Group:
    """A low wide cabinet (its back at y = 0)."""
    w, d, h = rng.uniform(1.2, 1.8), rng.uniform(0.4, 0.5), rng.uniform(0.45, 0.6)
    return Group([shapes.cabinet(rng, w, d, h).moved(dy=d / 2)])


def _wardrobe(rng: np.random.Generator, room_height: float) -> Group:
    """A tall cabinet with two to four doors."""
    w, d = rng.uniform(1.3, 2.0), rng.uniform(0.55, 0.62)
    return Group([_fronted(w, d, min(rng.uniform(1.9, 2.2), room_height - 0.15), 2 + int(w > 1.6) * 2)])


def _pantry(rng: np.random.Generator, room_height: float) -> Group:
    """A tall narrow kitchen cabinet."""
    w, d = rng.uniform(0.6, 0.9), rng.uniform(0.55, 0.62)
    return Group([_fronted(w, d, min(2.1, room_height - 0.2), 2)])


def _storage(rng: np.random.Generator) -> Group:
    """A chest-high two-door cabinet."""
    w, d, h = rng.uniform(0.8, 1.2), rng.uniform(0.35, 0.45), rng.uniform(0.9, 1.3)
    return Group([_fronted(w, d, h, 2)])


def _desk(rng: np.random.Generator) -> Model:
    """A desk, wider than the other presets' (a work table against the wall)."""
    w, d, h = rng.uniform(1.4, 1.9), rng.uniform(0.65, 0.8), rng.uniform(0.72, 0.76)
    dw = rng.uniform(0.4, 0.5)
    parts = [
        [-w / 2, w / 2, -d / 2, d / 2, h - 0.04, h, 1.0],
        [-w / 2, -w / 2 + 0.04, -d / 2, d / 2 - 0.02, 0.0, h - 0.04, 0.85],
        [w / 2 - dw, w / 2, -d / 2, d / 2 - 0.02, 0.0, h - 0.04, 0.9],
    ]
    return Model("desk", np.array(parts))


# -- zones --


def _retry(b: _ScanBuilder, make: Callable[[], Group], zone: Zone, tries: int = 3, corner: bool = False) -> bool:
    """Place a freshly drawn ``make()`` on a wall of the zone, up to ``tries`` draws (the room's key objects)."""
    return any(place_on_wall(b, make(), zone, corner) for _ in range(tries))


def _fill_service(b: _ScanBuilder, zone: Zone, rng: np.random.Generator) -> None:
    for n in (3, 2, 1):  # the longest run that fits
        if place_on_wall(b, _kitchen_run(rng, b.room[2], n), zone):
            break
    _retry(b, lambda: groups.single(shapes.toilet(rng)), zone, corner=True)
    _retry(b, lambda: _vanity(rng), zone)
    place_on_wall(b, _pantry(rng, b.room[2]), zone)
    place_free(b, groups.single(shapes.table(rng, rng.uniform(1.2, 1.6), rng.uniform(0.7, 0.9))), zone)


def _fill_living(b: _ScanBuilder, zone: Zone, rng: np.random.Generator) -> None:
    for sofa in (_sofa_corner(rng), groups.single(_sectional(rng))):  # without its coffee table if need be
        if b.try_add(sofa, _off_wall(wall_poses(b, sofa, zone, False), rng.uniform(0.05, 0.25)), clearance=0.02):
            break
    place_free(b, groups.single(shapes.table(rng, rng.uniform(1.6, 2.0), rng.uniform(0.9, 1.05))), zone)
    place_on_wall(b, groups.single(_armchair(rng)), zone)
    place_on_wall(b, _tv_stand(rng), zone)
    place_on_wall(b, groups.single(shapes.bookshelf(rng, rng.uniform(0.5, 0.7), rng.uniform(0.28, 0.35), 0.8)), zone)
    place_on_wall(b, _storage(rng), zone)


def _fill_sleeping(b: _ScanBuilder, zone: Zone, rng: np.random.Generator) -> None:
    _retry(b, lambda: groups.bed(rng), zone)
    _retry(b, lambda: groups.single(_desk(rng)), zone)
    place_on_wall(b, _wardrobe(rng, b.room[2]), zone)
    place_on_wall(b, groups.single(shapes.table(rng, rng.uniform(0.5, 0.8), rng.uniform(0.45, 0.6))), zone)


_FILLERS = {"service": _fill_service, "living": _fill_living, "sleeping": _fill_sleeping}


def _bath(rng: np.random.Generator) -> Group:
    """A bathtub (its long side on the wall) with a shower curtain drawn back to one end of its front."""
    tub = shapes.bathtub(rng)
    (x0, x1), (_, y1), (_, z1) = tub.bounds
    reach = rng.uniform(0.35, 0.6)
    x = (x0, x0 + reach) if rng.random() < 0.5 else (x1 - reach, x1)
    curtain = Model("curtain", np.array([[x[0], x[1], y1 - 0.04, y1 - 0.02, z1 + 0.1, rng.uniform(1.85, 2.0), 1.0]]))
    return Group([tub, curtain], [(0, 1)])


def _mirrored_vanity(rng: np.random.Generator, room_height: float) -> Group:
    """A vanity (cabinet and sink) with a shallow mirror cabinet on the wall above it."""
    vanity = _vanity(rng)
    w = vanity.models[0].bounds[0, 1] - vanity.models[0].bounds[0, 0]
    z0 = rng.uniform(1.35, 1.5)
    mirror = shapes.cabinet(rng, w * rng.uniform(0.7, 1.0), 0.14, min(rng.uniform(0.5, 0.7), room_height - 0.1 - z0))
    return Group([*vanity.models, mirror.moved(dy=0.07, dz=z0)], [*vanity.contacts])


def _fill_bathroom(b: _ScanBuilder, rng: np.random.Generator) -> None:
    """A bathroom's fixtures and furniture, each on a wall: a crowded room whose objects few key frames see."""
    whole, height = (0.0, float(b.room[0])), float(b.room[2])
    place_on_wall(b, groups.door(rng), whole)
    place_on_wall(b, _high_window(rng, height), whole)
    _retry(b, lambda: _bath(rng), whole, corner=True)
    _retry(b, lambda: groups.single(shapes.toilet(rng)), whole, corner=True)
    _retry(b, lambda: _mirrored_vanity(rng, height), whole)
    _retry(b, lambda: groups.vanity(rng), whole)  # a second sink: on a short counter, or a pedestal
    place_on_wall(b, _pantry(rng, height) if rng.random() < 0.5 else _storage(rng), whole)  # linen cabinet
    shelf = shapes.bookshelf(rng, rng.uniform(0.45, 0.7), rng.uniform(0.25, 0.32), rng.uniform(1.1, 1.7))
    place_on_wall(b, groups.single(shelf), whole)
    hamper = shapes.cabinet(rng, rng.uniform(0.35, 0.5), rng.uniform(0.3, 0.4), rng.uniform(0.5, 0.75))
    place_on_wall(b, groups.single(hamper.moved(dy=-hamper.bounds[1, 0])), whole)


# -- clutter --


def _clutter_box(rng: np.random.Generator, w: float, d: float, h: float) -> Group:
    """One box of clutter, centred (x and y), bottom at z = 0."""
    look = str(rng.choice(_CLUTTER_LOOKS))
    return Group([Model(look, np.array([[-w / 2, w / 2, -d / 2, d / 2, 0.0, h, 1.0]]))])


def _on_top(b: _ScanBuilder, support: int, group: Group) -> Iterator[np.ndarray]:
    """Random poses of a group standing on the top face of box ``support``, within its outline."""
    centre, half, yaw = b.boxes.centers[support], b.boxes.half[support], b.boxes.yaw[support]
    (x0, x1), (y0, y1) = group.bounds()[0], group.bounds()[1]
    room_x, room_y = max(half[0] - (x1 - x0) / 2, 0.0), max(half[1] - (y1 - y0) / 2, 0.0)
    c, s = np.cos(yaw), np.sin(yaw)
    for _ in range(8):
        u, v = b.rng.uniform(-room_x, room_x), b.rng.uniform(-room_y, room_y)
        yield np.array([centre[0] + c * u - s * v, centre[1] + s * u + c * v, centre[2] + half[2], yaw])


def _surface_clutter(b: _ScanBuilder, count: int) -> None:
    """Up to ``count`` boxes on furniture tops (tables, counter, desk, beds, cabinets), area-weighted."""
    boxes, rng = b.boxes, b.rng
    top = boxes.centers[:, 2] + boxes.half[:, 2]
    area = 4 * boxes.half[:, 0] * boxes.half[:, 1]
    instance = np.concatenate(b.box_instance)
    ok = (top > _SUPPORT_TOP[0]) & (top < _SUPPORT_TOP[1]) & (area > _SUPPORT_AREA)
    ok &= boxes.half[:, :2].min(axis=1) > 0.075  # not a headboard or a curtain: too thin to hold anything
    ok &= ~np.isin(instance, list(b.unannotated))
    support = np.flatnonzero(ok)
    if not len(support):
        return
    for _ in range(count):
        k = int(rng.choice(support, p=area[support] / area[support].sum()))
        w = rng.uniform(0.08, min(0.45, 2 * boxes.half[k, 0]))
        d = rng.uniform(0.08, min(0.4, 2 * boxes.half[k, 1]))
        group = _clutter_box(rng, w, d, rng.uniform(0.04, 0.35))
        b.add_clutter(group, _on_top(b, k, group), clearance=0.0)


def _floor_clutter(b: _ScanBuilder, count: int) -> None:
    """Up to ``count`` bins, bags, boxes and lamps on the floor, against the walls or in the open."""
    rng, whole = b.rng, (0.0, float(b.room[0]))
    for _ in range(count):
        pick = rng.random()
        if pick < 0.2:
            group = Group([_lamp(rng)])
        else:
            group = _clutter_box(rng, rng.uniform(0.2, 0.6), rng.uniform(0.2, 0.6), rng.uniform(0.15, 0.8))
        if pick < 0.75:
            b.add_clutter(group, wall_poses(b, group, whole, False), clearance=0.02)
        else:
            b.add_clutter(group, free_poses(b, whole), clearance=0.1)


def _wall_clutter(b: _ScanBuilder, count: int) -> None:
    """Posters and framed pictures (pictures are outside the real capture's label set)."""
    whole = (0.0, float(b.room[0]))
    for _ in range(count):
        group = groups.single(shapes.picture(b.rng))
        b.add_clutter(group, wall_poses(b, group, whole, False), clearance=0.02)


def _tv(b: _ScanBuilder) -> None:
    """A TV standing on the TV stand (the widest low cabinet), if there is one."""
    boxes = b.boxes
    top = boxes.centers[:, 2] + boxes.half[:, 2]
    cabinet = np.array(b.instance_class)[np.concatenate(b.box_instance)] == CLASS_ID["cabinet"]
    low = np.flatnonzero(cabinet & (top > 0.4) & (top < 0.65) & (boxes.half[:, 0] > 0.55))
    if not len(low):
        return
    k = int(low[np.argmax(boxes.half[low, 0])])
    w = min(2 * boxes.half[k, 0] - 0.1, b.rng.uniform(0.9, 1.3))
    tv = Group([Model("picture", np.array([[-w / 2, w / 2, -0.04, 0.04, 0.0, w * 0.58, 1.0]]))])
    b.add_clutter(tv, _on_top(b, k, tv), clearance=0.0)


# -- the room --


def build_scan_layout(spec: SyntheticSpec, rng: np.random.Generator) -> Layout:
    """Draw a furnished studio with clutter (module docstring).

    Args:
        spec: Room size ranges.
        rng: Source of every random choice.

    Returns:
        The room; ``annotated`` is False for the clutter and the ceiling.
    """
    room = np.array([rng.uniform(*spec.room_length), rng.uniform(*spec.room_width),
                     rng.uniform(*spec.room_height)])  # fmt: skip
    if spec.room_kind == "bathroom":
        return _bathroom_layout(room, rng)
    edges = np.linspace(0.0, room[0], len(_ZONES) + 1)
    zones = [(float(edges[i]), float(edges[i + 1])) for i in range(len(_ZONES))]
    families = _ZONES if rng.random() < 0.5 else _ZONES[::-1]  # the kitchen at one end: it needs the end wall
    b = _ScanBuilder(room, rng)
    whole = (0.0, float(room[0]))
    for _ in range(1 + int(rng.random() < 0.3)):
        place_on_wall(b, groups.door(rng), whole)
    for curtains in (True, rng.random() < 0.7):
        place_on_wall(b, _curtained_window(rng, room[2], curtains), whole)
    for zone, family in zip(zones, families):
        _FILLERS[family](b, zone, rng)
    _tv(b)
    _surface_clutter(b, int(rng.integers(30, 40)))
    _floor_clutter(b, int(rng.integers(18, 26)))
    _wall_clutter(b, int(rng.integers(1, 4)))
    for _ in range(spec.high_windows):  # no draw when there are none: the other rooms stay as they were
        place_on_wall(b, _high_window(rng, float(room[2])), whole)
    layout = finish_layout(b, families)
    annotated = np.ones(len(layout.instance_class), dtype=bool)
    annotated[sorted(b.unannotated)] = False
    return replace(layout, annotated=annotated)


def _bathroom_layout(room: np.ndarray, rng: np.random.Generator) -> Layout:
    """A bathroom (``_fill_bathroom``) with towels, bottles and bins as unannotated clutter."""
    b = _ScanBuilder(room, rng)
    _fill_bathroom(b, rng)
    _surface_clutter(b, int(rng.integers(8, 13)))
    _floor_clutter(b, int(rng.integers(2, 5)))
    _wall_clutter(b, int(rng.integers(0, 2)))
    layout = finish_layout(b, ("bathroom",))
    annotated = np.ones(len(layout.instance_class), dtype=bool)
    annotated[sorted(b.unannotated)] = False
    return replace(layout, annotated=annotated)
