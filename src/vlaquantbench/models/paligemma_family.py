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
from vlaquantbench.quant.rotation import ResidualStream, declare_stream

_VLM = "paligemma_with_expert.paligemma.model"
_EXPERT = "paligemma_with_expert.gemma_expert"
EXPERT_DECODER = f"{_EXPERT}.model"

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


def pi_components(action_projections: Sequence[str],
                  expert_stream: Callable[[nn.Module], tuple] | None = None) -> dict[str, Component]:
    """Component scopes of a pi-family policy whose expert-side projections are `action_projections`;
    `expert_stream(model)` declares the expert's residual stream where its norms fold (pi0's plain
    RMSNorms; pi0.5's adaptive ones do not). The VLM's Gemma stream always folds (`vlm_stream`); the
    SigLIP tower's LayerNorms (a mean subtracted, a bias added) do not, and it is rotated online."""
    return {
        "ve": Component(roots=(f"{_VLM}.vision_tower",)),
        "mp": Component(roots=(f"{_VLM}.multi_modal_projector",)),
        "llm": Component(roots=(f"{_VLM}.language_model",), residual_streams=vlm_stream),
        # The expert's lm_head is a vocabulary head that inference never calls: never quantized.
        "ah": Component(roots=(_EXPERT, *action_projections), never=("*lm_head",), residual_streams=expert_stream),
    }


# Gemma's RMSNorm computes x / rms(x) * (1 + w): gain offset 1.
GEMMA_GAIN_OFFSET = 1.0


def gemma_stream(model: nn.Module, name: str, root: str, writers: Sequence[str],
                 final_readers: Sequence[str] = ()) -> ResidualStream:
    """The residual stream of the Gemma decoder at `root` (`<root>.layers.<i>`): written by `writers`
    (embeddings, projections) and each layer's o_proj and down_proj, read through each layer's
    input_layernorm (q/k/v) and post_attention_layernorm (gate/up), and through the final
    `<root>.norm` by `final_readers` (none: the norm's output is not on the action path)."""
    depth = len(model.get_submodule(f"{root}.layers"))
    layers = [f"{root}.layers.{i}" for i in range(depth)]
    norms = [norm for layer in layers for norm in (
        (f"{layer}.input_layernorm", [f"{layer}.self_attn.{p}_proj" for p in "qkv"]),
        (f"{layer}.post_attention_layernorm", [f"{layer}.mlp.gate_proj", f"{layer}.mlp.up_proj"]))]
    if final_readers:
        norms.append((f"{root}.norm", final_readers))
    writers = [*writers, *(f"{layer}.{w}" for layer in layers for w in ("self_attn.o_proj", "mlp.down_proj"))]
    return declare_stream(model, name, writers, norms, GEMMA_GAIN_OFFSET)


def vlm_stream(model: nn.Module) -> tuple[ResidualStream, ...]:
    """PaliGemma's Gemma stream: written by the token embedding and the multi-modal projector (a
    scalar scaling of either would commute with the rotation; lerobot 0.6.1 applies none). Its
    final norm is left unfolded: the prefix pass's last hidden state is discarded (only the KV
    cache reaches the action expert), and the vocabulary head reading it, tied to the embedding,
    is never called; both would see the rotated stream."""
    return (gemma_stream(model, "vlm", f"{_VLM}.language_model",
                         (f"{_VLM}.language_model.embed_tokens", f"{_VLM}.multi_modal_projector.linear")),)


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

