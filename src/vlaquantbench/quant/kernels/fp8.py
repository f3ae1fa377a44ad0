"""W8A8 FP8 e4m3 kernels (`torch._scaled_mm`): per-channel / per-token (`fp8`), per tensor
(`fp8_tensor`), and with static calibrated activation scales (`fp8_static`)."""

from __future__ import annotations

import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.apply import layer_statistics
from vlaquantbench.quant.grid import SCALE_FLOOR
from vlaquantbench.quant.kernels.packed import FP8, FP8_MAX, PerTokenLinear, quantize_per_token, replace_all, require_preset
from vlaquantbench.quant.kernels.scaled_gemm import scaled_gemm, tile_for
from vlaquantbench.quant.scope import Selection


# Products of at most this many rows with per-token and per-channel scales run on `scaled_gemm` (small tiles) instead
# of `torch._scaled_mm`, whose 128 x 128 tiles leave the action expert's 50-row products on few SMs.
TRITON_MAX_ROWS = 64


class Fp8DynamicLinear(PerTokenLinear):
    """W8A8 FP8 e4m3 with per-output-channel weight scales and per-token activation scales, or with
    one scale per tensor for each (`tensorwise`)."""

    WEIGHT, INPUT = "weight_fp8", FP8
    KERNEL = (f"torch._scaled_mm (e4m3 x e4m3, FP32 scales); products of at most {TRITON_MAX_ROWS} rows with row-wise "
              "scales: Triton scaled GEMM (float32 accumulation)")

    def __init__(self, linear: nn.Linear, tensorwise: bool = False):
        super().__init__(linear)
        weight = linear.weight.detach().float()
        self.tensorwise = tensorwise
        amax = weight.abs().amax() if tensorwise else weight.abs().amax(dim=1, keepdim=True)
        scale = amax.clamp_min(1e-12) / FP8_MAX
        self.register_buffer("weight_fp8", (weight / scale).clamp(-FP8_MAX, FP8_MAX).to(FP8))
        self.register_buffer("weight_scale", scale.reshape(1, -1).contiguous())  # 1 x out (or 1 x 1), float32

    @property
    def per_token_input(self) -> bool:
        return not self.tensorwise

    def _as_merged(self) -> None:
        self.tensorwise = False

    def _quantize_input(self, x2d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if not self.tensorwise:
            return quantize_per_token(x2d, FP8)
        # One global amax, then one pass: dividing by the float32 scale promotes x inside the
        # kernel (no float32 copy of x first); under `torch.compile` both fuse into x's producer.
        scale = (x2d.abs().amax().float().clamp_min(SCALE_FLOOR) / FP8_MAX).reshape(1, 1)
        return torch.div(x2d, scale).clamp_(-FP8_MAX, FP8_MAX).to(FP8), scale

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        return self._product(*self._quantize_input(x2d))

    def _product(self, x_fp8: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        rows = x_fp8.shape[0]
        if (x_fp8.is_cuda and rows <= TRITON_MAX_ROWS and scale.numel() == rows > 1 and self.weight_scale.numel() > 1
                and not torch.compiler.is_compiling()):
            tile = tile_for("fp8", rows, self.in_features, self.weight_fp8.shape[0])
            return scaled_gemm(x_fp8, self.weight_fp8.t(), scale, self.weight_scale, self.out_dtype, tile)
        # Fast accumulation (Hopper's FP8 tensor-core accumulator without periodic FP32 promotion),
        # as FP8 inference stacks use it: 8.0 instead of 9.9 ms of GEMMs on the LLaMA benchmark.
        return torch._scaled_mm(x_fp8, self.weight_fp8.t(), scale_a=scale, scale_b=self.weight_scale,
                                out_dtype=self.out_dtype, use_fast_accum=x_fp8.is_cuda)


class Fp8StaticLinear(Fp8DynamicLinear):
    """W8A8 FP8 e4m3 with one weight scale and one static activation scale per layer, calibrated:
    the largest |x| the layer saw during calibration / 448. Quantizing the input is then one
    divide, clamp and cast with no reduction, which `torch.compile` fuses into the op producing
    the input; inputs beyond the calibrated range saturate at +-448 (the e4m3 maximum)."""

    def __init__(self, linear: nn.Linear, input_absmax: torch.Tensor):
        super().__init__(linear, tensorwise=True)
        scale = input_absmax.float().amax().clamp_min(SCALE_FLOOR) / FP8_MAX
        self.register_buffer("input_scale", scale.reshape(1, 1).to(linear.weight.device))

    def _quantize_input(self, x2d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return torch.div(x2d, self.input_scale).clamp_(-FP8_MAX, FP8_MAX).to(FP8), self.input_scale


def _require_rowwise_fp8(selection: Selection, method: str) -> None:
    """UserError, before any weight changes, unless every selected layer is on a CUDA GPU with FP8
    tensor cores: `torch._scaled_mm` with row-wise scales runs nowhere else (on the CPU, PyTorch
    2.11 scales only per tensor)."""
    for name, linear in selection.flat().items():
        device = linear.weight.device
        if device.type != "cuda" or torch.cuda.get_device_capability(device) < (8, 9):
            where = device.type if device.type != "cuda" else f"{device} ({torch.cuda.get_device_name(device)})"
            raise UserError(f"method {method!r} runs real FP8 kernels (torch._scaled_mm, row-wise scales), which need "
                            f"a CUDA GPU of compute capability 8.9 or newer (Ada, Hopper); layer {name!r} is on {where}. "
                            "Run the cell on such a GPU, or fake-quantize the same format with preset FP8E4M3 "
                            "(method rtn)")


def fp8(model, selection, config):
    require_preset(config, "fp8")
    _require_rowwise_fp8(selection, "fp8")
    return replace_all(model, selection, lambda n, m: Fp8DynamicLinear(m),
                        "W8A8 FP8 e4m3 (per-channel weights, dynamic per-token activations, torch._scaled_mm row-wise, fast accumulation)")


def fp8_tensorwise(model, selection, config):
    require_preset(config, "fp8_tensor")
    return replace_all(model, selection, lambda n, m: Fp8DynamicLinear(m, tensorwise=True),
                        "W8A8 FP8 e4m3 (one weight scale, one dynamic activation scale per call, torch._scaled_mm, fast accumulation)")


def fp8_static(model, selection, config):
    """FP8 W8A8 with static activation scales from the calibration statistics' per-channel absmax."""
    require_preset(config, "fp8_static")
    layers = layer_statistics(selection, config, "fp8_static", "calibration statistics (input absmax)",
                          "observe them on the unquantized policy with quant.calibration.observe(layers) "
                          "and pass stats=...")
    result = replace_all(model, selection, lambda n, m: Fp8StaticLinear(m, layers[n].absmax),
                          "W8A8 FP8 e4m3 (one weight scale, one static calibrated activation scale per layer, "
                          "torch._scaled_mm, fast accumulation)")
    result.calibrated = set(result.hooks)
    return result
