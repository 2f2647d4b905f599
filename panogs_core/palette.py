"""Colours of ids, classes and panoptic segments: shared by the exported PLYs and the renders."""

from __future__ import annotations

import numpy as np


def palette(ids: np.ndarray, salt: int = 0) -> np.ndarray:  # (M,) int64 -> (M, 3) uint8
    """Distinct, stable colours for integer ids (golden-ratio hues); -1 is grey."""
    import colorsys

    ids = np.asarray(ids, dtype=np.int64)
    uniq, inverse = np.unique(ids, return_inverse=True)
    table = np.zeros((len(uniq), 3), dtype=np.uint8)
    for row, value in enumerate(uniq):
        if value < 0:
            table[row] = (128, 128, 128)
            continue
        hue = ((int(value) + salt) * 0.61803398875) % 1.0
        sat = 0.55 + 0.35 * ((int(value) * 7 + salt) % 3) / 2
        table[row] = np.round(np.array(colorsys.hsv_to_rgb(hue, sat, 0.92)) * 255).astype(np.uint8)
    return table[inverse]


def panoptic_colors(semantic: np.ndarray, instance: np.ndarray, is_thing: np.ndarray) -> np.ndarray:
    """(N, 3) uint8: thing instances by instance id, stuff by class, void grey."""
    colors = palette(instance, salt=17)
    thing = (semantic >= 0) & (instance >= 0)
    thing[thing] = is_thing[semantic[thing]]
    stuff = (semantic >= 0) & ~thing
    colors[stuff] = palette(semantic[stuff], salt=3)
    colors[semantic < 0] = 128
    return colors
