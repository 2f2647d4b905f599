"""Settings of stage 8, and their scaling to the scene's point spacing."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import numpy as np

from panogs_core.errors import ConfigError

_UNSEEN_MODES = ("segment", "segment-field", "propagate", "field")


@dataclass(frozen=True, kw_only=True)
class LabelingConfig:
    """Settings of stage 8.

    Attributes:
        vote: ``superprimitive`` replaces the classes inside each graph-cut super-primitive by its majority
            class (docs/method.md §7.3, ties -> smallest class index); ``none`` keeps the per-primitive argmax.
        vote_min_fraction: Purity guard of the vote, a fraction of the segment's classified primitives in
            ``[0, 1]``: a segment is voted only when its majority class holds at least this share. 0 = the
            reference (always vote).
        min_instance_points: Instances with fewer primitives are dissolved (primitives keep their class,
            instance -1). Counts primitives; the reference removes clusters < 200 points with <= 2 segments
            (docs/method.md §6.2).
        score_temperature: Softmax temperature (cosine units) of the instance score; None = derived from the
            vocabulary's spread (``language.label_sets.default_temperature``; 0.01 for the CLIP label sets).
        split_classes: Split a cluster's thing primitives into one instance per class and connected part
            (``_assemble_split``) instead of relabelling them all to the cluster's majority thing class.
        split_neighbors: Neighbours of the kNN graph built for the split when ``assign_panoptic`` gets none.
        island_points: The island vote flips connected patches of fewer primitives than this.
        vote_max_ratio: The island vote flips a primitive only when the softmax probability of the segment's
            class is at least this share of its own class's (0 = always).
        evidence_fused_weight: Class evidence of a seen primitive: this weight on the fused feature's
            cosines, the rest on the field's (1 = fused only).
        unseen: ``segment`` (the segment's seen majority, then ``propagate``), ``segment-field`` (the same, but
            the nearest seen class along the kNN graph where it differs from the segment's and the field picks it,
            ``unseen_field_ratio``), ``propagate`` (the nearest seen class along the kNN graph) or ``field`` (the
            field's extrapolation, the reference).
        unseen_field_ratio: ``segment-field`` overrules the segment's class only where the field's softmax
            probability (at ``score_temperature``) of the nearest seen class is at least this many times the
            segment's class's, a lead of ``T ln(ratio)`` in cosine units.
        instances: ``hybrid`` (class components split by large clusters), ``components`` or ``clusters``
            (the SAM-guided clusters, split by class: the earlier rule).
        component_radius: Longest kNN edge that joins two primitives of one class into a component, metres.
        split_min_points: A cluster splits a component only if it holds this many of its primitives ...
        split_min_fraction: ... and this share of it, and so does at least one other cluster.
        reference_spacing: Point spacing (median nearest-neighbour distance, metres) at which the point counts
            above (``min_instance_points``, ``island_points``, ``split_min_points``) and ``component_radius``
            hold; on other clouds they are rescaled to the same surface area and gap (``scaled_to_spacing``).
            None = use them as given.
    """

    # DEPARTURE (the island vote with a close-second test, not the whole segment's): docs/method.md §7.5.
    vote: Literal["superprimitive", "islands", "none"] = "islands"
    vote_min_fraction: float = 0.5
    min_instance_points: int = 50
    score_temperature: float | None = None
    # DEPARTURE (a cluster's thing primitives split by class, ``instances.assemble_split``): docs/method.md §7.5.
    split_classes: bool = True
    split_neighbors: int = 7  # kNN used for the split when the caller passes none (the stage passes stage 5's)
    # Labels that never lose to the fused-feature baselines (docs/method.md §7.5): the class evidence of a seen
    # primitive (``votes.primitive_classes``), the unseen ones (``unseen.label_unseen``), the instances
    # (``instances.assemble_components``). The reference's labelling: evidence_fused_weight=0, unseen="field",
    # vote="superprimitive", instances="clusters".
    evidence_fused_weight: float = 0.5
    unseen: Literal["segment", "segment-field", "propagate", "field"] = "segment-field"
    unseen_field_ratio: float = 50.0
    island_points: int = 150
    vote_max_ratio: float = 0.1
    instances: Literal["clusters", "components", "hybrid"] = "hybrid"
    component_radius: float = 0.10
    split_min_points: int = 200
    split_min_fraction: float = 0.2
    # DEPARTURE (counts in the surface a primitive stands for, not in primitives): docs/method.md §7.5.
    reference_spacing: float | None = 0.037

    def __post_init__(self) -> None:
        if self.vote not in ("superprimitive", "islands", "none"):
            raise ConfigError(f"labeling.vote: expected 'superprimitive', 'islands' or 'none', found {self.vote!r}")
        if self.unseen not in _UNSEEN_MODES:
            raise ConfigError(f"labeling.unseen: expected one of {_UNSEEN_MODES}, found {self.unseen!r}")
        if self.instances not in ("clusters", "components", "hybrid"):
            raise ConfigError(
                f"labeling.instances: expected 'clusters', 'components' or 'hybrid', found {self.instances!r}"
            )
        if not 0.0 <= self.evidence_fused_weight <= 1.0:
            raise ConfigError(
                f"labeling.evidence_fused_weight: expected a value in [0, 1], found {self.evidence_fused_weight}"
            )
        if not self.component_radius > 0:
            raise ConfigError(f"labeling.component_radius: expected > 0 metres, found {self.component_radius}")
        if not 0.0 <= self.split_min_fraction <= 1.0:
            raise ConfigError(
                f"labeling.split_min_fraction: expected a value in [0, 1], found {self.split_min_fraction}"
            )
        if not (np.isfinite(self.unseen_field_ratio) and self.unseen_field_ratio >= 1.0):
            raise ConfigError(
                f"labeling.unseen_field_ratio: expected a finite value >= 1, found {self.unseen_field_ratio}"
            )
        if not (np.isfinite(self.vote_max_ratio) and 0.0 <= self.vote_max_ratio <= 1.0):
            raise ConfigError(f"labeling.vote_max_ratio: expected a value in [0, 1], found {self.vote_max_ratio}")
        for name in ("island_points", "split_min_points"):
            if getattr(self, name) < 0:
                raise ConfigError(f"labeling.{name}: expected >= 0, found {getattr(self, name)}")
        if not 0.0 <= self.vote_min_fraction <= 1.0:
            raise ConfigError(f"labeling.vote_min_fraction: expected a value in [0, 1], found {self.vote_min_fraction}")
        if self.split_neighbors < 1:
            raise ConfigError(f"labeling.split_neighbors: expected >= 1, found {self.split_neighbors}")
        if self.min_instance_points < 1:
            raise ConfigError(f"labeling.min_instance_points: expected >= 1, found {self.min_instance_points}")
        if self.reference_spacing is not None and not (
            np.isfinite(self.reference_spacing) and self.reference_spacing > 0
        ):
            raise ConfigError(
                f"labeling.reference_spacing: expected > 0 metres or None, found {self.reference_spacing}"
            )
        if self.score_temperature is not None and not self.score_temperature > 0:
            raise ConfigError(f"labeling.score_temperature: expected > 0 or None, found {self.score_temperature}")


def point_spacing(points: np.ndarray, neighbors: np.ndarray) -> float:  # metres
    """Median distance from a primitive to its nearest neighbour (column 0 of the kNN graph).

    Example:
        >>> pts = np.array([[0.0, 0, 0], [0.02, 0, 0], [0.06, 0, 0]], np.float32)
        >>> round(point_spacing(pts, np.array([[1], [0], [1]])), 3)
        0.02
    """
    if len(points) < 2 or neighbors.size == 0:
        return 0.0
    nearest = np.linalg.norm(points - points[neighbors[:, 0]], axis=1)
    return float(np.median(nearest))


def scaled_to_spacing(cfg: LabelingConfig, spacing: float) -> LabelingConfig:
    """The config with its point counts and join radius moved from ``cfg.reference_spacing`` to ``spacing``.

    A point stands for ``spacing^2`` of surface, so a count becomes ``count (reference / spacing)^2`` (at
    least 1 where it was); the radius that joins two primitives grows with the spacing and never shrinks.

    Example:
        >>> cfg = scaled_to_spacing(LabelingConfig(), 0.074)  # twice the reference spacing
        >>> cfg.island_points, cfg.split_min_points, cfg.min_instance_points, round(cfg.component_radius, 2)
        (38, 50, 12, 0.2)
    """
    reference = cfg.reference_spacing
    if reference is None or not spacing > 0:
        return cfg
    area = (reference / spacing) ** 2

    def count(value: int) -> int:
        return max(round(value * area), 1 if value > 0 else 0)

    return dataclasses.replace(
        cfg,
        island_points=count(cfg.island_points),
        split_min_points=count(cfg.split_min_points),
        min_instance_points=count(cfg.min_instance_points),
        component_radius=cfg.component_radius * max(1.0, spacing / reference),
        reference_spacing=None,  # applied
    )
