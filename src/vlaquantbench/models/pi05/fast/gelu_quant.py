"""GELU (tanh) MLP activations followed by per-token fake quantization, one Triton program per row.

Under W4A4 the down projection of every Gemma MLP and the fc2 of every SigLIP MLP quantize their
input per token, so the activation that produces it must also reduce each row to its absmax before
it can write anything. Inductor compiles that as a reduction whose row stays in registers (or, past
1,024 values, loops over it twice); on an H200 the VLM's 968 x 16,384 GELU product then took
69 us per call against 24 us unquantized, and the vision tower's 768 x 4,304 float32 GELU 20 us
against 6 us. Here one program per row computes the activation once, reduces, quantizes and writes
it: holding the row in registers (one read, one write) or, for many long rows, in chunks written
out and read back from L2 (`_launch` chooses).

The arithmetic is eager PyTorch's, operation by operation, so the result is bit-identical to the
hook path (`F.gelu(gate, approximate="tanh") * up`, then `quant.grid.fake_quant_activation`):
float32 opmath, `0.5 x (1 + tanh(k_beta (x + k_kappa x^3)))` with the CUDA kernel's constants and
its one fused multiply-add, the activation rounded to the tensor's dtype before the product and the
product rounded before it is quantized; the quantization is `quant.fused_kernel`'s (IEEE division's
quotient, round-half-even, the scale floor). `benchmarks/gpu_policy_inference.py` checks the equality on the
GPU (`checks.fused_norm_quant_equal_fraction`).

`gelu_rotated_fake_quant` is the same activation followed by a block-Hadamard rotation and the
quantization (`quant.fused_kernel.rotated_fake_quant_tile`), for rotated (`hadamard`) cells.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from vlaquantbench.quant.fused_kernel import fake_quant_row_args, rotation_tile, triton

# ATen's GeluCUDAKernelImpl (tanh): constexpr float kBeta = M_SQRT2 * M_2_SQRTPI * 0.5, kKappa = 0.044715.
K_BETA = float(np.float32(math.sqrt(2.0) * (2.0 / math.sqrt(math.pi)) * 0.5))
K_KAPPA = float(np.float32(0.044715))
MAX_ROW = 16384

if triton is not None:  # Triton ships with torch's CUDA wheels; without it the compiled composition runs.
    import triton.language as tl
    from triton.language.extra import libdevice

    from vlaquantbench.quant.fused_kernel import fake_quant_row, fake_quant_scaled, rotated_fake_quant_tile, token_tile

    @triton.jit
    def _gelu_product(gate_ptr, up_ptr, row, cols, inside, gate_row_stride, up_row_stride, k_beta, k_kappa,
                      HAS_UP: tl.constexpr):
        """`gelu(gate) * up` (`HAS_UP` False: the GELU alone) at some columns of one row, in the
        tensors' dtype, rounded where eager rounds; padding lanes 0 (gelu(0) = 0)."""
        gate = tl.load(gate_ptr + row * gate_row_stride + cols, mask=inside, other=0.0)
        dtype = gate.dtype
        x = gate.to(tl.float32)
        inner = k_beta * (x + k_kappa * (x * x * x))
        act = ((0.5 * x) * (1.0 + libdevice.tanh(inner))).to(dtype)
        if HAS_UP:
            up = tl.load(up_ptr + row * up_row_stride + cols, mask=inside, other=0.0)
            act = (act.to(tl.float32) * up.to(tl.float32)).to(dtype)
        return act

    @triton.jit
    def _gelu_fake_quant_rows(
        gate_ptr, up_ptr, out_ptr, n_cols, gate_row_stride, up_row_stride, q_max, inv_q_max, scale_floor, k_beta,
        k_kappa, HAS_UP: tl.constexpr, BLOCK: tl.constexpr,
    ):
        """A row per program, held in registers: one read, one write."""
        row = tl.program_id(0).to(tl.int64)
        cols = tl.arange(0, BLOCK)
        inside = cols < n_cols
        act = _gelu_product(gate_ptr, up_ptr, row, cols, inside, gate_row_stride, up_row_stride, k_beta, k_kappa,
                            HAS_UP)
        quantized = fake_quant_row(act.to(tl.float32), q_max, inv_q_max, scale_floor)
        tl.store(out_ptr + row * n_cols + cols, quantized.to(act.dtype), mask=inside)

    @triton.jit
    def _gelu_fake_quant_row_chunks(
        gate_ptr, up_ptr, out_ptr, n_cols, gate_row_stride, up_row_stride, q_max, inv_q_max, scale_floor, k_beta,
        k_kappa, HAS_UP: tl.constexpr, CHUNK: tl.constexpr,
    ):
        """A row per program, in chunks: the activation is written out while the absmax is taken,
        then read back (from L2: a row is at most 64 KiB) and quantized in place. Small programs,
        many per multiprocessor, so that one row's loads overlap another's arithmetic."""
        row = tl.program_id(0).to(tl.int64)
        absmax = tl.zeros((), dtype=tl.float32)
        for start in range(0, n_cols, CHUNK):
            cols = start + tl.arange(0, CHUNK)
            inside = cols < n_cols
            act = _gelu_product(gate_ptr, up_ptr, row, cols, inside, gate_row_stride, up_row_stride, k_beta,
                                k_kappa, HAS_UP)
            tl.store(out_ptr + row * n_cols + cols, act, mask=inside)
            absmax = tl.maximum(absmax, tl.max(tl.abs(act.to(tl.float32)), axis=0))
        tl.debug_barrier()  # every chunk written before any is read back
        for start in range(0, n_cols, CHUNK):
            cols = start + tl.arange(0, CHUNK)
            inside = cols < n_cols
            act = tl.load(out_ptr + row * n_cols + cols, mask=inside, other=0.0)
            quantized = fake_quant_scaled(act.to(tl.float32), absmax, q_max, inv_q_max, scale_floor)
            tl.store(out_ptr + row * n_cols + cols, quantized.to(act.dtype), mask=inside)

    @triton.jit
    def _gelu_rotated_fake_quant(
        gate_ptr, up_ptr, out_ptr, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr, n_tokens, n_cols,
        n_tile_rows, gate_row_stride, up_row_stride, q_max, inv_q_max, scale_floor, k_beta, k_kappa,
        HAS_UP: tl.constexpr, OUTER: tl.constexpr, INNER: tl.constexpr, TOKENS: tl.constexpr, TILE_ROWS: tl.constexpr,
    ):
        """TOKENS rows per program: the activation computed once in the rotation's tile layout
        (`quant.fused_kernel.token_tile`), rotated and quantized (`rotated_fake_quant_tile`), written once."""
        first = tl.program_id(0).to(tl.int64) * TOKENS
        rows, cols, token, within, inside = token_tile(first, n_tokens, n_tile_rows, TOKENS, TILE_ROWS, INNER)
        act = _gelu_product(gate_ptr, up_ptr, token[:, None], within, inside, gate_row_stride, up_row_stride, k_beta,
                            k_kappa, HAS_UP)
        quantized = rotated_fake_quant_tile(act, rows, cols, inner_ptr, outer_ptr, inner_signs_ptr, outer_signs_ptr,
                                            q_max, inv_q_max, scale_floor, OUTER, INNER, TOKENS, TILE_ROWS)
        tl.store(out_ptr + token[:, None] * n_cols + within, quantized.to(act.dtype), mask=inside)


# Warps of a rotated GELU program (at least what `rotation_tile` picks, which is at most 8): on an
# H200 the expert's 50 x 4,096 took 5.5 us with 8 warps, 6.8 with 4, and 1,600 x 4,096 (batch 32)
# 30.9 against 34.2 (calls in a CUDA graph; `benchmarks/results/gpu_hadamard_captured_run4.json`).
GELU_WARPS = 8
# Chunked programs (`_gelu_fake_quant_row_chunks`): values per chunk, warps per program.
CHUNK, CHUNK_WARPS = 2048, 8
# Chunks twice as long for rows they divide, past this many rows per multiprocessor.
LONG_CHUNK, LONG_CHUNK_ROWS_PER_SM = 4096, 6
# Rows of at most this many values are held whole whatever their number (the action expert's 4,096).
WHOLE_ROW_COLS = 4096


def _launch(rows: int, n_cols: int, device: torch.device) -> tuple[int, int]:
    """(chunk, warps), chunk 0 for a row held whole; measured on an H200 (`benchmarks/results/gpu_gelu_quant*.json`).
    While there are no more rows than about two per multiprocessor, a call's time is one row's
    latency: the row is held whole with as many warps as it can use (32; the action expert's 50
    rows at batch 1: 2.7 us, 4.9 with 8 warps). With more rows, rows up to `WHOLE_ROW_COLS` are still
    held whole (16 values per thread); longer ones are chunked, so that a row of 16,384 does not
    leave one 1,024-thread program per multiprocessor and the vision tower's 4,304 values are not
    padded to 8,192 (712 x 16,384: 34 against 36 us; 512 x 4,304 float32: 8 against 9 us). Past six
    rows per multiprocessor, rows that chunks of 4,096 divide take those (the VLM's at three cameras,
    968 x 16,384: 42 against 54 us; at batch 8, 5,696 rows: 214 against 242 us)."""
    multiprocessors = torch.cuda.get_device_properties(device).multi_processor_count
    if rows <= 2 * multiprocessors and n_cols <= MAX_ROW:
        return 0, 32
    if n_cols <= WHOLE_ROW_COLS:
        return 0, max(4, triton.next_power_of_2(n_cols) // 512)
    if rows > LONG_CHUNK_ROWS_PER_SM * multiprocessors and n_cols % LONG_CHUNK == 0:
        return LONG_CHUNK, CHUNK_WARPS
    return CHUNK, CHUNK_WARPS


def _rows(x: torch.Tensor) -> torch.Tensor:
    """`x` as rows x last dimension, a view where the layout allows (the gate and up halves of the
    gate/up product are column slices of one tensor: rows with a stride, read in place)."""
    rows = x.reshape(-1, x.shape[-1])
    return rows if rows.stride(-1) == 1 else rows.contiguous()


def _operands(gate: torch.Tensor, up: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(gate rows, up rows (the gate's without `up`), the output) of a GELU kernel's call."""
    if up is not None and (up.shape != gate.shape or up.dtype != gate.dtype):
        raise ValueError(f"gate {tuple(gate.shape)} {gate.dtype} and up {tuple(up.shape)} {up.dtype} differ")
    gate_rows = _rows(gate)
    return gate_rows, gate_rows if up is None else _rows(up), torch.empty(gate.shape, dtype=gate.dtype,
                                                                          device=gate.device)


def gelu_fake_quant(gate: torch.Tensor, up: torch.Tensor | None, bits: int, *, chunk: int | None = None,
                    num_warps: int | None = None) -> torch.Tensor:
    """`fake_quant_activation(F.gelu(gate, approximate="tanh") * up, bits)` (`up` None: the GELU
    alone) in one kernel on CUDA tensors (`quant.fused_kernel.supports`). The result is contiguous. `chunk` and
    `num_warps` override `_launch`'s choice (chunk 0: each row held whole, at most `MAX_ROW` values)."""
    gate_rows, up_rows, out = _operands(gate, up)
    rows, n_cols = gate_rows.shape
    if chunk is None:
        chunk, warps = _launch(rows, n_cols, gate.device)
    else:
        warps = CHUNK_WARPS if chunk else 32
    if not chunk and n_cols > MAX_ROW:
        raise ValueError(f"a row held whole has at most {MAX_ROW} values, not {n_cols}")
    args = (gate_rows, up_rows, out, n_cols, gate_rows.stride(0), up_rows.stride(0), *fake_quant_row_args(bits),
            K_BETA, K_KAPPA)
    if chunk:
        _gelu_fake_quant_row_chunks[(rows,)](*args, HAS_UP=up is not None, CHUNK=chunk, num_warps=num_warps or warps)
    else:
        _gelu_fake_quant_rows[(rows,)](*args, HAS_UP=up is not None, BLOCK=triton.next_power_of_2(n_cols),
                                       num_warps=num_warps or warps)
    return out


def gelu_rotated_fake_quant(gate: torch.Tensor, up: torch.Tensor | None, rotation, bits: int, *,
                            num_warps: int | None = None, tokens_per_program: int = 1) -> torch.Tensor:
    """`InputTransform(rotation=rotation, act_bits=bits)(F.gelu(gate, approximate="tanh") * up)` (`up`
    None: the GELU alone) in one kernel on CUDA tensors, for a rotation that
    `quant.fused_kernel.supports_rotation`: the down_proj / fc2 input of a rotated W4A4 model,
    without writing the activation out and reading it back. The result is contiguous. `num_warps`
    overrides `GELU_WARPS`; `tokens_per_program` as in `rotation_tile`."""
    gate_rows, up_rows, out = _operands(gate, up)
    rows, n_cols = gate_rows.shape
    q_max, inv_q_max, scale_floor = fake_quant_row_args(bits)
    launch = rotation_tile(n_cols, rotation, rows, tokens_per_program, num_warps or GELU_WARPS)
    _gelu_rotated_fake_quant[launch.pop("grid")](
        gate_rows, up_rows, out, n_cols=n_cols, gate_row_stride=gate_rows.stride(0), up_row_stride=up_rows.stride(0),
        q_max=q_max, inv_q_max=inv_q_max, scale_floor=scale_floor, k_beta=K_BETA, k_kappa=K_KAPPA,
        HAS_UP=up is not None, **launch)
    return out
