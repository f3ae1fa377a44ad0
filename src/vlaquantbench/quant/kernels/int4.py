"""4-bit weight-only kernels: `int4wo`, and `awq` with its activation-aware scales (`quant.awq`). On CUDA the
product is `scaled_gemm.w4a16_gemm` (Triton: the weights dequantized to bf16 inside the GEMM, tiles for pi0.5's
50 to thousands of rows); on the CPU PyTorch's tinygemm (`torch._weight_int4pack_mm_for_cpu`)."""

from __future__ import annotations

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.apply import MethodResult, layer_statistics
from vlaquantbench.quant.awq import search_scales
from vlaquantbench.quant.grid import fake_quant_weight
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.kernels.packed import PackedLinear, replace_all, require_preset, swap_linear
from vlaquantbench.quant.kernels.scaled_gemm import pack_int4, tile_for, w4a16_gemm


class Int4WeightOnlyLinear(PackedLinear):
    """int4 weights in asymmetric groups along the input, bf16 activations: on CUDA `w4a16_gemm` (Triton, its
    own packing `pack_int4`, scales and zeros as groups x out bf16 rows), on the CPU PyTorch's tinygemm
    (`torch._weight_int4pack_mm_for_cpu`).

    Both dequantize w = (q - 8) * scale + zero, so zero = min + 8 * scale for q in 0..15, scale and zero stored
    in bf16. The input size is padded to a multiple of 128 and of the group: a layer whose input is not
    (SigLIP's fc2 reads 4,304 values, pi0.5's action_in_proj 32) gets zero weight columns up to the next
    multiple, its last group's range then also spanning 0; the Triton kernel masks the input past its own
    columns, tinygemm reads a zero-padded copy of it."""

    INNER_K_TILES = 8  # tinygemm's packing (CPU)

    def __init__(self, linear: nn.Linear, group_size: int):
        super().__init__(linear)
        out_features, in_features = linear.weight.shape
        cuda = linear.weight.is_cuda
        if not cuda and out_features % 16:
            raise UserError(f"int4wo: out_features {out_features} is not a multiple of 16 (tinygemm's packing on the CPU)")
        multiple = max(self.INNER_K_TILES * 16, group_size)
        self.padded_in = -(-in_features // multiple) * multiple
        weight = F.pad(linear.weight.detach().float(), (0, self.padded_in - in_features))
        weight = weight.reshape(out_features, -1, group_size)
        low = weight.amin(dim=-1, keepdim=True)
        scale = ((weight.amax(dim=-1, keepdim=True) - low) / 15.0).clamp_min(1e-6)
        q = torch.clamp(torch.round((weight - low) / scale), 0, 15).reshape(out_features, self.padded_in)
        zero = low + 8.0 * scale
        self.group_size = group_size
        if cuda:
            self.KERNEL = "Triton W4A16 GEMM (int4 weights dequantized to bf16 in the kernel, bf16 activations)"
            self.register_buffer("weight_int4", pack_int4(q))
            self.register_buffer("scales", scale.squeeze(-1).t().contiguous().to(torch.bfloat16))  # groups x out
            self.register_buffer("zeros", zero.squeeze(-1).t().contiguous().to(torch.bfloat16))
            return
        self.KERNEL = "torch._weight_int4pack_mm_for_cpu (tinygemm: int4 weights, bf16 activations)"
        self.register_buffer("weight_int4", torch._convert_weight_to_int4pack_for_cpu(q.to(torch.int32),
                                                                                      self.INNER_K_TILES))
        scales_zeros = torch.stack([scale.squeeze(-1), zero.squeeze(-1)], dim=-1)  # out x groups x 2
        self.register_buffer("scales_and_zeros", scales_zeros.transpose(0, 1).contiguous().to(torch.bfloat16))

    def _matmul(self, x2d: torch.Tensor) -> torch.Tensor:
        if x2d.is_cuda:
            tile = tile_for("w4a16", x2d.shape[0], self.in_features, self.out_features)
            return w4a16_gemm(x2d, self.weight_int4, self.scales, self.zeros, self.group_size, torch.bfloat16, tile)
        x2d = F.pad(x2d.to(torch.bfloat16), (0, self.padded_in - self.in_features))
        return torch._weight_int4pack_mm_for_cpu(x2d, self.weight_int4, self.group_size, self.scales_and_zeros)


def int4_weight_only(model, selection, config):
    require_preset(config, "int4wo")
    group = config.preset.weight.group_size or 128
    return replace_all(model, selection, lambda n, m: Int4WeightOnlyLinear(m, group),
                        f"int4 weight-only, asymmetric group {group}, bf16 activations (Triton W4A16 GEMM on CUDA, "
                        "tinygemm on the CPU)")


def _int4_kernel_fits(linear: nn.Linear, grid) -> bool:
    """The int4 kernel takes 4-bit asymmetric groups of 32..256 with K a multiple of 128 and N of 8, on CUDA."""
    return (linear.weight.is_cuda and grid.bits == 4 and not grid.symmetric and grid.group_size in (32, 64, 128, 256)
            and linear.in_features % max(128, grid.group_size) == 0 and linear.out_features % 8 == 0)


def awq(model, selection, config):
    """AWQ: per layer, the `quant.awq` scale search on the calibration rows, then Q(W diag(s)) with
    an input hook dividing by s. W4 asymmetric groups on CUDA use the int4wo kernel
    (its grid spans [min, max] of each group, not the zero-including range of `quant.grid`)."""
    require_preset(config, "awq")
    grid = config.preset.weight
    stats = layer_statistics(selection, config, "awq", "AWQ calibration statistics (mean |x| and sampled input rows)",
                         "collect them on the unquantized policy with quant.calibration.observe(layers, "
                         "sample_rows=128) and pass stats=... (the runner's calibrate step does this for awq cells)",
                         usable=lambda layer: layer.samples is not None)
    fmt = f"awq-int{grid.bits}-" + (f"g{grid.group_size}" if grid.group_size else "channel")
    hooks, alphas, rows, error_ratios, kernel_layers = {}, [], [], [], 0
    for name, linear in selection.flat().items():
        absmean, samples = stats[name].absmean, stats[name].samples
        search = search_scales(linear.weight, absmean, samples, grid.bits, grid.group_size, grid.symmetric)
        with torch.no_grad():
            scaled = (linear.weight.float() * search.scales).to(linear.weight.dtype)
            if _int4_kernel_fits(linear, grid):
                linear.weight.copy_(scaled)
                target = Int4WeightOnlyLinear(linear, grid.group_size)
                swap_linear(model, name, linear, target)
                kernel_layers += 1
            else:
                linear.weight.copy_(fake_quant_weight(scaled, grid.bits, grid.group_size, grid.symmetric))
                target = linear
        hooks[name] = CountingHook(target, InputTransform(smooth=search.scales))
        alphas.append(search.alpha)
        rows.append(samples.shape[0])
        error_ratios.append(search.error / search.rtn_error if search.rtn_error > 0 else 1.0)
    described = (
        f"{fmt}: activation-aware scales (alpha grid 0..1 step 0.05 on calibration rows), weights "
        f"{grid.describe()}; {kernel_layers} layers on the int4 kernel (Triton W4A16 GEMM), "
        f"{len(hooks) - kernel_layers} fake-quantized"
    )
    details = {
        "format": fmt,
        "alpha_histogram": {f"{a:.2f}": alphas.count(a) for a in sorted(set(alphas))},
        "alpha_mean": sum(alphas) / len(alphas) if alphas else None,
        "calibration_rows": {"min": min(rows, default=0), "max": max(rows, default=0)},
        # mean over layers of E(alpha*) / E(0) on the calibration rows (1.0: no gain over RTN)
        "error_vs_rtn_mean": sum(error_ratios) / len(error_ratios) if error_ratios else None,
        "kernel_layers": kernel_layers,
        "stats_cache": f"{config.stats.key}.pt" if config.stats is not None else None,
    }
    return MethodResult(format=described, hooks=hooks, calibrated=set(hooks), details={"awq": details})
