"""The class catalogue of the synthetic generator: names, kinds, base colours, confusable classes.

Every class name is a Matterport-21 class (``data/label_sets/README.md``), so that scenes in the
``clip-vit-b32`` space can take their vocabulary rows straight from ``MATTERPORT_LABELS_21_dim512.npy``. The
vocabulary of every synthetic scene is this whole catalogue, in this order, whether or not a class occurs in
the scene (absent classes are distractors, as in a real label set).
"""

from __future__ import annotations

from importlib import resources

import numpy as np

from panogs_core.types import ClassKind, Vocabulary

# (name, kind, base RGB in [0, 1]). Order is the vocabulary order; stuff first.
_CLASSES: tuple[tuple[str, ClassKind, tuple[float, float, float]], ...] = (
    ("wall", "stuff", (0.82, 0.80, 0.74)),
    ("floor", "stuff", (0.55, 0.42, 0.30)),
    ("ceiling", "stuff", (0.93, 0.93, 0.92)),
    ("cabinet", "thing", (0.60, 0.45, 0.30)),
    ("bed", "thing", (0.70, 0.72, 0.85)),
    ("chair", "thing", (0.35, 0.25, 0.18)),
    ("sofa", "thing", (0.40, 0.50, 0.35)),
    ("table", "thing", (0.70, 0.55, 0.38)),
    ("door", "thing", (0.78, 0.66, 0.50)),
    ("window", "thing", (0.62, 0.78, 0.90)),
    ("bookshelf", "thing", (0.45, 0.33, 0.22)),
    ("picture", "thing", (0.85, 0.35, 0.30)),
    ("counter", "thing", (0.80, 0.80, 0.78)),
    ("desk", "thing", (0.62, 0.62, 0.60)),
    ("curtain", "thing", (0.70, 0.30, 0.40)),
    ("refrigerator", "thing", (0.90, 0.90, 0.92)),
    ("toilet", "thing", (0.96, 0.96, 0.96)),
    ("sink", "thing", (0.85, 0.88, 0.90)),
    ("bathtub", "thing", (0.92, 0.93, 0.95)),
)

CLASS_NAMES: tuple[str, ...] = tuple(c[0] for c in _CLASSES)
CLASS_KINDS: tuple[ClassKind, ...] = tuple(c[1] for c in _CLASSES)
CLASS_COLORS: np.ndarray = np.array([c[2] for c in _CLASSES], dtype=np.float32)  # (L, 3)
CLASS_ID: dict[str, int] = {name: i for i, name in enumerate(CLASS_NAMES)}

# Classes a 2D open-vocabulary model plausibly mistakes each class for (look-alike shape or context). The
# feature noise model leans some instances / image regions towards one of these.
CONFUSABLE: dict[str, tuple[str, ...]] = {
    "wall": ("door", "ceiling"),
    "floor": ("wall",),
    "ceiling": ("wall",),
    "cabinet": ("bookshelf", "counter", "refrigerator"),
    "bed": ("sofa",),
    "chair": ("sofa", "table"),
    "sofa": ("chair", "bed"),
    "table": ("desk", "counter"),
    "door": ("cabinet", "wall"),
    "window": ("picture", "curtain"),
    "bookshelf": ("cabinet",),
    "picture": ("window",),
    "counter": ("table", "cabinet"),
    "desk": ("table",),
    "curtain": ("window",),
    "refrigerator": ("cabinet",),
    "toilet": ("sink", "bathtub"),
    "sink": ("toilet", "counter"),
    "bathtub": ("sink", "toilet"),
}

# Realistic scenes only (anchored confusions, docs/synthetic.md): the classes a 2D model confuses each class
# with in a real capture, where the errors stay between related classes: counter / cabinet / desk / table (flat
# tops and fronts of furniture), door / wall, window / curtain / wall. Kept apart from CONFUSABLE, which the
# older presets draw from, so that their bytes do not change. A class without entries never leans.
RELATED: dict[str, tuple[str, ...]] = {
    "wall": ("door", "curtain", "window"),
    "floor": (),
    "ceiling": ("wall",),
    "cabinet": ("counter", "desk", "table"),
    "bed": ("sofa",),
    "chair": ("sofa",),
    "sofa": ("bed", "chair"),
    "table": ("desk", "counter", "cabinet"),
    "door": ("wall", "cabinet"),
    "window": ("curtain", "wall"),
    "bookshelf": ("cabinet",),
    "picture": ("window",),
    "counter": ("cabinet", "table", "desk"),
    "desk": ("table", "cabinet", "counter"),
    "curtain": ("window", "wall"),
    "refrigerator": ("cabinet", "door"),
    "toilet": ("sink",),
    "sink": ("counter", "toilet"),
    "bathtub": ("sink",),
}

# Row of each Matterport-21 class in MATTERPORT_LABELS_21_dim512.npy (label_sets/README.md).
_MP21 = (
    "wall floor cabinet bed chair sofa table door window bookshelf picture counter desk curtain refrigerator "
    "shower_curtain toilet sink bathtub other ceiling"
).split()


def confusion_targets(related: bool = False) -> tuple[np.ndarray, np.ndarray]:  # (L, C) int64, (L,) int64
    """Per class, the indices of its confusable classes (padded with -1) and how many there are.

    Args:
        related: Take :data:`RELATED` (realistic scenes) rather than :data:`CONFUSABLE`.
    """
    source = RELATED if related else CONFUSABLE
    width = max(len(v) for v in source.values())
    table = np.full((len(CLASS_NAMES), width), -1, dtype=np.int64)
    for i, name in enumerate(CLASS_NAMES):
        table[i, : len(source[name])] = [CLASS_ID[c] for c in source[name]]
    return table, (table >= 0).sum(axis=1)


def clip_label_embeddings() -> np.ndarray:  # (L, 512) float32, unit rows
    """The CLIP ViT-B/32 rows of the catalogue classes, from the shipped Matterport-21 label set."""
    ref = resources.files("panogs_core") / "data" / "label_sets" / "MATTERPORT_LABELS_21_dim512.npy"
    with resources.as_file(ref) as path:
        table = np.load(path, allow_pickle=False).astype(np.float32)
    rows = table[[_MP21.index(n) for n in CLASS_NAMES]]
    return rows / np.linalg.norm(rows, axis=1, keepdims=True)


def label_embeddings(feature_space: str) -> np.ndarray:  # (L, D) float32, unit rows
    """Text embeddings of the catalogue in a feature space.

    Args:
        feature_space: ``clip-vit-b32`` (shipped label-set rows) or ``minilm-l6`` (the offline sentence
            encoder through :func:`panogs_core.language.text_encoders.encode_labels`).

    Raises:
        EncoderUnavailableError: for ``minilm-l6`` without the text extra installed.
        ValueError: for another space.
    """
    if feature_space == "clip-vit-b32":
        return clip_label_embeddings()
    if feature_space == "minilm-l6":
        from panogs_core.language.text_encoders import encode_labels, get_text_encoder

        emb = encode_labels(get_text_encoder("minilm-l6"), list(CLASS_NAMES))
        return np.asarray(emb, dtype=np.float32)
    raise ValueError(f"feature_space must be 'clip-vit-b32' or 'minilm-l6', got {feature_space!r}")


def catalogue_vocabulary(embeddings: np.ndarray | None = None) -> Vocabulary:
    """The catalogue as a :class:`Vocabulary` (optionally with ``(L, D)`` embeddings)."""
    return Vocabulary(names=CLASS_NAMES, kinds=CLASS_KINDS, embeddings=embeddings)


def class_noise_scale(embeddings: np.ndarray) -> np.ndarray:  # (L,) float32
    """Per class, the median Euclidean distance from its unit embedding to the other classes' embeddings.

    The unit of the feature noise model. A perturbation of half the distance to another class, along the line
    to it, flips the argmax to that class; measuring noise against the median distance (rather than the
    nearest) gives the same pixel error rate for the same noise numbers in spaces as different as CLIP (rows
    0.35-0.7 apart, a few close pairs) and MiniLM (rows 0.9-1.2 apart, many at a similar distance).
    """
    emb = embeddings / np.linalg.norm(embeddings, axis=1, keepdims=True)
    dist = np.sqrt(np.maximum(2.0 - 2.0 * (emb @ emb.T), 0.0))
    others = dist[~np.eye(len(emb), dtype=bool)].reshape(len(emb), len(emb) - 1)
    return np.median(others, axis=1).astype(np.float32)
