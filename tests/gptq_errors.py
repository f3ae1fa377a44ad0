"""GPTQ's output error against round-to-nearest's at the same weight grid, layer by layer, on the
calibration inputs (all observed rows, through their second moment X^T X): what the GPTQ checks of
the demo and trained policies measure."""

import torch

from vlaquantbench.quant.gptq import gptq_weight
from vlaquantbench.quant.presets import parse_preset


def output_error(weight, quantized, hessian) -> float:
    """||X (W - Q)^T||_F^2 = sum_o d_o^T H d_o with d = W - Q, H = X^T X, in float64."""
    delta = weight.detach().double() - quantized.double()
    return float(torch.einsum("oi,ij,oj->", delta, hessian.double(), delta))


def gptq_against_rtn(layers, stats, presets) -> tuple[list[float], list[tuple[str, str, float]]]:
    """Per (preset, layer) of `layers` (name -> linear), GPTQ's output error over RTN's at the preset's
    weight grid with the layer's calibration Hessian from `stats`: (every ratio, the (preset, layer,
    ratio) where GPTQ's error exceeds RTN's beyond rounding)."""
    ratios, worse = [], []
    for preset in presets:
        grid = parse_preset(preset).weight
        for name, layer in layers.items():
            hessian = stats.layers[name].hessian
            gptq_error = output_error(layer.weight, gptq_weight(layer.weight, hessian, grid, damp=0.01).weight, hessian)
            rtn_error = output_error(layer.weight, grid.quantize_weight(layer.weight.detach().float()), hessian)
            ratios.append(gptq_error / rtn_error if rtn_error else 1.0)
            if gptq_error > rtn_error * (1 + 1e-9):
                worse.append((preset, name, gptq_error / rtn_error))
    return ratios, worse
