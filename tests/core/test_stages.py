"""Checkpoint keys: each stage is keyed on exactly the settings it reads and on the keys of what it reads."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from panogs_core.pipeline.config import PipelineConfig
from panogs_core.pipeline.stage_table import stage_keys
from panogs_core.types import Vocabulary

VOCAB = Vocabulary(names=("wall", "chair"), kinds=("stuff", "thing"), embeddings=np.eye(2, dtype=np.float32))
CHECKPOINTED = ("primitives", "visibility", "fusion", "language_field", "masks", "neighbors", "superprimitives",
                "clustering", "labeling")  # fmt: skip


def _redone(overrides: dict[str, Any]) -> set[str]:
    """The checkpointed stages whose key changes when ``overrides`` are applied to the defaults."""
    before = stage_keys("bundle-hash", PipelineConfig(), VOCAB)
    after = stage_keys("bundle-hash", PipelineConfig().with_overrides(overrides), VOCAB)
    return {stage for stage in CHECKPOINTED if before[stage] != after[stage]}


@pytest.mark.parametrize(
    ("overrides", "redone"),
    [
        # Read by the clustering only (the affinity it measures each round), though they share a YAML section
        # with the mask look-ups' settings.
        ({"affinity": {"aggregate": "mean"}}, {"clustering", "labeling"}),
        ({"affinity": {"min_covisibility": 0.5}}, {"clustering", "labeling"}),
        ({"clustering": {"thresholds": [0.9, 0.7]}}, {"clustering", "labeling"}),
        # Memory only: the clustering reads it (so it is redone), the look-ups and the graph cut do not.
        ({"affinity": {"chunk_rows": 1000}}, {"clustering", "labeling"}),
        # Read by the mask look-ups: they and everything after them are redone, the neighbours are not.
        ({"affinity": {"mask_depth_mad": 3.0}}, {"masks", "superprimitives", "clustering", "labeling"}),
        ({"affinity": {"mask_depth_floor": 0.02}}, {"masks", "superprimitives", "clustering", "labeling"}),
        # Read by the graph cut; k_neighbors also by the neighbour graph.
        ({"superprimitives": {"k_thresh": 0.15}}, {"superprimitives", "clustering", "labeling"}),
        ({"superprimitives": {"k_neighbors": 9}}, {"neighbors", "superprimitives", "clustering", "labeling"}),
        ({"labeling": {"min_instance_points": 7}}, {"labeling"}),
        ({"fusion": {"mask_pooling": 0.0}},
         {"fusion", "language_field", "superprimitives", "clustering", "labeling"}),
        ({"features_source": "fused"}, {"superprimitives", "clustering", "labeling"}),
    ],
)  # fmt: skip
def test_a_setting_redoes_the_stages_that_read_it_and_those_after_them(
    overrides: dict[str, Any], redone: set[str]
) -> None:
    assert _redone(overrides) == redone


def test_every_key_depends_on_the_bundle_and_labels_on_the_vocabulary() -> None:
    keys = stage_keys("bundle-a", PipelineConfig(), VOCAB)
    other = stage_keys("bundle-b", PipelineConfig(), VOCAB)
    assert all(keys[s] != other[s] for s in CHECKPOINTED)
    renamed = Vocabulary(names=("wall", "seat"), kinds=VOCAB.kinds, embeddings=VOCAB.embeddings)
    relabelled = stage_keys("bundle-a", PipelineConfig(), renamed)
    assert {s for s in CHECKPOINTED if keys[s] != relabelled[s]} == {"labeling"}


def test_other_computed_maps_redo_the_stages_that_read_maps_and_those_after_them() -> None:
    before = stage_keys("bundle-hash", PipelineConfig(), VOCAB)
    after = stage_keys("bundle-hash", PipelineConfig(), VOCAB, "other-maps-key")
    redone = {stage for stage in CHECKPOINTED if before[stage] != after[stage]}
    assert redone == set(CHECKPOINTED) - {"primitives", "visibility", "neighbors"}
    # The 2D-maps stage's own settings are not in any stage key: their maps' key carries them.
    changed = stage_keys("bundle-hash", PipelineConfig().with_overrides({"maps2d": {"points_per_side": 8}}), VOCAB)
    assert changed == before
