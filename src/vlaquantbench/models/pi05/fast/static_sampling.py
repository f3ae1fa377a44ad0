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
  step (lerobot clones a `DynamicCache` and concatenates every step), its length rounded up to a
  multiple of `KEY_ALIGNMENT` with zero keys and values that every query masks (`_aligned`);
* attention folds the 8 query heads that share one KV head into one batched product (or runs
  through `scaled_dot_product_attention` for the prefix, a kernel choice);
* the (Ada)RMSNorm and gated-residual arithmetic is written out here (same float32 formulas as
  lerobot's `PiGemmaRMSNorm`), so a compiler can fuse it;
* all cameras pass the vision tower as one batch, its encoder layers written out like the Gemma
  ones (LayerNorm and residual arithmetic as ops, q/k/v as one group);
* each SigLIP and Gemma layer's linears run as `linear_groups` groups (q/k/v as one
  product, gate/up as one), and where a group's quantizers only quantize per token, each
  member's quantizer quantizes inside the op that produces the group's input (the norm, the
  GELU, the head merge: `Ops.feed`, `ActivationQuantizer.fused`), so it fuses into that kernel (the
  GELUs carry a hand-written kernel for it, `gelu_quant`; the vision tower's LayerNorms are followed
  by `quant.fused_kernel`'s; inductor compiles the rest).

Packed per-token FP8 layers (`quant.kernels.fp8.Fp8DynamicLinear`) group too: their producer casts the
input to e4m3 rows and scales (`CastRows`, whose `shape` is all the code here reads of a group's
input) and the group multiplies once with `torch._scaled_mm`. Layers a group cannot fuse (calibrated
or wrapped transforms, other packed real-kernel layers) and the
layers outside the groups (projector, action and time projections, AdaRMS modulations) are called
as modules, so their hooks run as installed (and a captured graph records what they launch).
Either way each layer's own quantizer runs and counts itself; this module counts nothing. `tests/test_pi05_fast.py` checks the result against
lerobot's own `sample_actions` on the demo model, with and without quantization.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from lerobot.policies.common.vla_utils import create_sinusoidal_pos_embedding
from lerobot.utils.constants import OPENPI_ATTENTION_MASK_VALUE
from torch import nn
from transformers.models.gemma.modeling_gemma import apply_rotary_pos_emb

from vlaquantbench.models.pi05.fast import gelu_quant, rotated_norms
from vlaquantbench.models.pi05.fast.linear_groups import LinearGroup
from vlaquantbench.quant import fused_kernel
from vlaquantbench.quant.grid import fma_quotient
from vlaquantbench.quant.hooks import quantizing_op


# The action tokens' attention products read the cache with rows of prefix + chunk keys (1,018 for
# 3 cameras and 200 tokens, 762 for 2 cameras): at a multiple of 8 bf16 values (16 bytes) cuBLAS
# picks its aligned kernels (on an H200 the 2-element-aligned ones took 7.2 and 5.4 us per layer and
# step at batch 1: 2.3 ms of a 24 ms chunk). The extra keys are zeros under the mask value, so their
# softmax weight is exactly 0 and they add exact zeros to the product with the values.
KEY_ALIGNMENT = 8


def _aligned(length: int) -> int:
    return -(-length // KEY_ALIGNMENT) * KEY_ALIGNMENT


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


def modulation(dense_out: torch.Tensor, steps: int, batch: int, dtype: torch.dtype):
    """An AdaRMSNorm's `dense(cond)` output for all steps (steps * B x 3D), split once per chunk
    into per-step (scale, shift, gate) of shape steps x B x 1 x D, the gate already in the
    activation dtype (as `PiGemmaRMSNorm` returns it)."""
    scale, shift, gate = dense_out.view(steps, batch, 1, -1).chunk(3, dim=-1)
    return scale, shift, gate.to(dtype)


def ada_rms_norm(x: torch.Tensor, scale: torch.Tensor, shift: torch.Tensor, eps: float):
    """`PiGemmaRMSNorm(x, cond)`'s normalized output, given the scale and shift of `modulation`."""
    normed = _rms(x, eps) * (1 + scale.float()) + shift.float()
    return normed.to(x.dtype)


def gated_add_ada_rms_norm(hidden, update, gate, scale, shift, eps: float):
    """Gated residual `hidden + update * gate`, then the next AdaRMSNorm: (new hidden, normed)."""
    hidden = hidden + update * gate
    return hidden, ada_rms_norm(hidden, scale, shift, eps)


# With a rotation before the expert's q/k/v or gate/up quantization (the expert's stream is not
# rotated offline): the norm, the rotation and the quantization as one kernel (`rotated_norms`).
ada_rms_norm.rotated_kernel = rotated_norms.ada_rms_norm_rotated_fake_quant
gated_add_ada_rms_norm.rotated_kernel = rotated_norms.gated_add_ada_rms_norm_rotated_fake_quant


def gelu_tanh_mul(gate: torch.Tensor, up: torch.Tensor) -> torch.Tensor:
    """GemmaMLP's `act_fn(gate_proj(x)) * up_proj(x)` with Gemma's `gelu_pytorch_tanh`."""
    return F.gelu(gate, approximate="tanh") * up


# With down_proj's per-token input quantization: one hand-written kernel (see `gelu_quant`).
gelu_tanh_mul.per_token_kernel = gelu_quant.gelu_fake_quant
gelu_tanh_mul.per_token_kernel_supports = fused_kernel.supports
# ... and with its rotation first (`quant.hooks.Rotated`), as one kernel too.
gelu_tanh_mul.rotated_kernel = gelu_quant.gelu_rotated_fake_quant


def layer_norm(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, eps: float):
    """`nn.LayerNorm` (the vision tower's)."""
    return F.layer_norm(x, x.shape[-1:], weight, bias, eps)


def add_layer_norm(hidden, update, weight, bias, eps: float):
    """Residual add, then the next LayerNorm: returns (new hidden, its normalized copy)."""
    hidden = hidden + update
    return hidden, layer_norm(hidden, weight, bias, eps)


# With q/k/v's or fc1's per-token input quantization: the LayerNorm compiled alone, then one Triton
# kernel for the quantization (`quant.fused_kernel`). Compiled together, inductor split the absmax of
# the vision tower's 512 rows of 1,152 (batch 1, two cameras) into two kernels and rounded in a third.
layer_norm.per_token_quantizer = add_layer_norm.per_token_quantizer = fused_kernel.fused_fake_quant
layer_norm.per_token_kernel_supports = add_layer_norm.per_token_kernel_supports = fused_kernel.supports


def gelu_tanh(x: torch.Tensor) -> torch.Tensor:
    """SigLIP's MLP activation (`gelu_pytorch_tanh`)."""
    return F.gelu(x, approximate="tanh")


# The vision tower's FP8 products leave their float32 bias out (`LinearGroup(defer_bias=True)`):
# the op that reads the output adds it, instead of a pass of its own over the output.
def add_bias_layer_norm(hidden, update, update_bias, weight, bias, eps: float):
    """`add_layer_norm` of `update + update_bias`."""
    return add_layer_norm(hidden, update + update_bias, weight, bias, eps)


def bias_gelu_tanh(x: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """`gelu_tanh(x + bias)`."""
    return gelu_tanh(x + bias)


def _residual_layer_norm(hidden, update, update_bias, norm: nn.Module) -> tuple:
    """(op, *args): the residual add of `update` (plus the bias its linear deferred, if any), then `norm`."""
    if update_bias is None:
        return add_layer_norm, hidden, update, norm.weight, norm.bias, norm.eps
    return add_bias_layer_norm, hidden, update, update_bias, norm.weight, norm.bias, norm.eps


def _activation(x, bias) -> tuple:
    """(op, *args): SigLIP's activation of `x` (plus the bias its linear deferred, if any)."""
    return (gelu_tanh, x) if bias is None else (bias_gelu_tanh, x, bias)


# With fc2's per-token input quantization: one hand-written kernel (see `gelu_quant`).
gelu_tanh.per_token_kernel = functools.partial(gelu_quant.gelu_fake_quant, up=None)
gelu_tanh.per_token_kernel_supports = fused_kernel.supports
gelu_tanh.rotated_kernel = functools.partial(gelu_quant.gelu_rotated_fake_quant, up=None)


def rotary_into_cache(query, key, value, cos, sin, cache_keys, cache_values, start: int):
    """Rotary embedding of queries and keys; the keys and values go into the layer's KV buffers at
    `start` (in the same kernel once compiled). Returns the rotated queries, contiguous, so that
    the heads fold into one matrix product without another copy."""
    query, key = apply_rotary_pos_emb(query, key, cos, sin)
    length = key.shape[2]
    cache_keys[:, :, start : start + length] = key
    cache_values[:, :, start : start + length] = value
    return query.contiguous()


def merge_heads(out: torch.Tensor) -> torch.Tensor:
    """Attention output B x heads x L x D -> B x L x (heads * D)."""
    batch, heads, length, dim = out.shape
    return out.transpose(1, 2).reshape(batch, length, heads * dim)


# With o_proj's rotated quantization: the heads read where they are, rotated and quantized, one kernel.
merge_heads.rotated_kernel = rotated_norms.merge_heads_rotated_fake_quant


def attention_probs(scores: torch.Tensor, scaling: float, bias: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Gemma's eager attention weights: scores * scaling + bias, float32 softmax, cast back."""
    return torch.softmax(scores * scaling + bias, dim=-1, dtype=torch.float32).to(dtype)


# Inductor keeps eager's arithmetic where quantization decisions hang on it: the bf16 rounding of
# a norm's output before it is quantized (`emulate_precision_casts`) and IEEE division in x / scale
# (`division_rounding`; Triton's `/` is approximate), so a fused quantization rounds as the hook.
_EAGER_NUMERICS = {"emulate_precision_casts": True, "eager_numerics.division_rounding": True}

# Longest row (values along the last dimension) that a compiled op reduces in one pass over the row
# held in registers: the Gemma MLP's 16,384 activations, which per-token quantization reduces to
# their absmax. Inductor's own limit is 1,024: past it, it loops over the row once for the absmax
# and again for the result, which on an H200 made the W4A4 GELU products 2.4x the plain ones.
WHOLE_ROW_LIMIT = 16384


@functools.cache  # one handler per limit, made once
def _whole_row_choices(limit: int):
    """Inductor's heuristics (its documented `InductorChoices` extension point), except that an
    inner reduction over at most `limit` values is a persistent (one-pass) reduction."""
    from torch._inductor import config
    from torch._inductor.choices import InductorChoices
    from torch._inductor.runtime.hints import ReductionHint
    from torch._inductor.virtualized import V

    class WholeRowChoices(InductorChoices):
        def should_use_persistent_reduction(self, features, cooperative_reduction: bool) -> bool:
            if (config.triton.persistent_reductions and not cooperative_reduction
                    and features.get_reduction_hint() == ReductionHint.INNER
                    and V.graph.sizevars.statically_known_leq(features.reduction_numel, limit)):
                return True
            return super().should_use_persistent_reduction(features, cooperative_reduction)

    return WholeRowChoices()


@dataclass(frozen=True)
class Inductor:
    """Compiles one elementwise op (with the quantization of its output, if any) on its own:
    seconds per op and shape, not minutes like the whole loop. Reductions along rows of at most
    `whole_row_limit` values run in one pass (0: inductor's own choice)."""

    whole_row_limit: int = WHOLE_ROW_LIMIT

    # The quantization's x / scale as compiled code computes it exactly (`quant.hooks.quantizing_op`):
    # under `emulate_precision_casts` inductor makes `addcmul` one fused multiply-add, so the
    # quotient needs one division per row, not one per value.
    quotient = staticmethod(fma_quotient)

    def __call__(self, fn: Callable) -> Callable:
        # One compilation per op, input shape (VLM or expert, batch size) and bit width: more than
        # dynamo's default limit of 8, past which it would silently run the op uncompiled.
        torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, 64)
        if not self.whole_row_limit:
            return torch.compile(fn, dynamic=False, options=_EAGER_NUMERICS)
        from torch._inductor.virtualized import V

        choices = _whole_row_choices(self.whole_row_limit)
        # The limit is also a compile option, only so that inductor's on-disk cache keys the
        # kernels by it (the handler itself is thread state, which the cache key does not see).
        options = {**_EAGER_NUMERICS, "inductor_choices_class": functools.partial(_whole_row_choices, self.whole_row_limit)}
        compiled = torch.compile(fn, dynamic=False, options=options)

        @functools.wraps(fn)
        def with_whole_rows(*args):
            with V.set_choices_handler(choices):  # inductor compiles on the first call of a shape
                return compiled(*args)

        return with_whole_rows


inductor = Inductor()


@dataclass(frozen=True)
class Ops:
    """How the elementwise arithmetic between matrix products runs: eagerly (`compiler` None) or
    each op compiled by `compiler` (`inductor`), so a norm with its quantization, a residual or a
    rotary becomes one or two kernels."""

    compiler: Callable | None = None

    def __call__(self, op: Callable, *args):
        """An op whose output no linear group reads."""
        return quantizing_op(op, None, self.compiler)(*args)

    def feed(self, group: LinearGroup | None, op: Callable, *args):
        """An op whose output (the last, if several) is `group`'s input, quantized by the group's
        members' quantizers inside it (None: a module reads it, through its own hook)."""
        return self(op, *args) if group is None else group.input_from(op, args, self.compiler)


EAGER_OPS = Ops()
COMPILED_OPS = Ops(inductor)


@dataclass
class LayerGroups:
    """A transformer layer's linears grouped by shared input (see `linear_groups`): q/k/v,
    the attention output, the MLP's input projections (Gemma gate/up, SigLIP fc1) and its output."""

    qkv: LinearGroup
    out: LinearGroup
    mlp_in: LinearGroup
    mlp_out: LinearGroup

    @classmethod
    def of(cls, layer: nn.Module) -> "LayerGroups":
        attn, mlp = layer.self_attn, layer.mlp
        if hasattr(mlp, "gate_proj"):  # Gemma
            out, mlp_in, mlp_out = attn.o_proj, [mlp.gate_proj, mlp.up_proj], mlp.down_proj
        else:  # SigLIP
            out, mlp_in, mlp_out = attn.out_proj, [mlp.fc1], mlp.fc2
        return cls(LinearGroup([attn.q_proj, attn.k_proj, attn.v_proj]), LinearGroup([out]), LinearGroup(mlp_in),
                   LinearGroup([mlp_out]))


@dataclass
class ModelGroups:
    """Linear groups of the vision tower's, the VLM's and the action expert's layers, made once
    per capture."""

    vision: list[LayerGroups]
    prefix: list[LayerGroups]
    expert: list[LayerGroups]

    @classmethod
    def of(cls, model: nn.Module) -> "ModelGroups":
        pwe = model.paligemma_with_expert
        vision = pwe.paligemma.model.vision_tower.vision_model
        return cls([LayerGroups.of(layer) for layer in vision.encoder.layers],
                   [LayerGroups.of(layer) for layer in pwe.paligemma.model.language_model.layers],
                   [LayerGroups.of(layer) for layer in pwe.gemma_expert.model.layers])


def _project_qkv(attn: nn.Module, qkv: LinearGroup, hidden, cos, sin, kv, start: int, ops: Ops):
    """q/k/v projections and rotary; this call's keys/values go into the `kv` buffers at `start`."""
    batch, length, _ = hidden.shape
    shape = (batch, length, -1, attn.head_dim)
    query, key, value = (y.view(shape).transpose(1, 2) for y in qkv(hidden))
    return ops(rotary_into_cache, query, key, value, cos, sin, kv[0], kv[1], start)


def _attention(attn: nn.Module, groups: LayerGroups, hidden, cos, sin, bias, kv, start: int, ops: Ops,
               sdpa: bool = False):
    """Self-attention of `hidden` (at cache positions `start`...) over the cache's first
    `bias.shape[-1]` keys (the prefix: its own; the action tokens: the whole aligned cache).

    Folded (default): the 8 query heads share one KV head, so they fold into one batched matrix
    product (8 x L rows against the keys), then scores * scaling + bias, float32 softmax and the
    product with the values -- Gemma's eager arithmetic, in three kernels whatever L. Fused
    attention kernels with a bias were slower here: they parallelize over query blocks and leave
    the GPU idle on 50 action queries. `sdpa=True` runs `scaled_dot_product_attention` instead
    (prefix only)."""
    batch, length, _ = hidden.shape
    query = _project_qkv(attn, groups.qkv, hidden, cos, sin, kv, start, ops)
    heads, end = query.shape[1], bias.shape[-1]
    if sdpa:
        keys = kv[0][:, :, :end].expand(batch, heads, end, attn.head_dim)
        values = kv[1][:, :, :end].expand(batch, heads, end, attn.head_dim)
        out = F.scaled_dot_product_attention(query, keys, values, attn_mask=bias, scale=attn.scaling)
    else:
        keys, values = kv[0][:, 0, :end], kv[1][:, 0, :end]  # B x end x head_dim
        scores = torch.bmm(query.reshape(batch, heads * length, -1), keys.transpose(1, 2))
        probs = ops(attention_probs, scores.view(batch, heads, length, end), attn.scaling, bias, values.dtype)
        out = torch.bmm(probs.view(batch, heads * length, end), values).view(batch, heads, length, -1)
    return groups.out(ops.feed(groups.out, merge_heads, out))[0]


def _mlp(groups: LayerGroups, x: torch.Tensor, ops: Ops) -> torch.Tensor:
    """GemmaMLP: gate/up (one group), the activation (with down_proj's input quantization), down."""
    gate, up = groups.mlp_in(x)
    return groups.mlp_out(ops.feed(groups.mlp_out, gelu_tanh_mul, gate, up))[0]


def _layers_dtype(gemma_model: nn.Module) -> torch.dtype:
    """The activation dtype of a Gemma stack (lerobot casts hidden states to its q_proj dtype); for
    packed real-kernel layers (`quant.kernels`), their floating output/compute dtype."""
    q_proj = gemma_model.layers[0].self_attn.q_proj
    weight = getattr(q_proj, "weight", None)
    if isinstance(weight, torch.Tensor) and weight.is_floating_point() and weight.element_size() > 1:
        return weight.dtype
    return getattr(q_proj, "out_dtype", None) or getattr(q_proj, "compute_dtype", None) or torch.bfloat16


def _new_cache(gemma_model: nn.Module, batch: int, length: int, device, dtype) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """Per layer, key and value buffers of `length` slots rounded up by `_aligned`; the slots past
    `length` stay zero (finite, and masked by every query)."""
    attn = gemma_model.layers[0].self_attn
    kv_heads = attn.k_proj.out_features // attn.head_dim
    shape = (batch, kv_heads, _aligned(length), attn.head_dim)
    cache = [(torch.empty(shape, device=device, dtype=dtype), torch.empty(shape, device=device, dtype=dtype))
             for _ in gemma_model.layers]
    for buffers in cache:
        for buffer in buffers:
            buffer[:, :, length:].zero_()
    return cache


def embed_images(model: nn.Module, images, ops: Ops = EAGER_OPS,
                 groups: list[LayerGroups] | None = None) -> list[torch.Tensor]:
    """lerobot's `embed_image` (SigLIP tower in float32, projector) for every camera in one batch
    (lerobot embeds one camera per call: three times the kernels for the same rows), with the
    encoder layers written out like the Gemma ones: LayerNorm and residual arithmetic as
    (compiled) ops, q/k/v as one group, SDPA as SigLIP's own attention calls it."""
    batch = images[0].shape[0]
    paligemma = model.paligemma_with_expert.paligemma.model
    vision = paligemma.vision_tower.vision_model
    if vision.config.hidden_act != "gelu_pytorch_tanh" or vision.use_head:
        raise NotImplementedError(f"vision tower with {vision.config.hidden_act} / head: not the pi0.5 SigLIP")
    layers = vision.encoder.layers
    groups = groups or [LayerGroups.of(layer) for layer in layers]
    hidden = vision.embeddings(torch.cat(list(images)).to(torch.float32))
    first = layers[0].layer_norm1
    normed = ops.feed(groups[0].qkv, layer_norm, hidden, first.weight, first.bias, first.eps)
    for index, (layer, group) in enumerate(zip(layers, groups, strict=True)):
        attn = layer.self_attn
        rows, length, _ = normed.shape
        query, key, value = (y.view(rows, length, -1, attn.head_dim).transpose(1, 2)
                             for y in group.qkv(normed))
        out = F.scaled_dot_product_attention(query, key, value, scale=attn.scale)
        attn_out = group.out(ops.feed(group.out, merge_heads, out), defer_bias=True)[0]
        hidden, normed = ops.feed(group.mlp_in, *_residual_layer_norm(hidden, attn_out, group.out.deferred_bias,
                                                                      layer.layer_norm2))
        fc1 = group.mlp_in(normed, defer_bias=True)[0]
        activated = ops.feed(group.mlp_out, *_activation(fc1, group.mlp_in.deferred_bias))
        mlp_out = group.mlp_out(activated, defer_bias=True)[0]
        if index + 1 < len(layers):  # the residual, then the next layer's first LayerNorm
            nxt, reader = layers[index + 1].layer_norm1, groups[index + 1].qkv
        else:  # the tower's final LayerNorm feeds the projector, a module call with its own hook
            nxt, reader = vision.post_layernorm, None
        hidden, normed = ops.feed(reader, *_residual_layer_norm(hidden, mlp_out, group.mlp_out.deferred_bias, nxt))
    return list(paligemma.multi_modal_projector(normed).split(batch))


@torch.no_grad()
def prefix_cache(model: nn.Module, images, img_masks, tokens, masks, suffix_len: int, ops: Ops = EAGER_OPS,
                 groups: ModelGroups | None = None, prefix_sdpa: bool = False):
    """Run the VLM over images and prompt; return per-layer KV buffers (prefix filled, `suffix_len`
    free slots after it, then zeros up to the aligned length) and the prefix pad mask."""
    pwe = model.paligemma_with_expert
    embs, pads = [], []
    groups = groups or ModelGroups.of(model)
    for emb, img_mask in zip(embed_images(model, images, ops, groups.vision), img_masks, strict=True):
        embs.append(emb)
        pads.append(img_mask[:, None].expand(emb.shape[0], emb.shape[1]))
    embs.append(pwe.embed_language_tokens(tokens))
    pads.append(masks)
    pad = torch.cat(pads, dim=1)
    lm = pwe.paligemma.model.language_model
    layers = lm.layers
    dtype = _layers_dtype(lm)
    hidden = torch.cat(embs, dim=1).to(dtype)
    batch, length = pad.shape
    # Every prefix token has autoregressive mask 0, so each attends to every non-padding prefix token.
    bias = _attention_bias(pad[:, None, :] & pad[:, :, None], dtype)
    cos, sin = lm.rotary_emb(hidden, torch.cumsum(pad, dim=1) - 1)
    cache = _new_cache(lm, batch, length + suffix_len, hidden.device, dtype)
    first, layer_groups = layers[0].input_layernorm, groups.prefix
    normed = ops.feed(layer_groups[0].qkv, rms_norm, hidden, first.weight, first.eps)
    for index, (layer, group, kv) in enumerate(zip(layers, layer_groups, cache, strict=True)):
        attn_out = _attention(layer.self_attn, group, normed, cos, sin, bias, kv, 0, ops, prefix_sdpa)
        post = layer.post_attention_layernorm
        hidden, normed = ops.feed(group.mlp_in, add_rms_norm, hidden, attn_out, post.weight, post.eps)
        mlp_out = _mlp(group, normed, ops)
        if index + 1 < len(layers):
            nxt = layers[index + 1].input_layernorm
            hidden, normed = ops.feed(layer_groups[index + 1].qkv, add_rms_norm, hidden, mlp_out, nxt.weight, nxt.eps)
    return cache, pad


@torch.no_grad()
def sample_actions(model: nn.Module, images, img_masks, tokens, masks, noise, times, ops: Ops = EAGER_OPS,
                   groups: ModelGroups | None = None, prefix_sdpa: bool = False):
    """A whole chunk: prefix pass, then one Euler step per row of `times` (see `flow_times`).
    `groups` (made after quantization) defaults to groups made now; `prefix_sdpa` as `sdpa` in
    `_attention`."""
    config = model.config
    groups = groups or ModelGroups.of(model)
    expert = model.paligemma_with_expert.gemma_expert.model
    batch, chunk = noise.shape[:2]
    steps = times.shape[0]
    cache, prefix_pad = prefix_cache(model, images, img_masks, tokens, masks, chunk, ops, groups, prefix_sdpa)
    prefix_len = prefix_pad.shape[1]

    # Per-chunk constants: time conditioning and AdaRMS modulations of all steps, bias, rotary.
    step_times = times.expand(steps, batch).reshape(-1)
    time_emb = create_sinusoidal_pos_embedding(
        step_times, model.action_in_proj.out_features, config.min_period, config.max_period, device=times.device
    ).type(times.dtype)
    cond = F.silu(model.time_mlp_out(F.silu(model.time_mlp_in(time_emb))))
    dtype = _layers_dtype(expert)
    modulations = [(modulation(layer.input_layernorm.dense(cond), steps, batch, dtype),
                    modulation(layer.post_attention_layernorm.dense(cond), steps, batch, dtype)) for layer in expert.layers]
    final_modulation = modulation(expert.norm.dense(cond), steps, batch, dtype)
    # Action tokens see every non-padding prefix token and each other (one autoregressive block),
    # not the alignment slots after them.
    alignment = cache[0][0].shape[2] - prefix_len - chunk
    allowed = torch.cat(
        [prefix_pad[:, None, :].expand(batch, chunk, prefix_len),
         torch.ones(batch, chunk, chunk, dtype=torch.bool, device=prefix_pad.device),
         torch.zeros(batch, chunk, alignment, dtype=torch.bool, device=prefix_pad.device)],
        dim=2,
    )
    bias = _attention_bias(allowed, dtype)
    positions = prefix_pad.sum(dim=-1, keepdim=True) + torch.arange(chunk, device=prefix_pad.device)[None]
    cos, sin = expert.rotary_emb(noise.to(dtype), positions)

    dt = -1.0 / steps
    x_t = noise
    layers, layer_groups = expert.layers, groups.expert
    for step in range(steps):
        hidden = model.action_in_proj(x_t).to(dtype)
        scale, shift, gate = (m[step] for m in modulations[0][0])
        normed = ops.feed(layer_groups[0].qkv, ada_rms_norm, hidden, scale, shift, layers[0].input_layernorm.eps)
        for index, (layer, group, kv) in enumerate(zip(layers, layer_groups, cache, strict=True)):
            attn_out = _attention(layer.self_attn, group, normed, cos, sin, bias, kv, prefix_len, ops)
            scale, shift, post_gate = (m[step] for m in modulations[index][1])
            hidden, normed = ops.feed(group.mlp_in, gated_add_ada_rms_norm, hidden, attn_out, gate, scale, shift,
                                      layer.post_attention_layernorm.eps)
            mlp_out = _mlp(group, normed, ops)
            if index + 1 < len(layers):
                nxt, nxt_eps = modulations[index + 1][0], layers[index + 1].input_layernorm.eps
                reader = layer_groups[index + 1].qkv
            else:  # the final norm feeds action_out_proj (float32), a module call with its own hook
                nxt, nxt_eps, reader = final_modulation, expert.norm.eps, None
            scale, shift, gate = (m[step] for m in nxt)
            hidden, normed = ops.feed(reader, gated_add_ada_rms_norm, hidden, mlp_out, post_gate, scale, shift, nxt_eps)
        velocity = model.action_out_proj(normed[:, -config.chunk_size :].to(torch.float32))
        x_t = x_t + dt * velocity
    return x_t
