"""The output of stage 8: a class and an instance per primitive, and the instance table."""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.errors import InputError
from panogs_core.io.npz import save_npz
from panogs_core.types import InstanceInfo, Vocabulary


@dataclass(frozen=True)
class PanopticLabels:
    """Output of stage 8."""

    semantic: np.ndarray  # (N,) int64 class index into the vocabulary, -1 void
    instance: np.ndarray  # (N,) int64 InstanceInfo.id, -1 none
    instances: tuple[InstanceInfo, ...]
    # Primitives no key frame saw, and how many of them each rule labelled (``label_unseen``); for report.json.
    unseen: dict[str, int] = dataclasses.field(default_factory=dict)

    def save(self, path: str | Path) -> None:
        """Write one ``.npz`` (no pickles): per-point arrays, instance fields as arrays + a JSON string."""
        inst = self.instances
        dim = inst[0].feature.shape[0] if inst else 0
        text = json.dumps([[i.class_name, i.kind] for i in inst])
        save_npz(
            path,
            semantic=self.semantic,
            instance=self.instance,
            inst_id=np.array([i.id for i in inst], np.int64),
            inst_class=np.array([i.class_index for i in inst], np.int64),
            inst_score=np.array([i.score for i in inst], np.float64),
            inst_num_points=np.array([i.num_points for i in inst], np.int64),
            inst_centroid=_stack([i.centroid for i in inst], 3),
            inst_bbox_min=_stack([i.bbox_min for i in inst], 3),
            inst_bbox_max=_stack([i.bbox_max for i in inst], 3),
            inst_feature=_stack([i.feature for i in inst], dim),
            inst_text=np.array(text),
            unseen=np.array(json.dumps(self.unseen)),
        )

    @classmethod
    def load(cls, path: str | Path) -> PanopticLabels:
        """Read what :meth:`save` wrote."""
        with np.load(path, allow_pickle=False) as z:
            text = json.loads(str(z["inst_text"]))
            instances = tuple(
                InstanceInfo(
                    id=int(z["inst_id"][k]),
                    class_index=int(z["inst_class"][k]),
                    class_name=name,
                    kind=kind,
                    score=float(z["inst_score"][k]),
                    num_points=int(z["inst_num_points"][k]),
                    centroid=z["inst_centroid"][k],
                    bbox_min=z["inst_bbox_min"][k],
                    bbox_max=z["inst_bbox_max"][k],
                    feature=z["inst_feature"][k],
                )
                for k, (name, kind) in enumerate(text)
            )
            unseen = json.loads(str(z["unseen"])) if "unseen" in z.files else {}
            return cls(
                semantic=z["semantic"].astype(np.int64),
                instance=z["instance"].astype(np.int64),
                instances=instances,
                unseen=unseen,
            )


def instances_to_json(labels: PanopticLabels, vocabulary: Vocabulary) -> list[dict[str, Any]]:
    """The ``instances.json`` list: one :meth:`InstanceInfo.to_json` dict per instance, in id order.

    Raises:
        InputError: an instance's class does not match the vocabulary (labels from another label set).
    """
    out = []
    for info in labels.instances:
        c = info.class_index
        if not 0 <= c < len(vocabulary.names) or vocabulary.names[c] != info.class_name:
            raise InputError(
                f"instance {info.id}: class {info.class_name!r} is not class {info.class_index} of this vocabulary"
            )
        out.append(info.to_json())
    return out


def _stack(rows: list[np.ndarray], dim: int) -> np.ndarray:
    return np.stack([np.asarray(r, np.float32) for r in rows]) if rows else np.zeros((0, dim), np.float32)
