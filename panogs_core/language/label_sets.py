"""Label sets (vocabularies): the two built-in indoor sets, ``vocabulary.json`` files, inline lists, embeddings.

A :class:`~panogs_core.types.Vocabulary` carries class names, a thing/stuff kind per class and, once resolved,
unit text embeddings ``(L, D)`` in the feature space of the scene (docs/method.md §1.6). The built-in sets ship the
OpenScene CLIP ViT-B/32 label embeddings of the official release (``data/label_sets/README.md``); any other
space re-embeds the names with its text encoder (:func:`ensure_embeddings`).

This module also owns the default softmax temperatures used to turn cosines against the vocabulary into
probabilities (instance scores in ``labeling``, query scores in ``query``), see :func:`default_temperature`.
"""

from __future__ import annotations

import re
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from panogs_core.bounded_json import read_json_file
from panogs_core.errors import EncoderUnavailableError, InputError
from panogs_core.language.text_encoders import TextEncoder, encode_labels, get_text_encoder
from panogs_core.types import ClassKind, Vocabulary

_LABEL_DIR = Path(__file__).resolve().parents[1] / "data" / "label_sets"
_SCANNET20 = (
    "wall",
    "floor",
    "cabinet",
    "bed",
    "chair",
    "sofa",
    "table",
    "door",
    "window",
    "bookshelf",
    "picture",
    "counter",
    "desk",
    "curtain",
    "refrigerator",
    "shower curtain",
    "toilet",
    "sink",
    "bathtub",
    "otherfurniture",
)
_MATTERPORT21 = (*_SCANNET20[:19], "other", "ceiling")
# name -> (class names in row order, embedding file). Orders from data/label_sets/README.md (docs/method.md §1.6).
BUILTIN_VOCABULARIES: dict[str, tuple[tuple[str, ...], str]] = {
    "scannet20": (_SCANNET20, "SCANNET_LABELS_20.npy"),
    "matterport21": (_MATTERPORT21, "MATTERPORT_LABELS_21_dim512.npy"),
}
BUILTIN_SPACE = "clip-vit-b32"  # the space of the shipped embeddings
# The usual indoor panoptic split (README): these are stuff, every other class is a thing. "other" and
# "otherfurniture" are things here; the paper evaluation leaves them out of every average anyway.
STUFF_NAMES = frozenset({"wall", "floor", "ceiling"})

# Softmax temperature per feature space, in cosine units. Measured on the Matterport-21 label set: the
# largest round value at which every class, queried by its own name against a feature whose cosines to the
# label set are the class embedding's own cosines scaled by 0.3 (the cosine level of fused LSeg features to
# CLIP text), still gets probability >= 0.5 against the other 20 classes. CLIP: T=0.01 gives min 0.64 /
# median 0.82, T=0.015 gives min 0.37 (its classes are 0.68-0.94 similar to each other). MiniLM: T=0.05
# gives min 0.53 / median 0.67 (its classes are 0.09-0.85 similar, mean 0.34).
SPACE_TEMPERATURES = {"clip-vit-b32": 0.01, "minilm-l6": 0.05}
# Fallback for other spaces, from the spread of the vocabulary itself: T = 0.06 * (1 - mean inter-class
# cosine) reproduces the table above within 20 % (CLIP 0.172 -> 0.0103; MiniLM 0.661 -> 0.040).
_SPREAD_TO_TEMPERATURE = 0.06
_TEMPERATURE_RANGE = (0.002, 0.2)


def builtin_vocabulary(name: str, *, feature_space: str | None = None) -> Vocabulary:
    """One of the shipped label sets, with its CLIP ViT-B/32 embeddings.

    Args:
        name: ``scannet20`` or ``matterport21`` (case-insensitive).
        feature_space: The scene's feature space. When given and not ``clip-vit-b32`` the shipped embeddings
            belong to another space and are dropped (``ensure_embeddings`` then re-embeds the names).

    Returns:
        Classes in the README's row order; wall, floor and ceiling are stuff, the rest things; embeddings
        ``(L, 512)`` float32 with unit rows (the files are float16, so rows are re-normalised).

    Raises:
        InputError: unknown name.
    """
    key = name.strip().lower()
    if key not in BUILTIN_VOCABULARIES:
        raise InputError(
            f"vocabulary {describe_name(name)}: unknown built-in label set (known: {', '.join(BUILTIN_VOCABULARIES)})"
        )
    names, filename = BUILTIN_VOCABULARIES[key]
    kinds = tuple(default_kind(n) for n in names)
    if feature_space is not None and feature_space != BUILTIN_SPACE:
        return Vocabulary(names=names, kinds=kinds)
    emb = np.load(_LABEL_DIR / filename, allow_pickle=False)
    return Vocabulary(names=names, kinds=kinds, embeddings=_unit_rows(emb, source=filename))


def load_vocabulary_file(path: str | Path) -> Vocabulary:
    """Read a ``vocabulary.json`` (docs/scene_format.md §3) and the embeddings file it names, if any.

    ``kind`` may be left out of a class entry: it then defaults to stuff for wall/floor/ceiling, thing
    otherwise.

    Args:
        path: The JSON file. Its ``embeddings`` entry is a path relative to the JSON file's folder.

    Returns:
        The vocabulary; embeddings ``(L, D)`` float32 unit rows, or None when the file names none.

    Raises:
        InputError: unreadable file, bad JSON, missing/duplicate names, unknown kinds, or embeddings that are
            not a finite ``(L, D)`` array with non-zero rows.
    """
    path = Path(path)
    # The same bounded reader as a bundle's JSON files: a deep or huge file is a clear InputError, not a crash.
    doc = read_json_file(path, name=str(path))
    if not isinstance(doc, dict) or not isinstance(doc.get("classes"), list) or not doc["classes"]:
        raise InputError(f"{path}: expected {{'classes': [{{'name': ..., 'kind': ...}}, ...]}} with >= 1 class")
    names, kinds = _parse_classes(doc["classes"], source=str(path))
    embeddings = None
    if doc.get("embeddings") is not None:
        embeddings = _load_embeddings(path.parent, doc["embeddings"], len(names), source=str(path))
    return Vocabulary(names=names, kinds=kinds, embeddings=embeddings)


def is_builtin_name(spec: str) -> bool:
    """True when ``spec`` names a shipped label set (case-insensitive, surrounding blanks ignored)."""
    return spec.strip().lower() in BUILTIN_VOCABULARIES


# A value that looks like a label-set name is echoed in messages; anything else (a path, a long or odd string) is
# not, so that a message never repeats a host path (docs/service.md, "Which request fields reach the host").
_PLAIN_NAME = re.compile(r"[A-Za-z0-9_-]{1,64}")


def describe_name(spec: str) -> str:
    """``spec`` quoted when it looks like a label-set name, else a description that does not repeat it."""
    if _PLAIN_NAME.fullmatch(spec.strip()):
        return repr(spec.strip())
    return f"(a value of {len(spec)} characters that is not a label-set name)"


def inline_vocabulary(
    classes: Sequence[Mapping[str, Any]], embeddings: Sequence[Sequence[float]] | None = None, *, source: str
) -> Vocabulary:
    """A vocabulary from classes and vectors already in memory (a job's inline vocabulary); opens no file.

    Args:
        classes: ``[{"name": ..., "kind": "thing" | "stuff"}, ...]``; ``kind`` may be left out (stuff for
            wall/floor/ceiling, thing otherwise).
        embeddings: ``(L, D)`` rows, one per class, or None to embed the names later (:func:`ensure_embeddings`).
        source: Names the origin in messages (e.g. ``job <id> vocabulary``).

    Raises:
        InputError: no classes, blank or duplicate names, unknown kinds, or embeddings that are not a finite
            ``(L, D)`` array with non-zero rows.
    """
    if not classes:
        raise InputError(f"{source}: expected at least one class")
    names, kinds = _parse_classes(list(classes), source=source)
    if embeddings is None:
        return Vocabulary(names=names, kinds=kinds)
    try:
        emb = np.asarray(embeddings, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{source}: embeddings must be an (L, D) array of numbers: {exc}") from exc
    if emb.ndim != 2 or emb.shape[0] != len(names) or emb.shape[1] == 0:
        raise InputError(f"{source}: embeddings must be ({len(names)}, D), one row per class, found {emb.shape}")
    return Vocabulary(names=names, kinds=kinds, embeddings=_unit_rows(emb, source=f"{source}: embeddings"))


def vocabulary_from_name_or_file(spec: str, *, feature_space: str | None = None) -> Vocabulary:
    """For the CLI only (its user owns the disk): a built-in name or the path of a ``vocabulary.json``.

    The service never calls this: a job's vocabulary is a built-in name (:func:`builtin_vocabulary`) or an
    inline list of classes (:func:`inline_vocabulary`), so no request can make the worker open a file.

    Args:
        spec: Built-in name (case-insensitive) or path.
        feature_space: Passed to :func:`builtin_vocabulary` (drops CLIP embeddings in other spaces).

    Raises:
        InputError: neither a built-in name nor an existing file.
    """
    if is_builtin_name(spec):
        return builtin_vocabulary(spec, feature_space=feature_space)
    path = Path(spec)
    if not path.is_file():
        raise InputError(
            f"vocabulary {spec!r}: not a built-in label set ({', '.join(BUILTIN_VOCABULARIES)}) and no such file"
        )
    return load_vocabulary_file(path)


def ensure_embeddings(
    vocabulary: Vocabulary, feature_space: str, feature_dim: int, *, encoder: TextEncoder | None = None
) -> Vocabulary:
    """The vocabulary with embeddings in the scene's space: checked if present, computed if missing.

    Args:
        vocabulary: Any vocabulary.
        feature_space: ``features.space`` of the scene.
        feature_dim: ``features.dim`` (D) of the scene.
        encoder: Text encoder to use; default ``get_text_encoder(feature_space)``.

    Returns:
        A vocabulary whose embeddings are ``(L, feature_dim)`` float32 unit rows.

    Raises:
        InputError: the embeddings (given or computed) are not ``feature_dim`` wide.
        EncoderUnavailableError: names must be embedded but the space has no encoder on this machine.
    """
    if vocabulary.embeddings is not None:
        emb = np.asarray(vocabulary.embeddings)
        if emb.ndim != 2 or emb.shape[1] != feature_dim:
            raise InputError(
                f"vocabulary embeddings have shape {emb.shape} but the scene's {feature_space!r} features "
                f"are {feature_dim}-d; give embeddings of that space or leave them out to embed the names"
            )
        return Vocabulary(vocabulary.names, vocabulary.kinds, _unit_rows(emb, source="vocabulary embeddings"))
    if encoder is None:
        try:
            encoder = get_text_encoder(feature_space)
        except EncoderUnavailableError as exc:
            raise EncoderUnavailableError(
                f"the vocabulary has no embeddings and its names cannot be embedded: {exc}; provide "
                "vocabulary.npy in the scene's feature space"
            ) from exc
    emb = encode_labels(encoder, list(vocabulary.names))
    if emb.shape != (len(vocabulary.names), feature_dim):
        raise InputError(
            f"text encoder {encoder.space!r} gives {emb.shape[1]}-d embeddings but the scene's "
            f"{feature_space!r} features are {feature_dim}-d"
        )
    return Vocabulary(vocabulary.names, vocabulary.kinds, _unit_rows(emb, source=f"{encoder.space} encoder"))


def default_temperature(feature_space: str | None, embeddings: np.ndarray | None) -> float:
    """Softmax temperature (cosine units) for probabilities against a vocabulary.

    Args:
        feature_space: Known spaces use the measured ``SPACE_TEMPERATURES``; None or unknown falls back to the
            vocabulary's spread.
        embeddings: ``(L, D)`` unit rows, used by the fallback; None or a single class gives 0.05.

    Returns:
        A temperature > 0: ``0.06 * (1 - mean inter-class cosine)``, clipped to ``[0.002, 0.2]``, as fallback.
    """
    if feature_space in SPACE_TEMPERATURES:
        return SPACE_TEMPERATURES[feature_space]
    if embeddings is None or len(embeddings) < 2:
        return 0.05
    emb = _unit_rows(np.asarray(embeddings), source="embeddings")
    sims = emb @ emb.T
    n = len(emb)
    mean_off = (float(sims.sum()) - float(np.trace(sims))) / (n * (n - 1))
    return float(np.clip(_SPREAD_TO_TEMPERATURE * (1.0 - mean_off), *_TEMPERATURE_RANGE))


def default_kind(name: str) -> ClassKind:
    """The kind of a class whose entry names none: stuff for wall, floor and ceiling, thing otherwise."""
    return "stuff" if name.strip().lower() in STUFF_NAMES else "thing"


def _parse_classes(entries: list[Any], *, source: str) -> tuple[tuple[str, ...], tuple[ClassKind, ...]]:
    names: list[str] = []
    kinds: list[ClassKind] = []
    for i, entry in enumerate(entries):
        name = entry.get("name") if isinstance(entry, dict) else None
        if not isinstance(name, str) or not name.strip():
            raise InputError(f"{source}: classes[{i}] needs a non-empty string 'name', found {entry!r}")
        kind = entry.get("kind", default_kind(name))
        if kind not in ("thing", "stuff"):
            raise InputError(f"{source}: classes[{i}] ({name!r}) kind must be 'thing' or 'stuff', found {kind!r}")
        names.append(name.strip())
        kinds.append(kind)
    lowered = [n.lower() for n in names]
    duplicates = sorted({n for n in lowered if lowered.count(n) > 1})
    if duplicates:
        raise InputError(f"{source}: duplicate class names (case-insensitive): {duplicates}")
    return tuple(names), tuple(kinds)


def _load_embeddings(folder: Path, rel: Any, num_classes: int, *, source: str) -> np.ndarray:
    if not isinstance(rel, str) or Path(rel).is_absolute() or ".." in Path(rel).parts:
        raise InputError(f"{source}: 'embeddings' must be a relative path inside the folder, found {rel!r}")
    try:
        emb = np.load(folder / rel, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise InputError(f"{source}: cannot read embeddings {rel!r}: {exc}") from exc
    if emb.ndim != 2 or emb.shape[0] != num_classes or not np.issubdtype(emb.dtype, np.floating):
        raise InputError(
            f"{source}: embeddings {rel!r} must be a float ({num_classes}, D) array, found {emb.dtype} {emb.shape}"
        )
    return _unit_rows(emb, source=f"{source}: embeddings {rel!r}")


def _unit_rows(emb: np.ndarray, *, source: str) -> np.ndarray:  # (L, D) float32
    emb = np.asarray(emb, dtype=np.float32)
    norms = np.linalg.norm(emb, axis=1, keepdims=True)
    if not np.all(np.isfinite(emb)) or np.any(norms <= 1e-8):
        raise InputError(f"{source}: embeddings must be finite with non-zero rows")
    return np.ascontiguousarray(emb / norms)
