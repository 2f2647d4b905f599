"""Colours of classes, instances and panoptic segments: one rule for the viewer, the exported PLYs and the renders,
so that a class or an instance has the same colour wherever a user sees it. numpy only (the viewer needs no torch).
"""

from __future__ import annotations

import colorsys
from collections.abc import Callable

import numpy as np

# The semantic palette: fixed, so a class has the same colour in every scene, the legend and the tests. Tableau-20
# style hues, chosen apart from each other and from grey (void).
CLASS_PALETTE: tuple[tuple[int, int, int], ...] = (
    (31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189), (140, 86, 75),
    (227, 119, 194), (188, 189, 34), (23, 190, 207), (174, 199, 232), (255, 187, 120), (152, 223, 138),
    (255, 152, 150), (197, 176, 213), (196, 156, 148), (247, 182, 210), (219, 219, 141), (158, 218, 229),
    (57, 59, 121), (99, 121, 57), (140, 109, 49), (132, 60, 57), (123, 65, 115), (82, 84, 163),
)  # fmt: skip
VOID_COLOR = (128, 128, 128)


def class_color(index: int) -> tuple[int, int, int]:
    """The palette colour of class ``index`` (-1: void grey)."""
    return VOID_COLOR if index < 0 else CLASS_PALETTE[index % len(CLASS_PALETTE)]


def instance_color(instance_id: int) -> tuple[int, int, int]:
    """A distinct colour per instance: golden-ratio hue steps, saturated and bright (-1: void grey)."""
    if instance_id < 0:
        return VOID_COLOR
    r, g, b = colorsys.hsv_to_rgb((instance_id * 0.618033988749895) % 1.0, 0.75, 0.95)
    return round(r * 255), round(g * 255), round(b * 255)


def class_colors(ids: np.ndarray) -> np.ndarray:  # (M,) int -> (M, 3) uint8
    """:func:`class_color` of every id."""
    return _colors(ids, class_color)


def instance_colors(ids: np.ndarray) -> np.ndarray:  # (M,) int -> (M, 3) uint8
    """:func:`instance_color` of every id."""
    return _colors(ids, instance_color)


def panoptic_colors(semantic: np.ndarray, instance: np.ndarray, is_thing: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: thing instances by instance id, stuff by class, void grey."""
    semantic = np.asarray(semantic, dtype=np.int64)
    colors = instance_colors(instance)
    thing = (semantic >= 0) & (np.asarray(instance) >= 0)
    thing[thing] = is_thing[semantic[thing]]
    stuff = (semantic >= 0) & ~thing
    colors[stuff] = class_colors(semantic[stuff])
    colors[semantic < 0] = VOID_COLOR
    return colors


def _colors(ids: np.ndarray, color_of: Callable[[int], tuple[int, int, int]]) -> np.ndarray:
    uniq, inverse = np.unique(np.asarray(ids, dtype=np.int64), return_inverse=True)
    table = np.array([color_of(int(v)) for v in uniq], dtype=np.uint8).reshape(-1, 3)
    return table[inverse.reshape(-1)]
