"""Round-to-nearest fake quantization grids (paper appendix `app:quant-prelim`), as pure functions.

Every function quantizes and immediately dequantizes: the result has the input's shape and dtype,
with values on the b-bit grid. Arithmetic runs in float32; rounding is `torch.round` (ties to even).

    x_hat = s * (clip(round(x / s) + z, q_min, q_max) - z)

symmetric:  q in [-2^(b-1), 2^(b-1) - 1], z = 0, s = max(max|x|, 1e-8) / (2^(b-1) - 1)
asymmetric: m = min(min x, 0), M = max(max x, 0), L = 2^b - 1, q in [0, L],
            s = max((M - m) / L, 1e-8), z = clip(round(-m / s), 0, L)

A "group" is a run of consecutive values along the last dimension that shares one scale.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import torch

SCALE_FLOOR = 1e-8


def fake_quant_sym(x: torch.Tensor, bits: int,
                   quotient: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] = torch.div) -> torch.Tensor:
    """Symmetric b-bit RTN with one scale per row of the last dimension. `quotient(x, scale)` is
    x / scale; `fma_quotient` is the same value for code compiled by inductor."""
    xf = x.float()
    q_max = 2 ** (bits - 1) - 1
    scale = xf.abs().amax(dim=-1, keepdim=True).clamp_min(SCALE_FLOOR) / q_max
    q = torch.clamp(torch.round(quotient(xf, scale)), -(q_max + 1), q_max)
    return (q * scale).to(x.dtype)


def fma_quotient(x: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """x / scale rounded as IEEE division rounds it, with one division per row instead of one per
    value: the product with the row's correctly rounded reciprocal y, corrected once by its exact
    residual, RN(q + RN(x - scale q) y) (Markstein; `quant.fused_kernel.fake_quant_scaled` is the
    same in Triton). Exact only where `addcmul` with value 1 is a fused multiply-add, as inductor
    compiles it under `emulate_precision_casts` (Triton's `tl.fma`, C++'s `std::fma`); eager CUDA
    rounds its product before adding, so this is for compiled code only."""
    inverse = torch.div(1.0, scale)  # a row's scale is [..., 1]: one division per row
    estimate = x * inverse
    return torch.addcmul(estimate, torch.addcmul(x, -estimate, scale), inverse)


def fake_quant_asym(x: torch.Tensor, bits: int) -> torch.Tensor:
    """Asymmetric b-bit RTN with one scale and zero point per row of the last dimension."""
    return grid_of(x, bits, symmetric=False).quantize(x).to(x.dtype)


class RowGrid(NamedTuple):
    """The b-bit grid of each row of a tensor (scale and zero point [..., 1], integer range), fixed
    once: GPTQ (`quant.gptq`) rounds a group's columns one at a time on the grid of the whole group."""

    scale: torch.Tensor
    zero: torch.Tensor
    q_min: int
    q_max: int

    def quantize(self, x: torch.Tensor) -> torch.Tensor:
        """x on this grid, in float32 (x's last dimension: columns sharing a row's scale, or one column
        [rows] against scales [rows, 1] -- use `quantize_column`)."""
        q = torch.clamp(torch.round(x.float() / self.scale) + self.zero, self.q_min, self.q_max)
        return (q - self.zero) * self.scale

    def quantize_column(self, column: torch.Tensor) -> torch.Tensor:
        return self.quantize(column[:, None])[:, 0]


def grid_of(x: torch.Tensor, bits: int, symmetric: bool) -> RowGrid:
    """The grid `fake_quant_sym` / `fake_quant_asym` put each row of x's last dimension on (float32)."""
    xf = x.float()
    if symmetric:
        q_max = 2 ** (bits - 1) - 1
        scale = xf.abs().amax(dim=-1, keepdim=True).clamp_min(SCALE_FLOOR) / q_max
        return RowGrid(scale, torch.zeros_like(scale), -(q_max + 1), q_max)
    levels = 2**bits - 1
    low = xf.amin(dim=-1, keepdim=True).clamp_max(0.0)
    high = xf.amax(dim=-1, keepdim=True).clamp_min(0.0)
    scale = ((high - low) / levels).clamp_min(SCALE_FLOOR)
    zero = torch.clamp(torch.round(-low / scale), 0, levels)
    return RowGrid(scale, zero, 0, levels)


def fake_quant_weight(weight: torch.Tensor, bits: int, group_size: int | None, symmetric: bool) -> torch.Tensor:
    """Quantize a C_out x C_in weight per output channel (`group_size` None) or per group of
    `group_size` consecutive input columns; a shorter final group gets its own scale, unpadded."""
    quant = fake_quant_sym if symmetric else fake_quant_asym
    in_features = weight.shape[-1]
    if group_size is None or group_size >= in_features:
        return quant(weight, bits)
    full = in_features - in_features % group_size
    head = weight[..., :full].reshape(*weight.shape[:-1], full // group_size, group_size)
    pieces = [quant(head, bits).reshape(*weight.shape[:-1], full)]
    if full < in_features:
        pieces.append(quant(weight[..., full:], bits))
    return torch.cat(pieces, dim=-1)


def fake_quant_activation(x: torch.Tensor, bits: int,
                          quotient: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] = torch.div) -> torch.Tensor:
    """Dynamic symmetric per-token quantization: one absmax scale per vector along the last
    dimension, all leading dimensions treated as tokens (`quotient` as in `fake_quant_sym`)."""
    return fake_quant_sym(x, bits, quotient)


@dataclass(frozen=True)
class PerTokenCast:
    """Real (not fake) dynamic symmetric per-token quantization, the input side of a W8A8 kernel:
    each row along the last dimension cast to `dtype` (int8 rounded to nearest, ties to even; a
    float8 format by its own cast, which rounds to nearest even and saturates here by the clamp),
    with one float32 scale per row, s = max(max|x|, 1e-8) / q_max. Returns `CastRows`. The same
    scale as `fake_quant_sym` (q_max 127) and as the fp8 formats' per-token scale (q_max 448), so
    s * values is what fake quantization computes. `quotient` as in `fake_quant_sym`."""

    dtype: torch.dtype

    @property
    def q_max(self) -> float:
        return 127.0 if self.dtype == torch.int8 else float(torch.finfo(self.dtype).max)

    @property
    def name(self) -> str:
        return str(self.dtype).removeprefix("torch.")

    def __call__(self, x: torch.Tensor,
                 quotient: Callable[[torch.Tensor, torch.Tensor], torch.Tensor] = torch.div) -> CastRows:
        xf = x.float()
        scales = xf.abs().amax(dim=-1, keepdim=True).clamp_min(SCALE_FLOOR) / self.q_max
        y = torch.clamp(quotient(xf, scales), -self.q_max, self.q_max)
        return CastRows((torch.round(y) if self.dtype == torch.int8 else y).to(self.dtype), scales)


class CastRows(NamedTuple):
    """A tensor quantized by `PerTokenCast`: x ≈ values * scales (scales of shape [..., 1])."""

    values: torch.Tensor
    scales: torch.Tensor

    @property
    def shape(self) -> torch.Size:
        """The quantized tensor's shape (code that only reads a layer input's shape reads it here)."""
        return self.values.shape
