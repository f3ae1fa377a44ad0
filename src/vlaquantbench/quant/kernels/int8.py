"""W8A8 int8 kernels (`torch._int_mm`): `int8_dynamic`, and `smoothquant` with its migration vector
folded into the weights."""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.calibration import smoothing_factors
from vlaquantbench.quant.kernels.packed import PerTokenLinear, quantize_per_token, replace_all, require_preset
from vlaquantbench.quant.kernels.scaled_gemm import scaled_gemm, tile_for

# The CPU's int8 product (`torch._int_mm` there) is padded as cuBLASLt's needed it (more than 16 rows, in multiples
# of 8); on CUDA the product is `scaled_gemm`, which takes any number of rows.
INT_MM_MIN_ROWS = 32


def dequantize_int32(acc: torch.Tensor, row_scales: torch.Tensor, col_scales: torch.Tensor,
                     dtype: torch.dtype) -> torch.Tensor:
    """(acc * row_scales) * col_scales in float32, rounded once to `dtype`: an int8 product's int32
    sums back to the layer's scale (`scaled_gemm`'s epilogue computes the same on CUDA)."""
    return (acc.float() * row_scales * col_scales).to(dtype)


class Int8DynamicLinear(PerTokenLinear):
    """W8A8 int8: y = (round(x/s_x) @ W_q^T) * s_x * s_w (+ b), int32 accumulation in `torch._int_mm`
    (exact), the scales applied in float32 and the result rounded once to the layer's dtype.

    `smooth` (SmoothQuant's d) is folded into the weights and divided out of the input first; a
    layer without it takes its input cast per token by its producer (`input_cast`)."""

    WEIGHT, INPUT = "weight_int8", torch.int8
    KERNEL = "Triton scaled GEMM (int8 x int8 -> int32, float32 rescale in its epilogue)"
    CPU_KERNEL = "torch._int_mm (int8 x int8 -> int32) + float32 rescale"  # what a layer on the CPU runs

    def __init__(self, linear: nn.Linear, smooth: torch.Tensor | None = None):
        super().__init__(linear)
        if not linear.weight.is_cuda:
            self.KERNEL = self.CPU_KERNEL
        weight = linear.weight.detach().float()
        if smooth is not None:
            weight = weight * smooth
        scale = weight.abs().amax(dim=1, keepdim=True).clamp_min(1e-8) / 127.0
        self.register_buffer("weight_int8", torch.clamp(torch.round(weight / scale), -128, 127).to(torch.int8))
        self.register_buffer("weight_scale", scale.t().contiguous())  # 1 x out
        self.register_buffer("smooth", None if smooth is None else smooth.float())

    @property
    def per_token_input(self) -> bool:
        return self.smooth is None

    def _as_merged(self) -> None:
        self.register_buffer("smooth", None)

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        if self.smooth is not None:
            x2d = x2d.float() / self.smooth
        return self._product(*quantize_per_token(x2d, torch.int8))

    def _product(self, values: torch.Tensor, scales: torch.Tensor) -> torch.Tensor:
        rows = values.shape[0]
        if values.is_cuda and not torch.compiler.is_compiling():
            tile = tile_for("int8", rows, self.in_features, self.weight_int8.shape[0])
            return scaled_gemm(values, self.weight_int8.t(), scales, self.weight_scale, self.out_dtype, tile)
        padded = max(INT_MM_MIN_ROWS, (rows + 7) // 8 * 8)
        if padded != rows:
            values = F.pad(values, (0, 0, 0, padded - rows))
        acc = torch._int_mm(values, self.weight_int8.t())[:rows]
        return dequantize_int32(acc, scales, self.weight_scale, self.out_dtype)


def int8_dynamic(model, selection, config):
    """W8A8 int8 without smoothing: the int8 counterpart of `fp8` (in pi0.5's captured sampler the
    producing op casts the input rows, and q/k/v and gate/up run as one product)."""
    require_preset(config, "int8_dynamic")
    return replace_all(model, selection, lambda n, m: Int8DynamicLinear(m),
                        "W8A8 int8 (per-channel weights, dynamic per-token activations, int32 accumulation, "
                        "float32 rescale; Triton scaled GEMM on CUDA, torch._int_mm on the CPU)")


def smoothquant(model, selection, config):
    """SmoothQuant W8A8: migrate activation outliers into the weights with d_j = a_j^alpha / w_j^(1-alpha)
    (`quant.calibration.smoothing_factors`), then int8 per-channel weights and per-token inputs.
    Layers of components the calibration does not cover (the pi models' projector) run unsmoothed."""
    require_preset(config, "smoothquant")
    if config.calibration is None or config.calibration.alpha is None:
        raise UserError("method 'smoothquant' smooths by definition: pass calibration=CalibrationSettings(alpha=...) "
                        "and stats=... (the runner's calibrate step collects them for smoothquant cells)")
    smoothed = set()

    def make(name, linear):
        stats = config.stats.layers.get(name) if selection.component_of(name) in config.calibration.components else None
        if stats is None:
            return Int8DynamicLinear(linear)
        smoothed.add(name)
        return Int8DynamicLinear(linear, smoothing_factors(stats.absmax, linear.weight, config.calibration.alpha))

    result = replace_all(model, selection, make,
                          "W8A8 int8 (per-channel weights, dynamic per-token activations, int32 accumulation), SmoothQuant "
                          f"migration alpha={config.calibration.alpha} from rollout calibration statistics "
                          f"(cache {config.stats.key}; not the paper's 512 text samples)")
    result.calibrated = smoothed
    return result
