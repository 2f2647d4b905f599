"""Procedural indoor scenes with known answers, written as scene bundles.

``make_scene(out_dir, preset=..., difficulty=..., seed=...)`` builds a furnished room (walls, floor, ceiling
and box-modelled furniture of the Matterport-21 classes), samples its surfaces into ``geometry.ply`` with
per-point ground truth, ray-casts a handheld trajectory into depth, colour, SAM-like masks and language
feature maps, and degrades each per the difficulty. The ``scan`` preset is a realistic capture (a cluttered
studio with unannotated ground truth, a dense trajectory with sparse key frames, world-anchored feature
confusions). See ``docs/synthetic.md`` for the noise model and the presets.
"""

from __future__ import annotations

from panogs_core.synthetic.building import make_building
from panogs_core.synthetic.catalog import CLASS_KINDS, CLASS_NAMES, catalogue_vocabulary, label_embeddings
from panogs_core.synthetic.layout import Layout
from panogs_core.synthetic.presets import (
    DIFFICULTIES,
    PRESETS,
    REALISTIC_DIFFICULTIES,
    DepthNoise,
    Difficulty,
    FeatureNoise,
    MaskNoise,
    SyntheticSpec,
    TrajectoryNoise,
    get_difficulty,
    get_preset,
)
from panogs_core.synthetic.rooms import build_layout
from panogs_core.synthetic.scene import make_scene, spec_camera

__all__ = [
    "CLASS_KINDS",
    "CLASS_NAMES",
    "DIFFICULTIES",
    "PRESETS",
    "REALISTIC_DIFFICULTIES",
    "DepthNoise",
    "Difficulty",
    "FeatureNoise",
    "Layout",
    "MaskNoise",
    "SyntheticSpec",
    "TrajectoryNoise",
    "build_layout",
    "catalogue_vocabulary",
    "get_difficulty",
    "get_preset",
    "label_embeddings",
    "make_building",
    "make_scene",
    "spec_camera",
]
