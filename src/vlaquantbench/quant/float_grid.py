"""Floating-point fake quantization grids: FP8, OCP Microscaling (MX v1.0) and NVFP4, as pure functions.

Like `quant.grid`, every function quantizes and immediately dequantizes (the result has the input's
shape and dtype) and computes in float32. Element rounding is round-to-nearest-even onto the
element format's grid, subnormals included, *saturating*: magnitudes above the largest normal
(and +-Inf) become +-max; NaN stays NaN.

    element formats (OCP OFP8 / MX v1.0)   bias   max normal   emax
    E4M3  (FP8, no Inf)                       7        448        8
    E5M2  (FP8)                              15      57344       15
    E3M2  (FP6)                               3         28        4
    E2M3  (FP6)                               1        7.5        2
    E2M1  (FP4)                               1          6        2

FP8 (`fake_quant_fp8`): s = max(amax, floor) / max_elem per tensor or per row; x_hat = s * Q(x / s).

MX (`fake_quant_mx`, OCP MX v1.0 section 6.3): blocks of 32 consecutive values along the last
dimension share an E8M0 scale X = 2^k, k = floor(log2 amax_block) - emax_elem clamped to
[-127, 127] (E8M0 code k + 127; code 0 is 2^-127 exactly, as the spec encodes it); x_hat = X * Q(x / X).
A block whose amax is NaN gets the NaN scale (code 255): the whole block dequantizes to NaN. A block
holding +-Inf is scaled as if its amax were 2^128 (the exponent Inf carries), so Inf saturates to
+-max_elem * X and the block's finite values round at that scale.

NVFP4 (`fake_quant_nvfp4`): blocks of 16 with an E4M3 block scale times an FP32 tensor scale.
    s_t = max(amax_tensor, floor) / (448 * 6)
    s_b = E4M3(clamp(amax_block / 6 / s_t, 2^-6, 448))      (the block scale never becomes 0 or subnormal)
    x_hat = (s_t * s_b) * E2M1(clamp(x * ((1 / s_t) / s_b), -6, 6))
The arithmetic order is the reference's (torchao `nvfp4_quantize`) so results agree bit for bit.

A final block shorter than the block size (last dimension not a multiple of it) has its own scale,
computed over the values it has (equivalently: zero-padded to a full block).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

SCALE_FLOOR = 1e-12  # amax floor of tensor/row scales: an all-zero tensor quantizes to zeros, not NaN
MX_BLOCK = 32
NVFP4_BLOCK = 16
E8M0_MIN_EXPONENT, E8M0_MAX_EXPONENT = -127, 127


@dataclass(frozen=True)
class FloatElement:
    """A sign + `exponent_bits` + `mantissa_bits` minifloat with bias 2^(e-1) - 1 (OCP conventions)."""

    name: str
    exponent_bits: int
    mantissa_bits: int
    max_normal: float

    @property
    def bias(self) -> int:
        return 2 ** (self.exponent_bits - 1) - 1

    @property
    def min_normal_exponent(self) -> int:
        return 1 - self.bias

    @property
    def emax(self) -> int:
        """Exponent of the largest normal (MX's emax_elem), as a Python int: computed on the host from
        the format's constants, never from a tensor, so MX quantization records into a CUDA graph and
        compiles without a graph break or device sync. frexp's exponent is exact: floor(log2 m) = e - 1."""
        return math.frexp(self.max_normal)[1] - 1


E4M3 = FloatElement("E4M3", 4, 3, 448.0)
E5M2 = FloatElement("E5M2", 5, 2, 57344.0)
E3M2 = FloatElement("E3M2", 3, 2, 28.0)
E2M3 = FloatElement("E2M3", 2, 3, 7.5)
E2M1 = FloatElement("E2M1", 2, 1, 6.0)
ELEMENTS = {e.name: e for e in (E4M3, E5M2, E3M2, E2M3, E2M1)}


def pow2(exponent: torch.Tensor) -> torch.Tensor:
    """2^e as float32, exactly, for integer e in [-127, 127] (float32 bit construction; 2^-127 is
    the one subnormal and is built separately)."""
    e = exponent.to(torch.int32)
    normal = ((e.clamp(-126, 127) + 127) << 23).view(torch.float32)
    return torch.where(e < -126, torch.full_like(normal, 2.0**-127), normal)


def floor_log2(x: torch.Tensor) -> torch.Tensor:
    """floor(log2 |x|) as int32, read from the float32 exponent field (shifts and masks, which a
    compiler fuses like any elementwise op). Exact for normal values; 0 and subnormals give -127,
    which every use clamps as the exact value would be (no element format's smallest normal exponent
    and no E8M0 exponent lies below -126 / -127); Inf and NaN give 128 (the exponent field of Inf, so an Inf block is scaled as one of amax 2^128)."""
    return ((x.float().view(torch.int32) >> 23) & 0xFF) - 127


def round_to_element(x: torch.Tensor, element: FloatElement) -> torch.Tensor:
    """x (float32) rounded to the nearest value of `element`, ties to even, saturating at +-max."""
    magnitude = x.abs().clamp(max=element.max_normal)  # clamp keeps NaN
    exponent = floor_log2(magnitude).clamp_min(element.min_normal_exponent)
    quantum = pow2(exponent - element.mantissa_bits)  # spacing of the grid in |x|'s binade
    # |x| / quantum and the product are exact (powers of two); torch.round ties to even.
    return torch.copysign(torch.round(magnitude / quantum) * quantum, x)


def _blocks(x: torch.Tensor, block: int, fn) -> torch.Tensor:
    """Apply `fn` to [..., n_blocks, block] views of x's last dimension; a short final block is
    zero-padded (padding changes no block maximum) and the padding dropped afterwards."""
    size = x.shape[-1]
    pad = -size % block
    padded = torch.nn.functional.pad(x, (0, pad)) if pad else x
    out = fn(padded.reshape(*x.shape[:-1], (size + pad) // block, block))
    return out.reshape(*x.shape[:-1], size + pad)[..., :size]


def mx_scale_exponent(block_amax: torch.Tensor, element: FloatElement) -> torch.Tensor:
    """The E8M0 exponent k (int32) of MX blocks with maxima `block_amax`: scale X = 2^k."""
    return (floor_log2(block_amax) - element.emax).clamp(E8M0_MIN_EXPONENT, E8M0_MAX_EXPONENT)


def fake_quant_mx(x: torch.Tensor, element: FloatElement, block: int = MX_BLOCK) -> torch.Tensor:
    """OCP MX fake quantization along the last dimension (blocks of `block`, shared E8M0 scale)."""

    def quantize(blocks: torch.Tensor) -> torch.Tensor:
        amax = blocks.abs().amax(dim=-1, keepdim=True)
        scale = pow2(mx_scale_exponent(amax, element))
        scale = torch.where(torch.isnan(amax), amax, scale)  # E8M0 NaN: the whole block is NaN
        return round_to_element(blocks / scale, element) * scale

    return _blocks(x.float(), block, quantize).to(x.dtype)


def nvfp4_tensor_scale(amax: torch.Tensor) -> torch.Tensor:
    """FP32 tensor scale of NVFP4: amax / (448 * 6), so the largest block scale reaches 448."""
    return amax.float().clamp_min(SCALE_FLOOR) / (E4M3.max_normal * E2M1.max_normal)


def nvfp4_block_scales(block_amax: torch.Tensor, tensor_scale: torch.Tensor) -> torch.Tensor:
    """E4M3 block scales (as float32) of NVFP4 blocks with maxima `block_amax`."""
    tiny = 2.0**E4M3.min_normal_exponent
    return round_to_element((block_amax / E2M1.max_normal / tensor_scale).clamp(tiny, E4M3.max_normal), E4M3)


def fake_quant_nvfp4(x: torch.Tensor, tensor_amax: torch.Tensor | None = None, block: int = NVFP4_BLOCK) -> torch.Tensor:
    """NVFP4 fake quantization along the last dimension. `tensor_amax` (broadcastable to x with the
    last dimension kept, e.g. one value per sample) defaults to the amax of all of x."""
    xf = x.float()
    amax = xf.abs().amax() if tensor_amax is None else tensor_amax.float()
    tensor_scale = nvfp4_tensor_scale(amax)
    if tensor_scale.dim():
        tensor_scale = tensor_scale.unsqueeze(-1)  # [..., 1] per row -> [..., 1, 1] per block row

    def quantize(blocks: torch.Tensor) -> torch.Tensor:
        block_scale = nvfp4_block_scales(blocks.abs().amax(dim=-1, keepdim=True), tensor_scale)
        scaled = (blocks * ((1.0 / tensor_scale) / block_scale)).clamp(-E2M1.max_normal, E2M1.max_normal)
        return round_to_element(scaled, E2M1) * (tensor_scale * block_scale)

    return _blocks(xf, block, quantize).to(x.dtype)


def fake_quant_fp8(x: torch.Tensor, element: FloatElement, per_row: bool) -> torch.Tensor:
    """FP8 fake quantization with one scale per row of the last dimension (`per_row`) or one for
    all of x: s = max(amax, SCALE_FLOOR) / max_elem, x_hat = s * Q(x / s)."""
    xf = x.float()
    amax = xf.abs().amax(dim=-1, keepdim=True) if per_row else xf.abs().amax()
    scale = amax.clamp_min(SCALE_FLOOR) / element.max_normal
    return (round_to_element(xf / scale, element) * scale).to(x.dtype)
