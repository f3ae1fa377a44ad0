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

from collections.abc import Callable
from dataclasses import dataclass, fields

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


def rms_norm(x: torch.Tensor, weight: torch.Tensor, eps: float) -> torch.Tensor:
    """`PiGemmaRMSNorm(x)` without a condition."""
    return (_rms(x, eps) * (1.0 + weight.float())).type_as(x)


def add_rms_norm(hidden, update, weight, eps: float):
    """Residual add, then the next RMSNorm: returns (new hidden, its normalized copy)."""
    hidden = hidden + update
    return hidden, rms_norm(hidden, weight, eps)


def ada_rms_norm(x: torch.Tensor, modulation: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """`PiGemmaRMSNorm(x, cond)` given `modulation = norm.dense(cond)` (B x 3D), computed ahead."""
    scale, shift, gate = modulation.unsqueeze(1).chunk(3, dim=-1)
    normed = _rms(x, eps) * (1 + scale.float()) + shift.float()
    return normed.to(x.dtype), gate.to(x.dtype)


def gated_add_ada_rms_norm(hidden, update, gate, modulation, eps: float):
    """Gated residual `hidden + update * gate`, then the next AdaRMSNorm: (new hidden, normed, gate)."""
    hidden = hidden + update * gate
    return (hidden, *ada_rms_norm(hidden, modulation, eps))


def gelu_tanh_mul(gate: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """GemmaMLP's `act_fn(gate_proj(x)) * up_proj(x)` with Gemma's `gelu_pytorch_tanh`."""
    return F.gelu(gate, approximate="tanh") * up


@dataclass(frozen=True)
class ElementwiseOps:
    """The arithmetic between matrix products, swappable for compiled (fused) versions."""

    rms_norm: Callable = rms_norm
    add_rms_norm: Callable = add_rms_norm
    ada_rms_norm: Callable = ada_rms_norm
    gated_add_ada_rms_norm: Callable = gated_add_ada_rms_norm
    rotary: Callable = apply_rotary_pos_emb
    gelu_tanh_mul: Callable = gelu_tanh_mul


EAGER_OPS = ElementwiseOps()


def compiled_ops() -> ElementwiseOps:
    """Each elementwise op compiled on its own by inductor (seconds per op and shape, not minutes
    like the whole loop), so a norm, residual or rotary becomes one or two kernels."""
    return ElementwiseOps(**{f.name: torch.compile(getattr(EAGER_OPS, f.name), dynamic=False)
                             for f in fields(ElementwiseOps)})


def _project_qkv(attn: nn.Module, hidden, cos, sin, kv, start: int, ops: ElementwiseOps):
    """q/k/v projections and rotary; this call's keys/values go into the `kv` buffers at `start`."""
    batch, length, _ = hidden.shape
    shape = (batch, length, -1, attn.head_dim)
    query = attn.q_proj(hidden).view(shape).transpose(1, 2)
    key = attn.k_proj(hidden).view(shape).transpose(1, 2)
    value = attn.v_proj(hidden).view(shape).transpose(1, 2)
    query, key = ops.rotary(query, key, cos, sin)
    kv[0][:, :, start : start + length].copy_(key)
    kv[1][:, :, start : start + length].copy_(value)
    return query


def _prefix_attention(attn: nn.Module, hidden, cos, sin, bias, kv, ops: ElementwiseOps):
    """Prefix self-attention through SDPA (memory-efficient kernel; 8 query heads share 1 KV head)."""
    batch, length, _ = hidden.shape
    query = _project_qkv(attn, hidden, cos, sin, kv, 0, ops)
    heads = query.shape[1]
    keys = kv[0][:, :, :length].expand(batch, heads, length, attn.head_dim)
    values = kv[1][:, :, :length].expand(batch, heads, length, attn.head_dim)
    out = F.scaled_dot_product_attention(query, keys, values, attn_mask=bias, scale=attn.scaling)
    return attn.o_proj(out.transpose(1, 2).reshape(batch, length, -1))


def _action_attention(attn: nn.Module, hidden, cos, sin, bias, kv, start: int, ops: ElementwiseOps):
    """Action tokens attending to prefix + action keys. With one KV head, all 8 heads' queries fold
    into one batched matrix product (8 x 50 rows against ~1000 keys): fused attention kernels
    parallelize over query blocks and leave the GPU mostly idle on 50 queries. Same arithmetic as
    Gemma's eager attention: scores * scaling + bias, float32 softmax, product with values."""
    batch, length, _ = hidden.shape
    query = _project_qkv(attn, hidden, cos, sin, kv, start, ops)
    heads, end = query.shape[1], start + length
    keys, values = kv[0][:, 0, :end], kv[1][:, 0, :end]  # B x end x head_dim
    scores = torch.bmm(query.reshape(batch, heads * length, -1), keys.transpose(1, 2))
    scores = scores.view(batch, heads, length, end) * attn.scaling + bias
    probs = torch.softmax(scores, dim=-1, dtype=torch.float32).to(values.dtype)
    out = torch.bmm(probs.view(batch, heads * length, end), values).view(batch, heads, length, -1)
    return attn.o_proj(out.transpose(1, 2).reshape(batch, length, -1))


def _mlp(mlp: nn.Module, x: torch.Tensor, ops: ElementwiseOps) -> torch.Tensor:
    """GemmaMLP, its three projections called as modules."""
    return mlp.down_proj(ops.gelu_tanh_mul(mlp.gate_proj(x), mlp.up_proj(x)))


def _layers_dtype(gemma_model: nn.Module) -> torch.dtype:
    """The activation dtype of a Gemma stack (lerobot casts hidden states to its q_proj dtype); for
    packed real-kernel layers (`quant.kernels`), their floating output/compute dtype."""
    q_proj = gemma_model.layers[0].self_attn.q_proj
    weight = getattr(q_proj, "weight", None)
    if isinstance(weight, torch.Tensor) and weight.is_floating_point() and weight.element_size() > 1:
        return weight.dtype
    return getattr(q_proj, "out_dtype", None) or getattr(q_proj, "compute_dtype", None) or torch.bfloat16


def _new_cache(gemma_model: nn.Module, batch: int, length: int, device, dtype) -> list[tuple[torch.Tensor, torch.Tensor]]:
    attn = gemma_model.layers[0].self_attn
    kv_heads = attn.k_proj.out_features // attn.head_dim
    shape = (batch, kv_heads, length, attn.head_dim)
    return [(torch.empty(shape, device=device, dtype=dtype), torch.empty(shape, device=device, dtype=dtype))
            for _ in gemma_model.layers]


@torch.no_grad()
def prefix_cache(model: nn.Module, images, img_masks, tokens, masks, suffix_len: int, ops: ElementwiseOps = EAGER_OPS):
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
    layers = lm.layers
    normed = ops.rms_norm(hidden, layers[0].input_layernorm.weight, layers[0].input_layernorm.eps)
    for index, (layer, kv) in enumerate(zip(layers, cache, strict=True)):
        attn_out = _prefix_attention(layer.self_attn, normed, cos, sin, bias, kv, ops)
        post = layer.post_attention_layernorm
        hidden, normed = ops.add_rms_norm(hidden, attn_out, post.weight, post.eps)
        mlp_out = _mlp(layer.mlp, normed, ops)
        if index + 1 < len(layers):
            nxt = layers[index + 1].input_layernorm
            hidden, normed = ops.add_rms_norm(hidden, mlp_out, nxt.weight, nxt.eps)
    return cache, pad


@torch.no_grad()
def sample_actions(model: nn.Module, images, img_masks, tokens, masks, noise, times, ops: ElementwiseOps = EAGER_OPS):
    """A whole chunk: prefix pass, then one Euler step per row of `times` (see `flow_times`)."""
    config = model.config
    expert = model.paligemma_with_expert.gemma_expert.model
    batch, chunk = noise.shape[:2]
    steps = times.shape[0]
    cache, prefix_pad = prefix_cache(model, images, img_masks, tokens, masks, suffix_len=chunk, ops=ops)
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
    layers = expert.layers
    for step in range(steps):
        hidden = model.action_in_proj(x_t).to(dtype)
        normed, gate = ops.ada_rms_norm(hidden, modulations[0][0][step], layers[0].input_layernorm.eps)
        for index, (layer, kv, (_, mod_post)) in enumerate(zip(layers, cache, modulations, strict=True)):
            attn_out = _action_attention(layer.self_attn, normed, cos, sin, bias, kv, prefix_len, ops)
            eps = layer.post_attention_layernorm.eps
            hidden, normed, next_gate = ops.gated_add_ada_rms_norm(hidden, attn_out, gate, mod_post[step], eps)
            mlp_out = _mlp(layer.mlp, normed, ops)
            if index + 1 < len(layers):
                nxt_mod, nxt_eps = modulations[index + 1][0][step], layers[index + 1].input_layernorm.eps
            else:
                nxt_mod, nxt_eps = final_modulation[step], expert.norm.eps
            hidden, normed, gate = ops.gated_add_ada_rms_norm(hidden, mlp_out, next_gate, nxt_mod, nxt_eps)
        velocity = model.action_out_proj(normed[:, -config.chunk_size :].to(torch.float32))
        x_t = x_t + dt * velocity
    return x_t
