"""Tiny SAM and CLIP models with random weights, saved as ``save_pretrained`` saves a real checkpoint: a user's
model folder in miniature, loaded through exactly the path a real one takes (meaningless maps, real code)."""

from __future__ import annotations

import json
from pathlib import Path

# Random weights score every mask near 0: keep them all, so that the painting and the crops run.
KEEP_ALL = {"pred_iou_thresh": -1.0, "stability_score_thresh": 0.0, "min_mask_fraction": 0.0}
# The ``maps2d`` settings of a run on the tiny models: every mask kept, a 4x4 grid, the tiny models' small images.
TINY_MAPS = {**KEEP_ALL, "points_per_side": 4, "max_masks": 8, "mask_long_side": 64, "feature_long_side": 16}


def _byte_alphabet() -> list[str]:
    """The 256 printable stand-ins of the bytes used by byte-level BPE (GPT-2 / CLIP convention)."""
    printable = {*range(ord("!"), ord("~") + 1), *range(ord("¡"), ord("¬") + 1), *range(ord("®"), ord("ÿ") + 1)}
    shifted = iter(range(256, 512))
    return [chr(b) if b in printable else chr(next(shifted)) for b in range(256)]


def tiny_clip(folder: Path, *, seed: int = 0, projection_dim: int = 12) -> Path:
    """A random tiny CLIP model, its image processor and a tiny BPE tokenizer, saved into ``folder``."""
    import torch
    from transformers import CLIPConfig, CLIPImageProcessorPil, CLIPModel

    alphabet = _byte_alphabet()
    merges = ["c h", "ch a", "cha i", "chai r</w>"]
    tokens = [*alphabet, *(c + "</w>" for c in alphabet), "ch", "cha", "chai", "chair</w>"]
    tokens += ["<|startoftext|>", "<|endoftext|>"]
    vocab = {t: i for i, t in enumerate(tokens)}
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "vocab.json").write_text(json.dumps(vocab))
    (folder / "merges.txt").write_text("#version: 0.2\n" + "\n".join(merges) + "\n")
    special = {
        "bos_token_id": vocab["<|startoftext|>"],
        "eos_token_id": vocab["<|endoftext|>"],
        "pad_token_id": vocab["<|endoftext|>"],
    }
    config = CLIPConfig(
        text_config={
            "vocab_size": len(vocab),
            "hidden_size": 16,
            "intermediate_size": 32,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "max_position_embeddings": 16,
            **special,
        },
        vision_config={
            "hidden_size": 16,
            "intermediate_size": 32,
            "num_hidden_layers": 1,
            "num_attention_heads": 2,
            "image_size": 16,
            "patch_size": 8,
        },
        projection_dim=projection_dim,
    )
    torch.manual_seed(seed)
    CLIPModel(config).save_pretrained(folder)
    CLIPImageProcessorPil(size={"shortest_edge": 16}, crop_size={"height": 16, "width": 16}).save_pretrained(folder)
    return folder


def tiny_sam(folder: Path, *, seed: int = 0) -> Path:
    """A random tiny SAM (SlimSAM and SAM ViT-B/H share its classes) and its processor, saved into ``folder``."""
    import torch
    from transformers import SamConfig, SamImageProcessorPil, SamModel

    config = SamConfig(
        vision_config={
            "hidden_size": 16,
            "output_channels": 16,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "image_size": 64,
            "patch_size": 8,
            "mlp_dim": 32,
            "global_attn_indexes": [1],
            "window_size": 4,
            "num_pos_feats": 8,
        },
        prompt_encoder_config={"hidden_size": 16, "image_size": 64, "patch_size": 8, "mask_input_channels": 4},
        mask_decoder_config={
            "hidden_size": 16,
            "num_hidden_layers": 2,
            "num_attention_heads": 2,
            "mlp_dim": 32,
            "iou_head_hidden_dim": 16,
        },
    )
    torch.manual_seed(seed)
    SamModel(config).save_pretrained(folder)
    SamImageProcessorPil(
        size={"longest_edge": 64},
        pad_size={"height": 64, "width": 64},
        mask_size={"longest_edge": 16},
        mask_pad_size={"height": 16, "width": 16},
    ).save_pretrained(folder)
    return folder
