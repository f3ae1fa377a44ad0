"""The captured sampler's norms and head merge followed by a block-Hadamard rotation and per-token
quantization, one Triton program per token: for rotated (`hadamard`) cells, the input of the
action expert's q/k/v and gate/up products (pi0.5's expert stream cannot be rotated offline: its
AdaRMS norms scale and shift each channel by the flow time), and of every o_proj.

Without them each such input took two kernels, the op compiled by inductor and then
`quant.fused_kernel.rotated_fake_quant` reading its output back: 558 of a batch-1 chunk's kernels
(the expert's 18 layers, twice per layer and Euler step, and every layer's head merge). Here the op
is computed in the rotation's tile layout (`rotated_fake_quant_tile`) and only its result is
written: the new residual stream (where the op adds one) and the quantized, rotated input.

The arithmetic is the ops' (`static_sampling.gated_add_ada_rms_norm`, `ada_rms_norm`,
`merge_heads`) as eager PyTorch rounds it: the gated update rounded to the activation dtype before
the residual add, the sum rounded again, the mean square in float32 (times the float32 reciprocal
of the width, as ATen's mean multiplies), `rsqrt` from libdevice (CUDA's `rsqrtf`, which eager
calls), the scale and shift in float32 without fused multiply-adds (`enable_fp_fusion=False`: eager
rounds each product), the normalized row rounded to the activation dtype; then the rotation and
quantization of `rotated_fake_quant`. The mean square sums in another order than ATen's, so a row's
value may differ from the reference by the float32 rounding of that sum.
"""

from __future__ import annotations

import numpy as np
import torch

from vlaquantbench.quant.fused_kernel import fake_quant_row_args, rotation_tile, triton

if triton is not None:  # Triton ships with torch's CUDA wheels; without it the compiled composition runs.
    import triton.language as tl
    from triton.language.extra import libdevice

    from vlaquantbench.quant.fused_kernel import per_token, rotated_fake_quant_tile, token_tile

    @triton.jit
    def _ada_rms_norm_rotated_fake_quant(
        hidden_ptr, update_ptr, gate_ptr, scale_ptr, shift_ptr, hidden_out_ptr, out_ptr,
        inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr, n_tokens, n_cols, n_tile_rows, tokens,
        gate_batch_stride, scale_batch_stride, shift_batch_stride, inv_n_cols, eps, q_max, inv_q_max, scale_floor,
        HAS_RESIDUAL: tl.constexpr, OUTER: tl.constexpr, INNER: tl.constexpr, TOKENS: tl.constexpr,
        TILE_ROWS: tl.constexpr,
    ):
        """TOKENS tokens per program (`token_tile`): (with `HAS_RESIDUAL`) hidden + update * gate,
        written; its AdaRMS norm, x / rms(x) * (1 + scale) + shift; rotated and quantized, written."""
        first = tl.program_id(0).to(tl.int64) * TOKENS
        rows, cols, token, within, inside = token_tile(first, n_tokens, n_tile_rows, TOKENS, TILE_ROWS, INNER)
        offsets = token[:, None] * n_cols + within
        batch = (token // tokens)[:, None]
        x = tl.load(hidden_ptr + offsets, mask=inside, other=0.0)
        dtype = x.dtype
        if HAS_RESIDUAL:
            update = tl.load(update_ptr + offsets, mask=inside, other=0.0).to(tl.float32)
            gate = tl.load(gate_ptr + batch * gate_batch_stride + within, mask=inside, other=0.0).to(tl.float32)
            x = (x.to(tl.float32) + (update * gate).to(dtype).to(tl.float32)).to(dtype)
            tl.store(hidden_out_ptr + offsets, x, mask=inside)
        x = x.to(tl.float32)
        mean_square = per_token(tl.sum(x * x, axis=1), TOKENS, TILE_ROWS, False) * inv_n_cols
        scale = tl.load(scale_ptr + batch * scale_batch_stride + within, mask=inside, other=0.0).to(tl.float32)
        shift = tl.load(shift_ptr + batch * shift_batch_stride + within, mask=inside, other=0.0).to(tl.float32)
        normed = ((x * libdevice.rsqrt(mean_square + eps)) * (1.0 + scale) + shift).to(dtype)
        quantized = rotated_fake_quant_tile(normed, rows, cols, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr,
                                            q_max, inv_q_max, scale_floor, OUTER, INNER, TOKENS, TILE_ROWS)
        tl.store(out_ptr + offsets, quantized.to(dtype), mask=inside)

    @triton.jit
    def _merge_heads_rotated_fake_quant(
        src_ptr, out_ptr, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr, n_tokens, n_cols, n_tile_rows,
        tokens, head_dim, batch_stride, head_stride, token_stride, q_max, inv_q_max, scale_floor,
        OUTER: tl.constexpr, INNER: tl.constexpr, TOKENS: tl.constexpr, TILE_ROWS: tl.constexpr,
    ):
        """TOKENS tokens per program (`token_tile`): their heads' outputs gathered from
        B x heads x L x D (any strides but the last) as rows of heads * D, rotated and quantized, written."""
        first = tl.program_id(0).to(tl.int64) * TOKENS
        rows, cols, token, within, inside = token_tile(first, n_tokens, n_tile_rows, TOKENS, TILE_ROWS, INNER)
        batch, position = (token // tokens)[:, None], (token % tokens)[:, None]
        head, dim = within // head_dim, within % head_dim
        x = tl.load(src_ptr + batch * batch_stride + position * token_stride + head * head_stride + dim, mask=inside,
                    other=0.0)
        quantized = rotated_fake_quant_tile(x, rows, cols, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr,
                                            q_max, inv_q_max, scale_floor, OUTER, INNER, TOKENS, TILE_ROWS)
        tl.store(out_ptr + token[:, None] * n_cols + within, quantized.to(x.dtype), mask=inside)


def _per_batch(name: str, t: torch.Tensor, batch: int, width: int) -> tuple[torch.Tensor, int]:
    """A modulation tensor of shape B x 1 x width (or 1 x 1 x width) and its batch stride (0 when
    broadcast), its channels contiguous."""
    if t.dim() != 3 or t.shape[1] != 1 or t.shape[2] != width or t.shape[0] not in (1, batch) or t.stride(-1) != 1:
        raise ValueError(f"{name} must be B x 1 x {width} with contiguous channels, not {tuple(t.shape)} "
                         f"strides {t.stride()}")
    return t, t.stride(0) if t.shape[0] == batch and batch > 1 else 0


def _ada_norm_launch(hidden, update, gate, scale, shift, eps: float, rotation, bits: int, num_warps,
                     tokens_per_program: int) -> tuple:
    hidden = hidden.contiguous()
    batch, tokens, width = hidden.shape
    has_residual = update is not None
    hidden_out = torch.empty_like(hidden) if has_residual else hidden
    update = update.contiguous() if has_residual else hidden
    gate, gate_stride = _per_batch("gate", gate, batch, width) if has_residual else (hidden, 0)
    scale, scale_stride = _per_batch("scale", scale, batch, width)
    shift, shift_stride = _per_batch("shift", shift, batch, width)
    out = torch.empty_like(hidden)
    q_max, inv_q_max, scale_floor = fake_quant_row_args(bits)
    launch = rotation_tile(width, rotation, batch * tokens, tokens_per_program, num_warps)
    _ada_rms_norm_rotated_fake_quant[launch.pop("grid")](
        hidden, update, gate, scale, shift, hidden_out, out, n_cols=width, tokens=tokens,
        gate_batch_stride=gate_stride, scale_batch_stride=scale_stride, shift_batch_stride=shift_stride,
        inv_n_cols=float(np.float32(1.0) / np.float32(width)), eps=eps, q_max=q_max, inv_q_max=inv_q_max,
        scale_floor=scale_floor, HAS_RESIDUAL=has_residual, enable_fp_fusion=False, **launch)
    return hidden_out, out


def gated_add_ada_rms_norm_rotated_fake_quant(hidden, update, gate, scale, shift, eps: float, *, rotation, bits: int,
                                              num_warps: int | None = None, tokens_per_program: int = 1):
    """`gated_add_ada_rms_norm(hidden, update, gate, scale, shift, eps)` with its normalized output
    rotated and quantized (`InputTransform(rotation=rotation, act_bits=bits)`), in one kernel on
    CUDA tensors (or CPU ones under Triton's interpreter): (new hidden, quantized input).
    `num_warps` overrides `rotation_tile`'s choice; `tokens_per_program` as there (both for the
    other two as well)."""
    return _ada_norm_launch(hidden, update, gate, scale, shift, eps, rotation, bits, num_warps, tokens_per_program)


def ada_rms_norm_rotated_fake_quant(x, scale, shift, eps: float, *, rotation, bits: int, num_warps: int | None = None,
                                    tokens_per_program: int = 1):
    """`ada_rms_norm(x, scale, shift, eps)` rotated and quantized, in one kernel."""
    return _ada_norm_launch(x, None, None, scale, shift, eps, rotation, bits, num_warps, tokens_per_program)[1]


def merge_heads_rotated_fake_quant(out: torch.Tensor, *, rotation, bits: int, num_warps: int | None = None,
                                   tokens_per_program: int = 1):
    """`merge_heads(out)` (B x heads x L x D -> B x L x heads * D) rotated and quantized, in one
    kernel that reads the heads where they are."""
    if out.stride(-1) != 1:
        out = out.contiguous()
    batch, heads, tokens, head_dim = out.shape
    merged = torch.empty(batch, tokens, heads * head_dim, dtype=out.dtype, device=out.device)
    q_max, inv_q_max, scale_floor = fake_quant_row_args(bits)
    launch = rotation_tile(heads * head_dim, rotation, batch * tokens, tokens_per_program, num_warps)
    _merge_heads_rotated_fake_quant[launch.pop("grid")](
        out, merged, n_cols=heads * head_dim, tokens=tokens, head_dim=head_dim, batch_stride=out.stride(0),
        head_stride=out.stride(1), token_stride=out.stride(2), q_max=q_max, inv_q_max=inv_q_max,
        scale_floor=scale_floor, **launch)
    return merged
