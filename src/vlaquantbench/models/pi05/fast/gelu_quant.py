"""GELU (tanh) MLP activations followed by per-token fake quantization, one Triton program per row.

Under W4A4 the down projection of every Gemma MLP and the fc2 of every SigLIP MLP quantize their
input per token, so the activation that produces it must also reduce each row to its absmax before
it can write anything. Inductor compiles that as a reduction whose row stays in registers (or, past
1,024 values, loops over it twice); on an H200 the VLM's 968 x 16,384 GELU product then took
69 us per call against 24 us unquantized, and the vision tower's 768 x 4,304 float32 GELU 20 us
against 6 us. Here one program holds a row (16,384 values at most), computes the activation once,
reduces, quantizes and writes it, with as many warps as the row needs.

The arithmetic is eager PyTorch's, operation by operation, so the result is bit-identical to the
hook path (`F.gelu(gate, approximate="tanh") * up`, then `quant.grid.fake_quant_activation`):
float32 opmath, `0.5 x (1 + tanh(k_beta (x + k_kappa x^3)))` with the CUDA kernel's constants and
its one fused multiply-add, the activation rounded to the tensor's dtype before the product and the
product rounded before it is quantized; the quantization is `quant.fused_kernel`'s (IEEE division,
round-half-even, the scale floor). `benchmarks/gpu_policy_inference.py` checks the equality on the
GPU (`checks.fused_norm_quant_equal_fraction`).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from vlaquantbench.quant.fused_kernel import fake_quant_row_args, triton

# ATen's GeluCUDAKernelImpl (tanh): constexpr float kBeta = M_SQRT2 * M_2_SQRTPI * 0.5, kKappa = 0.044715.
K_BETA = float(np.float32(math.sqrt(2.0) * (2.0 / math.sqrt(math.pi)) * 0.5))
K_KAPPA = float(np.float32(0.044715))
MAX_ROW = 16384

if triton is not None:  # Triton ships with torch's CUDA wheels; without it the compiled composition runs.
    import triton.language as tl
    from triton.language.extra import libdevice

    from vlaquantbench.quant.fused_kernel import fake_quant_row

    @triton.jit
    def _gelu_fake_quant_rows(
        gate_ptr, up_ptr, out_ptr, n_cols, gate_row_stride, up_row_stride, q_max, inv_q_max, scale_floor, k_beta,
        k_kappa, HAS_UP: tl.constexpr, BLOCK: tl.constexpr,
    ):
        row = tl.program_id(0).to(tl.int64)
        cols = tl.arange(0, BLOCK)
        inside = cols < n_cols
        gate = tl.load(gate_ptr + row * gate_row_stride + cols, mask=inside, other=0.0)
        dtype = gate.dtype
        x = gate.to(tl.float32)
        inner = k_beta * (x + k_kappa * (x * x * x))
        act = ((0.5 * x) * (1.0 + libdevice.tanh(inner))).to(dtype)
        if HAS_UP:
            up = tl.load(up_ptr + row * up_row_stride + cols, mask=inside, other=0.0)
            act = (act.to(tl.float32) * up.to(tl.float32)).to(dtype)
        quantized = fake_quant_row(act.to(tl.float32), q_max, inv_q_max, scale_floor)  # padding lanes: gelu(0) = 0
        tl.store(out_ptr + row * n_cols + cols, quantized.to(dtype), mask=inside)


def _warps(block: int, rows: int, device: torch.device) -> int:
    """Warps per row (measured on an H200): as many as a row can use (32) while there are no more
    rows than about two per multiprocessor, where a call's time is one row's latency (the action
    expert's 50 rows at batch 1: 3.3 us with 32 warps, 4.9 with 8); otherwise 16 values per thread."""
    if rows <= 2 * torch.cuda.get_device_properties(device).multi_processor_count:
        return 32
    return min(32, max(4, block // 512))


def supports(x: torch.Tensor) -> bool:
    return triton is not None and x.is_cuda and x.shape[-1] <= MAX_ROW


def _rows(x: torch.Tensor) -> torch.Tensor:
    """`x` as rows x last dimension, a view where the layout allows (the gate and up halves of the
    gate/up product are column slices of one tensor: rows with a stride, read in place)."""
    rows = x.reshape(-1, x.shape[-1])
    return rows if rows.stride(-1) == 1 else rows.contiguous()


def gelu_fake_quant(gate: torch.Tensor, up: torch.Tensor | None, bits: int, num_warps: int | None = None) -> torch.Tensor:
    """`fake_quant_activation(F.gelu(gate, approximate="tanh") * up, bits)` (`up` None: the GELU
    alone) in one kernel; CUDA tensors with rows of at most `MAX_ROW` values (`supports`). The
    result is contiguous."""
    if up is not None and (up.shape != gate.shape or up.dtype != gate.dtype):
        raise ValueError(f"gate {tuple(gate.shape)} {gate.dtype} and up {tuple(up.shape)} {up.dtype} differ")
    gate_rows = _rows(gate)
    up_rows = gate_rows if up is None else _rows(up)
    rows, n_cols = gate_rows.shape
    out = torch.empty(gate.shape, dtype=gate.dtype, device=gate.device)
    block = triton.next_power_of_2(n_cols)
    _gelu_fake_quant_rows[(rows,)](
        gate_rows, up_rows, out, n_cols, gate_rows.stride(0), up_rows.stride(0), *fake_quant_row_args(bits),
        K_BETA, K_KAPPA,
        HAS_UP=up is not None, BLOCK=block, num_warps=num_warps or _warps(block, rows, gate.device),
    )
    return out
