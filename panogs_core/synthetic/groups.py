"""Furniture groups: objects that are placed together and touch by design (group-local frames, front +y)."""

from __future__ import annotations

import numpy as np

from panogs_core.synthetic import shapes
from panogs_core.synthetic.placement import Group
from panogs_core.synthetic.shapes import Model


def single(model: Model) -> Group:
    """One object on its own."""
    return Group([model])


def dining(rng: np.random.Generator, coffee: bool = False) -> Group:
    """A table with chairs pulled up on its sides (seats slide under the top, clear of the legs).

    A coffee table is low and gets no chairs.
    """
    if coffee:
        return Group([shapes.table(rng, rng.uniform(0.8, 1.2), rng.uniform(0.5, 0.7), rng.uniform(0.4, 0.46))])
    w, d = rng.uniform(1.0, 1.9), rng.uniform(0.8, 1.0)
    top = shapes.table(rng, w, d)
    models, contacts = [top], []
    for side in range(4):
        span = (w if side % 2 == 0 else d) - 2 * 0.12  # keep clear of the legs at the corners
        chair = shapes.chair(rng)
        cw = chair.bounds[0, 1] - chair.bounds[0, 0]
        fit = int((span + 0.1) // (cw + 0.12))
        count = rng.integers(0 if side % 2 else 1, min(fit, 3) + 1) if fit > 0 else 0
        for x in (np.arange(count) - (count - 1) / 2) * (span / max(count, 1)):
            models.append(_pulled_up(rng, shapes.chair(rng), side, x, w, d))
            contacts.append((0, len(models) - 1))
    return Group(models, contacts)


def _pulled_up(rng: np.random.Generator, chair: Model, side: int, x: float, w: float, d: float) -> Model:
    """A chair facing the table from one side (0: -y, 1: +x, 2: +y, 3: -x), pushed in up to 12 cm."""
    push = rng.uniform(0.0, 0.12)
    depth = chair.bounds[1, 1]  # the chair's front edge, local y
    c = chair.moved(dy=-depth + push)  # front edge at y = push, the back behind
    if side == 0:
        return c.moved(dx=x, dy=-d / 2)
    if side == 2:
        return c.turned().moved(dx=x, dy=d / 2)
    if side == 1:
        return c.quarter(1).moved(dx=w / 2, dy=x)
    return c.quarter(-1).moved(dx=-w / 2, dy=x)


def desk(rng: np.random.Generator, hutch: bool) -> Group:
    """A desk against the wall with a chair in its knee space and optionally a hutch shelf on top."""
    top = shapes.desk(rng)
    h = top.bounds[2, 1]
    d_back, d_front = top.bounds[1]
    models, contacts = [top], []
    chair = shapes.chair(rng).turned()  # local front now -y: faces the desk from the room side
    knee0, knee1 = top.parts[1, 1], top.parts[2, 0]
    cw = chair.bounds[0, 1] - chair.bounds[0, 0]
    push = rng.uniform(0.05, 0.25) if knee1 - knee0 > cw + 0.04 else -rng.uniform(0.02, 0.1)
    models.append(chair.moved(dx=(knee0 + knee1) / 2, dy=d_front - push - chair.bounds[1, 0]))
    contacts.append((0, 1))
    if hutch:
        w = min(rng.uniform(0.6, 1.0), top.bounds[0, 1] - top.bounds[0, 0] - 0.1)
        shelf = shapes.bookshelf(rng, w, rng.uniform(0.24, 0.3), rng.uniform(0.4, 0.55))
        models.append(shelf.moved(dy=d_back - shelf.bounds[1, 0], dz=h))
        contacts.append((0, 2))
    return Group(models, contacts)


def side_by_side(members: list[Group], rng: np.random.Generator) -> Group:
    """Groups in a row along local x, backs aligned, each touching the next (0-1 cm apart).

    Same-class objects that touch are everyday scenes (a run of bookshelves, chairs along a wall, a bench of
    desks) and the case where only the 2D masks can tell instances apart: their language features agree. The
    first model of each member touches the first model of the next (they are listed as contacts).
    """
    models: list[Model] = []
    contacts: list[tuple[int, int]] = []
    cursor, anchors = 0.0, list[int]()
    for member in members:
        (x0, x1), (y0, _) = member.bounds()[0], member.bounds()[1]
        first = len(models)
        models += [m.moved(dx=cursor - x0, dy=-y0) for m in member.models]
        contacts += [(first + i, first + j) for i, j in member.contacts]
        if anchors:
            contacts.append((anchors[-1], first))
        anchors.append(first)
        cursor += (x1 - x0) + rng.uniform(0.0, 0.01)
    return Group([m.moved(dx=-cursor / 2) for m in models], contacts)


def bed(rng: np.random.Generator) -> Group:
    """A bed with its headboard on the wall and zero to two night stands touching its sides."""
    frame = shapes.bed(rng)
    models, contacts = [frame], []
    (x0, x1), back = frame.bounds[0], frame.bounds[1, 0]
    for sign in rng.permutation([-1, 1])[: rng.integers(0, 3)]:
        w, d = rng.uniform(0.4, 0.5), rng.uniform(0.38, 0.45)
        stand = shapes.cabinet(rng, w, d, rng.uniform(0.45, 0.6))
        gap = rng.uniform(0.0, 0.02)
        dx = x1 + gap + w / 2 if sign > 0 else x0 - gap - w / 2
        models.append(stand.moved(dx=dx, dy=back + d / 2))
        contacts.append((0, len(models) - 1))
    return Group(models, contacts)


def kitchen(rng: np.random.Generator, room_height: float) -> Group:
    """A counter run with sinks on it, maybe a refrigerator at one end and wall cabinets above."""
    length = rng.uniform(1.2, 2.6)
    run = shapes.counter(rng, length)
    models, contacts = [run], []
    back, top = run.bounds[1, 0], run.bounds[2, 1]
    n_sinks = 2 if length > 2.2 and rng.random() < 0.5 else 1
    for x in (np.arange(n_sinks) - (n_sinks - 1) / 2) * (length / n_sinks) + rng.uniform(-0.15, 0.15):
        s = shapes.sink(rng, on_counter=True)
        models.append(s.moved(dx=x, dy=back + 0.05 - s.bounds[1, 0], dz=top))
        contacts.append((0, len(models) - 1))
    if rng.random() < 0.7:
        fridge = shapes.refrigerator(rng, room_height)
        fw = fridge.bounds[0, 1] - fridge.bounds[0, 0]
        side = rng.choice([-1, 1])
        models.append(fridge.moved(dx=side * (length / 2 + rng.uniform(0.0, 0.02) + fw / 2),
                                   dy=back - fridge.bounds[1, 0]))  # fmt: skip
        contacts.append((0, len(models) - 1))
    if rng.random() < 0.7:
        first = len(models)
        models += _wall_cabinets(rng, length, back, room_height)
        contacts += [(k - 1, k) for k in range(first + 1, len(models))]  # neighbouring cabinets touch
    return Group(models, contacts)


def _wall_cabinets(rng: np.random.Generator, length: float, back: float, room_height: float) -> list[Model]:
    """One to three side-by-side wall cabinets above a counter run of ``length``, backs at ``back``."""
    n = int(rng.integers(1, 4))
    w = length / n
    z0 = rng.uniform(1.45, 1.55)
    h = min(rng.uniform(0.55, 0.75), room_height - 0.1 - z0)
    return [
        shapes.cabinet(rng, w - 0.004, 0.34, h).moved(dx=-length / 2 + (i + 0.5) * w, dy=back + 0.17, dz=z0)
        for i in range(n)
    ]


def sideboard(rng: np.random.Generator) -> Group:
    """A low, wide cabinet, with a framed picture standing on it against the wall half of the time."""
    w, d, h = rng.uniform(0.8, 1.6), rng.uniform(0.4, 0.5), rng.uniform(0.55, 0.9)
    body = shapes.cabinet(rng, w, d, h)
    if rng.random() < 0.5:
        return Group([body])
    frame = shapes.picture(rng, standing=True)
    return Group([body, frame.moved(dx=rng.uniform(-0.25, 0.25) * w, dy=-d / 2, dz=h)], [(0, 1)])


def vanity(rng: np.random.Generator) -> Group:
    """A short counter with a sink, or a pedestal sink."""
    if rng.random() < 0.4:
        return Group([shapes.sink(rng, on_counter=False)])
    run = shapes.counter(rng, rng.uniform(0.8, 1.3))
    s = shapes.sink(rng, on_counter=True)
    return Group([run, s.moved(dy=run.bounds[1, 0] + 0.05 - s.bounds[1, 0], dz=run.bounds[2, 1])], [(0, 1)])


def window(rng: np.random.Generator, room_height: float) -> Group:
    """A window, with a curtain panel on each side half of the time."""
    pane = shapes.window(rng, room_height)
    models, contacts = [pane], []
    if rng.random() < 0.55:
        (x0, x1), (z0, z1) = pane.bounds[0], pane.bounds[2]
        top = min(z1 + 0.15, room_height - 0.03)
        bottom = rng.choice([0.05, max(z0 - 0.25, 0.05)])
        for sign in (-1, 1):
            panel = shapes.curtain(rng, top, bottom)
            half = panel.bounds[0, 1]
            models.append(panel.moved(dx=(x1 + half) if sign > 0 else (x0 - half)))
            contacts.append((0, len(models) - 1))
    return Group(models, contacts)


def door(rng: np.random.Generator) -> Group:
    """A door with the floor in front of it kept free (its swing and the way in)."""
    leaf = shapes.door(rng)
    (x0, x1), (_, z1) = leaf.bounds[0], leaf.bounds[2]
    keep = np.array([[x0, x1, 0.1, 1.0, 0.0, z1, 1.0]])
    return Group([leaf], keepout=keep)
