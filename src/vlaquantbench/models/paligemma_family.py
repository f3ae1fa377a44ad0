"""What pi0 and pi0.5 share: a PaliGemma VLM (SigLIP vision tower, projector, Gemma-2B LLM) plus a
Gemma-300M action expert, built by lerobot 0.6.1 as `PaliGemmaWithExpertModel`.

Both policies name their modules identically below `paligemma_with_expert`; they differ only in
the top-level action projections, which each model's `components.py` lists.
"""

from __future__ import annotations

import contextlib
import json
import types
from collections.abc import Callable, Sequence
from pathlib import Path
from unittest import mock

import torch
from torch import nn

from vlaquantbench.models.registry import Component, demo_build, seeded_build

_VLM = "paligemma_with_expert.paligemma.model"
_EXPERT = "paligemma_with_expert.gemma_expert"

# Demo sizes keep every depth, head count and the grouped-query layout (8 query heads, 1 KV head,
# shared between VLM and expert) so layer names and subset counts equal the full model's; only
# widths shrink. Vision keeps 224 px / patch 14, so the image token count is the released one.
DEMO_WIDTHS = {
    "gemma_2b": dict(width=64, depth=18, mlp_dim=256, num_heads=8, num_kv_heads=1, head_dim=16),
    "gemma_300m": dict(width=32, depth=18, mlp_dim=128, num_heads=8, num_kv_heads=1, head_dim=16),
    "vision": dict(hidden_size=64, intermediate_size=128, num_attention_heads=4, num_hidden_layers=27),
}
# A checkpoint folder holding this file was saved at reduced widths (the offline hub fixture,
# `vqb hub-fixture`): lerobot hard-codes the released widths, so loading it needs `reduced_widths`.
# Released checkpoints have no such file and load unpatched.
REDUCED_WIDTHS_FILE = "vlaquantbench_reduced_widths.json"
# A checkpoint trained here (`vlaquantbench.training`) holds its training provenance in this file.
TRAINING_FILE = "vlaquantbench_training.json"


def pi_components(action_projections: Sequence[str]) -> dict[str, Component]:
    """Component scopes of a pi-family policy whose expert-side projections are `action_projections`."""
    return {
        "ve": Component(roots=(f"{_VLM}.vision_tower",)),
        "mp": Component(roots=(f"{_VLM}.multi_modal_projector",)),
        "llm": Component(roots=(f"{_VLM}.language_model",)),
        # The expert's lm_head is a vocabulary head that inference never calls: never quantized.
        "ah": Component(roots=(_EXPERT, *action_projections), never=("*lm_head",)),
    }


def pi_builders(modeling: types.ModuleType, model_cls: type, config_cls: type) -> dict[str, Callable]:
    """`full` and `demo` builders for a lerobot pi-family core model (`PI05Pytorch`/`PI0Pytorch`)."""

    def full(device: torch.device, seed: int) -> nn.Module:
        config = config_cls(dtype="bfloat16", device="cpu")
        return seeded_build(lambda: model_cls(config), device, seed)

    def demo(device: torch.device, seed: int) -> nn.Module:
        config = config_cls(dtype="float32", device="cpu")
        with reduced_widths(modeling):
            return demo_build(lambda: model_cls(config), device, seed)

    return {"full": full, "demo": demo}


@contextlib.contextmanager
def reduced_widths(modeling: types.ModuleType, widths: dict[str, dict] = DEMO_WIDTHS):
    """Patch the two size sources lerobot hard-codes while a reduced-width model is constructed.

    lerobot accepts only the released Gemma variants (`get_gemma_config`) and sets the SigLIP MLP
    width and projector output inside `PaliGemmaWithExpertModel`, so this resizes the finished
    PaliGemma config just before the VLM is instantiated from it. `widths` maps each Gemma variant
    and "vision" to its sizes (`DEMO_WIDTHS`), and optionally "vocab_size" to the vocabulary of a
    small tokenizer shipped with the checkpoint: lerobot hard-codes PaliGemma's 257,152 entries for
    the VLM's embedding and the expert's (never called) vocabulary head, which alone would outweigh
    a small trained policy many times over.
    """
    real_vlm_cls = modeling.PaliGemmaForConditionalGenerationWithPiGemma
    real_expert_cls = modeling.PiGemmaForCausalLM
    vocab_size = widths.get("vocab_size")

    def demo_vlm(config):
        for key, value in widths["vision"].items():
            setattr(config.vision_config, key, value)
        config.vision_config.projection_dim = config.text_config.hidden_size
        if vocab_size is not None:  # as lerobot sets its own: image token just past the vocabulary
            config._vocab_size = config.text_config.vocab_size = config.image_token_index = vocab_size
        return real_vlm_cls(config=config)

    def demo_expert(config):
        if vocab_size is not None:
            config.vocab_size = vocab_size
        return real_expert_cls(config=config)

    def demo_gemma_config(variant: str):
        return modeling.GemmaConfig(**widths[variant])

    with (
        mock.patch.object(modeling, "PaliGemmaForConditionalGenerationWithPiGemma", demo_vlm),
        mock.patch.object(modeling, "PiGemmaForCausalLM", demo_expert),
        mock.patch.object(modeling, "get_gemma_config", demo_gemma_config),
    ):
        yield


def checkpoint_widths(modeling: types.ModuleType, folder: str | Path):
    """The context a checkpoint folder loads in: `reduced_widths` with the sizes its
    `REDUCED_WIDTHS_FILE` records, or nothing for a released checkpoint."""
    marker = Path(folder) / REDUCED_WIDTHS_FILE
    if not marker.exists():
        return contextlib.nullcontext()
    return reduced_widths(modeling, json.loads(marker.read_text()))

