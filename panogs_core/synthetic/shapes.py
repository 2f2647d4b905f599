"""Object models built from axis-aligned boxes, in the object's local frame.

Local frame of every model: x along its width, y along its depth with the *front* facing +y and the back at
the smallest y, z up with z = 0 on the supporting surface (floor, counter top, desk top). Wall-mounted models
have their back face at the smallest y too, so that putting that face on a wall plane mounts them.

A model is a ``(P, 7)`` float array of parts: ``x0, x1, y0, y1, z0, z1, shade`` (extents in metres; shade
multiplies the instance colour so that parts such as doors or cushions read as separate surfaces). Parts of
one model touch but never overlap.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

Parts = np.ndarray  # (P, 7) float64: x0, x1, y0, y1, z0, z1, shade


@dataclass(frozen=True)
class Model:
    """One object: its class name and its parts in the local frame."""

    cls: str
    parts: Parts  # (P, 7)

    @property
    def bounds(self) -> np.ndarray:  # (3, 2) min / max per axis
        """Axis-aligned local bounds of all parts."""
        p = self.parts
        return np.array([[p[:, 0].min(), p[:, 1].max()], [p[:, 2].min(), p[:, 3].max()],
                         [p[:, 4].min(), p[:, 5].max()]])  # fmt: skip

    def moved(self, dx: float = 0.0, dy: float = 0.0, dz: float = 0.0) -> Model:
        """The same model translated in its local frame."""
        p = self.parts.copy()
        p[:, 0:2] += dx
        p[:, 2:4] += dy
        p[:, 4:6] += dz
        return Model(self.cls, p)

    def turned(self) -> Model:
        """The model rotated by 180 degrees about z (front facing -y)."""
        p = self.parts.copy()
        p[:, [0, 1]] = -self.parts[:, [1, 0]]
        p[:, [2, 3]] = -self.parts[:, [3, 2]]
        return Model(self.cls, p)

    def quarter(self, sign: int) -> Model:
        """The model rotated by +90 (sign=1, front to -x) or -90 degrees (sign=-1, front to +x) about z."""
        p = self.parts.copy()
        if sign > 0:  # (x, y) -> (-y, x)
            p[:, [0, 1]] = -self.parts[:, [3, 2]]
            p[:, [2, 3]] = self.parts[:, [0, 1]]
        else:  # (x, y) -> (y, -x)
            p[:, [0, 1]] = self.parts[:, [2, 3]]
            p[:, [2, 3]] = -self.parts[:, [1, 0]]
        return Model(self.cls, p)


def _box(x0: float, x1: float, y0: float, y1: float, z0: float, z1: float, shade: float = 1.0) -> list[float]:
    return [x0, x1, y0, y1, z0, z1, shade]


def _centred(w: float, d: float, z0: float, z1: float, shade: float = 1.0) -> list[float]:
    return _box(-w / 2, w / 2, -d / 2, d / 2, z0, z1, shade)


def _legs(w: float, d: float, h: float, leg: float, inset: float) -> list[list[float]]:
    """Four square legs under a ``w`` x ``d`` top, from the floor to height ``h``."""
    out = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (w / 2 - inset - leg / 2), sy * (d / 2 - inset - leg / 2)
            out.append(_box(cx - leg / 2, cx + leg / 2, cy - leg / 2, cy + leg / 2, 0.0, h, 0.8))
    return out


def chair(rng: np.random.Generator) -> Model:
    """Seat on four legs with a back rest at the back edge."""
    w, d = rng.uniform(0.42, 0.52), rng.uniform(0.42, 0.50)
    seat, t, back = rng.uniform(0.43, 0.48), 0.05, rng.uniform(0.38, 0.50)
    parts = [_centred(w, d, seat - t, seat), *_legs(w, d, seat - t, 0.04, 0.0)]
    parts.append(_box(-w / 2, w / 2, -d / 2, -d / 2 + 0.05, seat, seat + back, 1.1))
    return Model("chair", np.array(parts))


def table(rng: np.random.Generator, w: float, d: float, h: float | None = None) -> Model:
    """Top slab on four legs."""
    h = rng.uniform(0.72, 0.76) if h is None else h
    parts = [_centred(w, d, h - 0.04, h), *_legs(w, d, h - 0.04, 0.06, 0.04)]
    return Model("table", np.array(parts))


def desk(rng: np.random.Generator) -> Model:
    """Top on a side panel and a drawer block."""
    w, d, h = rng.uniform(1.0, 1.6), rng.uniform(0.6, 0.75), rng.uniform(0.72, 0.76)
    dw = rng.uniform(0.38, 0.45)
    parts = [
        _centred(w, d, h - 0.04, h),
        _box(-w / 2, -w / 2 + 0.04, -d / 2, d / 2 - 0.02, 0.0, h - 0.04, 0.85),
        _box(w / 2 - dw, w / 2, -d / 2, d / 2 - 0.02, 0.0, h - 0.04, 0.9),
    ]
    return Model("desk", np.array(parts))


def sofa(rng: np.random.Generator) -> Model:
    """Seat block, back rest and two arms."""
    w, d = rng.uniform(1.5, 2.2), rng.uniform(0.8, 0.95)
    seat, back, arm, bt = rng.uniform(0.40, 0.45), rng.uniform(0.78, 0.9), 0.16, 0.2
    parts = [
        _box(-w / 2 + arm, w / 2 - arm, -d / 2 + bt, d / 2, 0.0, seat),
        _box(-w / 2 + arm, w / 2 - arm, -d / 2, -d / 2 + bt, 0.0, back, 0.9),
        _box(-w / 2, -w / 2 + arm, -d / 2, d / 2, 0.0, seat + 0.2, 0.85),
        _box(w / 2 - arm, w / 2, -d / 2, d / 2, 0.0, seat + 0.2, 0.85),
    ]
    return Model("sofa", np.array(parts))


def bed(rng: np.random.Generator) -> Model:
    """Frame, mattress on top, headboard at the back (length along y)."""
    w, length = rng.choice([0.95, 1.4, 1.6, 1.8]) + rng.uniform(-0.05, 0.05), rng.uniform(1.95, 2.1)
    frame, mat, hb = rng.uniform(0.25, 0.32), rng.uniform(0.18, 0.25), rng.uniform(0.9, 1.1)
    parts = [
        _box(-w / 2, w / 2, -length / 2 + 0.06, length / 2, 0.0, frame, 0.7),
        _box(-w / 2 + 0.03, w / 2 - 0.03, -length / 2 + 0.06, length / 2 - 0.03, frame, frame + mat, 1.15),
        _box(-w / 2, w / 2, -length / 2, -length / 2 + 0.06, 0.0, hb, 0.75),
    ]
    return Model("bed", np.array(parts))


def cabinet(rng: np.random.Generator, w: float, d: float, h: float) -> Model:
    """Body with one or two door panels on the front."""
    n = 1 if w < 0.6 else 2
    parts = [_box(-w / 2, w / 2, -d / 2, d / 2 - 0.02, 0.0, h)]
    edges = np.linspace(-w / 2, w / 2, n + 1)
    for i in range(n):
        parts.append(_box(edges[i] + 0.01, edges[i + 1] - 0.01, d / 2 - 0.02, d / 2, 0.03, h - 0.03, 1.12))
    return Model("cabinet", np.array(parts))


def bookshelf(rng: np.random.Generator, w: float, d: float, h: float) -> Model:
    """Open shelving: sides, top, bottom, back panel and evenly spaced shelves."""
    t = 0.025
    parts = [
        _box(-w / 2, -w / 2 + t, -d / 2, d / 2, 0.0, h),
        _box(w / 2 - t, w / 2, -d / 2, d / 2, 0.0, h),
        _box(-w / 2 + t, w / 2 - t, -d / 2, -d / 2 + 0.015, 0.0, h, 0.8),
        _box(-w / 2 + t, w / 2 - t, -d / 2 + 0.015, d / 2, 0.0, 0.06),
        _box(-w / 2 + t, w / 2 - t, -d / 2 + 0.015, d / 2, h - t, h),
    ]
    n = max(1, int(h / 0.36) - 1)
    for z in np.linspace(0.06, h - t, n + 2)[1:-1]:
        parts.append(_box(-w / 2 + t, w / 2 - t, -d / 2 + 0.015, d / 2, z - t / 2, z + t / 2))
    return Model("bookshelf", np.array(parts))


def refrigerator(rng: np.random.Generator, room_height: float) -> Model:
    """Body with a freezer door and a fridge door on the front."""
    w, d = rng.uniform(0.6, 0.8), rng.uniform(0.62, 0.72)
    h = min(rng.uniform(1.7, 1.95), room_height - 0.2)
    split = h * rng.uniform(0.3, 0.4)
    parts = [
        _box(-w / 2, w / 2, -d / 2, d / 2 - 0.03, 0.0, h),
        _box(-w / 2 + 0.01, w / 2 - 0.01, d / 2 - 0.03, d / 2, 0.02, h - split - 0.01, 1.05),
        _box(-w / 2 + 0.01, w / 2 - 0.01, d / 2 - 0.03, d / 2, h - split + 0.01, h - 0.02, 1.05),
    ]
    return Model("refrigerator", np.array(parts))


def counter(rng: np.random.Generator, length: float) -> Model:
    """Base block under a slightly overhanging top slab (height about 0.9 m)."""
    d, h = rng.uniform(0.58, 0.65), rng.uniform(0.86, 0.92)
    parts = [
        _box(-length / 2, length / 2, -d / 2, d / 2 - 0.03, 0.0, h - 0.04, 0.8),
        _box(-length / 2, length / 2, -d / 2, d / 2, h - 0.04, h, 1.1),
    ]
    return Model("counter", np.array(parts))


def sink(rng: np.random.Generator, on_counter: bool) -> Model:
    """Basin with a faucet at the back; on a pedestal when it stands on the floor."""
    w, d, bh = rng.uniform(0.45, 0.6), rng.uniform(0.36, 0.45), rng.uniform(0.12, 0.16)
    z0 = 0.0 if on_counter else rng.uniform(0.68, 0.72)
    parts = [
        _box(-w / 2, w / 2, -d / 2 + 0.06, d / 2, z0, z0 + bh),
        _box(-0.02, 0.02, -d / 2, -d / 2 + 0.06, z0, z0 + bh + 0.15, 0.8),
    ]
    if not on_counter:
        parts.append(_box(-0.1, 0.1, -d / 2 + 0.06, -d / 2 + 0.26, 0.0, z0, 0.95))
    return Model("sink", np.array(parts))


def toilet(rng: np.random.Generator) -> Model:
    """Bowl block, seat slab and tank at the back."""
    w, d = rng.uniform(0.36, 0.42), rng.uniform(0.6, 0.7)
    parts = [
        _box(-w / 2, w / 2, -d / 2 + 0.2, d / 2, 0.0, 0.38),
        _box(-w / 2, w / 2, -d / 2 + 0.2, d / 2, 0.38, 0.42, 0.9),
        _box(-w / 2 - 0.02, w / 2 + 0.02, -d / 2, -d / 2 + 0.2, 0.0, rng.uniform(0.75, 0.82), 1.05),
    ]
    return Model("toilet", np.array(parts))


def bathtub(rng: np.random.Generator) -> Model:
    """Open tub: bottom slab and four rims (length along x)."""
    length, w, h, t = rng.uniform(1.5, 1.7), rng.uniform(0.7, 0.8), rng.uniform(0.5, 0.58), 0.08
    parts = [
        _centred(length, w, 0.0, t, 0.9),
        _box(-length / 2, length / 2, -w / 2, -w / 2 + t, t, h),
        _box(-length / 2, length / 2, w / 2 - t, w / 2, t, h),
        _box(-length / 2, -length / 2 + t, -w / 2 + t, w / 2 - t, t, h),
        _box(length / 2 - t, length / 2, -w / 2 + t, w / 2 - t, t, h),
    ]
    return Model("bathtub", np.array(parts))


def door(rng: np.random.Generator) -> Model:
    """Door leaf standing proud of the wall, with a handle (back at y = 0)."""
    w, h = rng.uniform(0.8, 0.95), rng.uniform(2.0, 2.1)
    hx = w / 2 - 0.12
    parts = [
        _box(-w / 2, w / 2, 0.0, 0.04, 0.0, h),
        _box(hx - 0.06, hx + 0.06, 0.04, 0.08, 0.98, 1.02, 0.6),
    ]
    return Model("door", np.array(parts))


def window(rng: np.random.Generator, room_height: float) -> Model:
    """Glass pane with a centre mullion and a sill (back at y = 0)."""
    w = rng.uniform(0.8, 1.6)
    z0 = rng.uniform(0.8, 1.0)
    z1 = min(z0 + rng.uniform(1.0, 1.4), room_height - 0.2)
    parts = [
        _box(-w / 2, -0.02, 0.0, 0.02, z0, z1),
        _box(0.02, w / 2, 0.0, 0.02, z0, z1),
        _box(-0.02, 0.02, 0.0, 0.04, z0, z1, 0.6),
        _box(-w / 2 - 0.05, w / 2 + 0.05, 0.0, 0.12, z0 - 0.04, z0, 0.7),
    ]
    return Model("window", np.array(parts))


def curtain(rng: np.random.Generator, top: float, bottom: float) -> Model:
    """One hanging panel, a little off the wall (back at y = 0)."""
    w = rng.uniform(0.3, 0.5)
    return Model("curtain", np.array([_box(-w / 2, w / 2, 0.0, 0.06, bottom, top)]))


def picture(rng: np.random.Generator, standing: bool = False) -> Model:
    """Framed picture centred at eye height, or standing on a surface (back at y = 0)."""
    if standing:
        w, h = rng.uniform(0.25, 0.5), rng.uniform(0.2, 0.4)
        return Model("picture", np.array([_box(-w / 2, w / 2, 0.0, 0.03, 0.0, h)]))
    w, h = rng.uniform(0.4, 1.1), rng.uniform(0.3, 0.8)
    zc = rng.uniform(1.45, 1.7)
    return Model("picture", np.array([_box(-w / 2, w / 2, 0.0, 0.03, zc - h / 2, zc + h / 2)]))
