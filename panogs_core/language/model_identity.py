"""Where a 2D model's files are, what identifies them, and the feature space a CLIP-family model names.

A model is named by the user as a folder in the Hugging Face layout (``config.json``, the weights, the processor's
files, as ``save_pretrained`` writes them) or as a hub name (``openai/clip-vit-base-patch16``), which resolves to
the hub cache's folder, offline unless the caller allows a download. Its identity is a hash of its files' contents
and names, never its path: the same weights copied elsewhere keep their checkpoints, other weights at the same
path do not.

Reads files and JSON only (no torch), so the API process can name spaces and check model entries.
"""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

from panogs_core.errors import InputError

# The files whose contents decide a model's outputs: its weights, its architecture and its pre-processing.
# Tokenizer files join for the text tower (a CLIP space covers both towers).
WEIGHT_SUFFIXES = (".safetensors", ".bin", ".pt", ".pth")
CONFIG_FILES = ("config.json", "preprocessor_config.json", "processor_config.json")
TOKENIZER_FILES = ("vocab.json", "merges.txt", "tokenizer.json", "tokenizer_config.json", "special_tokens_map.json")
_CHUNK = 1 << 20
_HUB_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]*/[A-Za-z0-9][A-Za-z0-9._-]*")


class ModelLoadError(InputError):
    """A 2D model cannot be loaded; the message names the model's place and what is missing."""


def resolve_model_dir(name_or_path: str | Path, *, allow_download: bool = False) -> Path:
    """The local folder of a model: the folder itself, or a hub name's snapshot in the local hub cache.

    Args:
        name_or_path: A folder in the Hugging Face layout, or a hub name ``owner/name``.
        allow_download: Fetch a hub name missing from the cache (only where the user asked for it and a
            network exists). Never used for a folder.

    Raises:
        ModelLoadError: naming the path or hub name and what is missing.
    """
    text = str(name_or_path)
    path = Path(text).expanduser()
    if path.is_dir():
        if not (path / "config.json").is_file():
            raise ModelLoadError(f"{text}: no config.json; expected a model folder as save_pretrained writes it")
        if not weight_files(path):
            raise ModelLoadError(
                f"{text}: no weights ({', '.join('*' + s for s in WEIGHT_SUFFIXES)}); expected a model folder "
                "as save_pretrained writes it"
            )
        return path
    if not _HUB_NAME.fullmatch(text) or path.exists():
        raise ModelLoadError(f"{text}: not a folder, and not a hub name of the form owner/name")
    try:
        from huggingface_hub import snapshot_download
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise ModelLoadError(f"{text}: a hub name needs huggingface_hub (pip install 'panogs[maps2d]')") from exc
    try:
        folder = snapshot_download(text, local_files_only=not allow_download)
    except Exception as exc:  # the hub client raises many types for "not in the cache" and "no network"
        how = "not in the local hub cache and downloads are off" if not allow_download else "could not be fetched"
        raise ModelLoadError(f"{text}: {how} ({type(exc).__name__}); give a local folder instead") from exc
    return resolve_model_dir(folder)


def weight_files(folder: Path) -> list[Path]:
    """The weight files of a model folder, sorted by name."""
    return sorted(p for p in folder.iterdir() if p.is_file() and p.name.endswith(WEIGHT_SUFFIXES))


def model_hash(folder: str | Path, *, with_tokenizer: bool = False) -> str:
    """SHA-256 (hex) of a model folder's weights, config and processor files: names and contents, not the path.

    Args:
        folder: A resolved model folder (:func:`resolve_model_dir`).
        with_tokenizer: Cover the tokenizer's files too (a text tower's identity).
    """
    root = Path(folder)
    names = [p.name for p in weight_files(root)]
    names += [n for n in CONFIG_FILES if (root / n).is_file()]
    if with_tokenizer:
        names += [n for n in TOKENIZER_FILES if (root / n).is_file()]
    digest = hashlib.sha256()
    for name in sorted(names):
        digest.update(name.encode() + b"\0")
        with open(root / name, "rb") as fh:
            while chunk := fh.read(_CHUNK):
                digest.update(chunk)
        digest.update(b"\0")
    return digest.hexdigest()


def read_config(folder: Path) -> dict[str, object]:
    """A model folder's ``config.json`` as a dict.

    Raises:
        ModelLoadError: the file is missing or not a JSON object.
    """
    try:
        data = json.loads((folder / "config.json").read_text())
    except (OSError, ValueError) as exc:
        raise ModelLoadError(f"{folder}: config.json unreadable: {exc}") from exc
    if not isinstance(data, dict):
        raise ModelLoadError(f"{folder}: config.json is not a JSON object")
    return data


# ViT widths of the published CLIP image towers: B 768, L 1024, H 1280, g 1408, G 1664.
_VIT_SIZES = {768: "b", 1024: "l", 1280: "h", 1408: "g", 1664: "bigg"}
SPACE_HASH_CHARS = 16  # 64 bits of the weights' hash in a space name


def clip_space(folder: str | Path) -> str:
    """The feature space a CLIP-family model's image tower writes: ``<family>-vit-<size><patch>[-<res>]@<hash>``.

    The architecture part is for people (``clip-vit-b16``, ``clip-vit-l14-336``); the
    hash (the first 16 hex digits of :func:`model_hash` with the tokenizer) names the exact weights, so two
    fine-tunes of one architecture never share a space and a query's text tower can be checked against it.

    Raises:
        ModelLoadError: the folder's config is not a CLIP-family model's.
    """
    root = Path(folder)
    config = read_config(root)
    family = config.get("model_type")
    vision = config.get("vision_config")
    if family != "clip" or not isinstance(vision, dict):
        raise ModelLoadError(f"{root}: config.json model_type {family!r}, expected a CLIP model ('clip')")
    width = int(vision.get("hidden_size", 768))
    patch = int(vision.get("patch_size", 32))
    resolution = int(vision.get("image_size", 224))
    size = _VIT_SIZES.get(width)
    tower = f"{size}{patch}" if size else f"w{width}p{patch}"  # an unpublished width: w<width>p<patch>
    arch = f"{family}-vit-{tower}" + ("" if resolution == 224 else f"-{resolution}")
    return f"{arch}@{model_hash(root, with_tokenizer=True)[:SPACE_HASH_CHARS]}"


def split_space(space: str) -> tuple[str, str | None]:
    """``(architecture, hash or None)`` of a space name: ``clip-vit-b16@0123...`` -> ``("clip-vit-b16", "0123...")``."""
    arch, sep, digest = space.partition("@")
    return arch, (digest if sep else None)
