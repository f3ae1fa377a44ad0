"""pi0.5 action sampling written so that one chunk is a fixed sequence of device operations.

Mirrors lerobot 0.6.1 `PI05Pytorch.sample_actions` (prefix pass that fills the KV cache, then
`num_steps` Euler steps of the action expert) with the same modules, weights and dtypes, but:

* no host work inside: masks and positions come from the input tensors by tensor ops (lerobot
  builds them from Python lists, a host-to-device copy that cannot be captured), and the flow
  timesteps live in a device buffer made before capture;
* what does not change between Euler steps is computed once per chunk: the attention bias, the
  rotary tables, the time embedding MLP and every AdaRMS modulation (`*.dense(cond)`) -- one call
  on all steps' rows instead of one per step; per-token activation quantization works row by row,
  so quantized results are the same;
* the KV cache is one preallocated buffer per layer whose action-token slots are overwritten each
  step (lerobot clones a `DynamicCache` and concatenates every step);
* attention runs through `scaled_dot_product_attention`, not the eager matmul-softmax-matmul
  lerobot forces;
* the (Ada)RMSNorm and gated-residual arithmetic is written out here (same float32 formulas as
  lerobot's `PiGemmaRMSNorm`), so a compiler can fuse it.

Every linear layer is still called as a module, so quantization hooks installed on it run (and a
captured graph records what they launch). `tests/test_accel_pi05.py` checks the result against
lerobot's own `sample_actions` on the demo model.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.common.vla_utils import create_sinusoidal_pos_embedding
from lerobot.utils.constants import OPENPI_ATTENTION_MASK_VALUE
from torch import nn
from transformers.models.gemma.modeling_gemma import apply_rotary_pos_emb


def flow_times(num_steps: int, device: torch.device) -> torch.Tensor:
    """The Euler timesteps 1, 1 - 1/n, ... as lerobot's `euler_integrate` computes them, one row each."""
    dt = -1.0 / num_steps
    return torch.tensor([[1.0 + step * dt] for step in range(num_steps)], dtype=torch.float32, device=device)


def _attention_bias(allowed: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Additive mask as openpi uses it (a large negative number, not -inf, so fully padded query
    rows stay finite instead of turning into NaN), shaped B x 1 x Q x K for SDPA."""
    zero = torch.zeros((), dtype=dtype, device=allowed.device)
    blocked = torch.full((), OPENPI_ATTENTION_MASK_VALUE, dtype=dtype, device=allowed.device)
    return torch.where(allowed[:, None], zero, blocked)


def _rms(x: torch.Tensor, eps: float) -> torch.Tensor:
    return x * torch.rsqrt(torch.mean(torch.square(x.float()), dim=-1, keepdim=True) + eps)


def rms_norm(norm: nn.Module, x: torch.Tensor) -> tuple[torch.Tensor, None]:
    """`PiGemmaRMSNorm(x)` without a condition."""
    return (_rms(x, norm.eps) * (1.0 + norm.weight.float())).type_as(x), None


def ada_rms_norm(norm: nn.Module, x: torch.Tensor, modulation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """`PiGemmaRMSNorm(x, cond)` given `modulation = norm.dense(cond)` (B x 3D), computed ahead."""
    scale, shift, gate = modulation.unsqueeze(1).chunk(3, dim=-1)
    normed = _rms(x, norm.eps) * (1 + scale.float()) + shift.float()
    return normed.to(x.dtype), gate.to(x.dtype)


def _gated_residual(x: torch.Tensor, y: torch.Tensor, gate: torch.Tensor | None) -> torch.Tensor:
    return x + y if gate is None else x + y * gate


def _attention(attn: nn.Module, hidden, cos, sin, bias, kv: tuple[torch.Tensor, torch.Tensor], start: int):
    """GemmaAttention: projections, rotary, write this call's keys/values into `kv` at `start`,
    attend over kv[:, :, :start + length] with SDPA, o_proj."""
    batch, length, _ = hidden.shape
    shape = (batch, length, -1, attn.head_dim)
    query = attn.q_proj(hidden).view(shape).transpose(1, 2)
    key = attn.k_proj(hidden).view(shape).transpose(1, 2)
    value = attn.v_proj(hidden).view(shape).transpose(1, 2)
    query, key = apply_rotary_pos_emb(query, key, cos, sin)
    end = start + length
    kv[0][:, :, start:end].copy_(key)
    kv[1][:, :, start:end].copy_(value)
    heads = query.shape[1]
    # Grouped-query attention (8 query heads, 1 KV head): broadcast views, no copy.
    keys = kv[0][:, :, :end].expand(batch, heads, end, attn.head_dim)
    values = kv[1][:, :, :end].expand(batch, heads, end, attn.head_dim)
    out = F.scaled_dot_product_attention(query, keys, values, attn_mask=bias, scale=attn.scaling)
    return attn.o_proj(out.transpose(1, 2).reshape(batch, length, -1))


def _mlp(mlp: nn.Module, x: torch.Tensor) -> torch.Tensor:
    """GemmaMLP, its three projections called as modules."""
    return mlp.down_proj(mlp.act_fn(mlp.gate_proj(x)) * mlp.up_proj(x))


def _layers_dtype(gemma_model: nn.Module) -> torch.dtype:
    return gemma_model.layers[0].self_attn.q_proj.weight.dtype


def _new_cache(gemma_model: nn.Module, batch: int, length: int, device, dtype) -> list[tuple[torch.Tensor, torch.Tensor]]:
    attn = gemma_model.layers[0].self_attn
    kv_heads = attn.k_proj.out_features // attn.head_dim
    shape = (batch, kv_heads, length, attn.head_dim)
    return [(torch.empty(shape, device=device, dtype=dtype), torch.empty(shape, device=device, dtype=dtype))
            for _ in gemma_model.layers]


@torch.no_grad()
def prefix_cache(model: nn.Module, images, img_masks, tokens, masks, suffix_len: int):
    """Run the VLM over images and prompt; return per-layer KV buffers (prefix filled, `suffix_len`
    free slots after it) and the prefix pad mask."""
    pwe = model.paligemma_with_expert
    embs, pads = [], []
    for img, img_mask in zip(images, img_masks, strict=True):
        emb = pwe.embed_image(img)
        embs.append(emb)
        pads.append(img_mask[:, None].expand(emb.shape[0], emb.shape[1]))
    embs.append(pwe.embed_language_tokens(tokens))
    pads.append(masks)
    pad = torch.cat(pads, dim=1)
    lm = pwe.paligemma.model.language_model
    dtype = _layers_dtype(lm)
    hidden = torch.cat(embs, dim=1).to(dtype)
    batch, length = pad.shape
    # Every prefix token has autoregressive mask 0, so each attends to every non-padding prefix token.
    bias = _attention_bias(pad[:, None, :] & pad[:, :, None], dtype)
    cos, sin = lm.rotary_emb(hidden, torch.cumsum(pad, dim=1) - 1)
    cache = _new_cache(lm, batch, length + suffix_len, hidden.device, dtype)
    for layer, kv in zip(lm.layers, cache, strict=True):
        normed, _ = rms_norm(layer.input_layernorm, hidden)
        hidden = hidden + _attention(layer.self_attn, normed, cos, sin, bias, kv, 0)
        normed, _ = rms_norm(layer.post_attention_layernorm, hidden)
        hidden = hidden + _mlp(layer.mlp, normed)
    return cache, pad


@torch.no_grad()
def sample_actions(model: nn.Module, images, img_masks, tokens, masks, noise, times):
    """A whole chunk: prefix pass, then one Euler step per row of `times` (see `flow_times`)."""
    config = model.config
    expert = model.paligemma_with_expert.gemma_expert.model
    batch, chunk = noise.shape[:2]
    steps = times.shape[0]
    cache, prefix_pad = prefix_cache(model, images, img_masks, tokens, masks, suffix_len=chunk)
    prefix_len = prefix_pad.shape[1]

    # Per-chunk constants: time conditioning and AdaRMS modulations of all steps, bias, rotary.
    step_times = times.expand(steps, batch).reshape(-1)
    time_emb = create_sinusoidal_pos_embedding(
        step_times, model.action_in_proj.out_features, config.min_period, config.max_period, device=times.device
    ).type(times.dtype)
    cond = F.silu(model.time_mlp_out(F.silu(model.time_mlp_in(time_emb))))
    modulations = [(layer.input_layernorm.dense(cond).view(steps, batch, -1),
                    layer.post_attention_layernorm.dense(cond).view(steps, batch, -1)) for layer in expert.layers]
    final_modulation = expert.norm.dense(cond).view(steps, batch, -1)
    # Action tokens see every non-padding prefix token and each other (one autoregressive block).
    allowed = torch.cat(
        [prefix_pad[:, None, :].expand(batch, chunk, prefix_len),
         torch.ones(batch, chunk, chunk, dtype=torch.bool, device=prefix_pad.device)],
        dim=2,
    )
    dtype = _layers_dtype(expert)
    bias = _attention_bias(allowed, dtype)
    positions = prefix_pad.sum(dim=-1, keepdim=True) + torch.arange(chunk, device=prefix_pad.device)[None]
    cos, sin = expert.rotary_emb(noise.to(dtype), positions)

    dt = -1.0 / steps
    x_t = noise
    for step in range(steps):
        hidden = model.action_in_proj(x_t).to(dtype)
        for layer, kv, (mod_in, mod_post) in zip(expert.layers, cache, modulations, strict=True):
            normed, gate = ada_rms_norm(layer.input_layernorm, hidden, mod_in[step])
            hidden = _gated_residual(hidden, _attention(layer.self_attn, normed, cos, sin, bias, kv, prefix_len), gate)
            normed, gate = ada_rms_norm(layer.post_attention_layernorm, hidden, mod_post[step])
            hidden = _gated_residual(hidden, _mlp(layer.mlp, normed), gate)
        hidden, _ = ada_rms_norm(expert.norm, hidden, final_modulation[step])
        velocity = model.action_out_proj(hidden[:, -config.chunk_size :].to(torch.float32))
        x_t = x_t + dt * velocity
    return x_t
