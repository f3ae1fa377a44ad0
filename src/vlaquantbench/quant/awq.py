"""Activation-aware weight quantization (AWQ, Lin et al. 2024): the per-layer scale search, as
pure tensor functions (the `awq` method in `quant.kernels` applies the result to a model).

Input channels that carry large activations matter most to the output, so AWQ scales them up
before weight quantization and divides the input by the same scale (an exact identity without
quantization): y = Q(W diag(s)) (x / s). With m_j the mean |x_j| over the calibration rows,

    s(alpha) = m^alpha / sqrt(max(m^alpha) * min(m^alpha))     (m floored at 1e-5)

and alpha is searched on {0, 0.05, ..., 1} for the smallest output error on sampled input rows X,

    E(alpha) = || Q(W diag(s)) (X / s)^T - W X^T ||^2,

where Q is the weight grid of the preset (W4: asymmetric, group 128, `quant.grid`). alpha = 0
gives s = 1, i.e. plain RTN, so the search never does worse than RTN on the calibration rows;
ties keep the smaller alpha.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from vlaquantbench.quant.grid import fake_quant_weight

ALPHAS = tuple(round(0.05 * i, 2) for i in range(21))
MEAN_FLOOR = 1e-5


@dataclass(frozen=True)
class ScaleSearch:
    scales: torch.Tensor  # [in_features] float32, s of the chosen alpha
    alpha: float
    error: float  # E(alpha) on the calibration rows
    rtn_error: float  # E(0): the plain RTN error on the same rows


def awq_scales(act_absmean: torch.Tensor, alpha: float) -> torch.Tensor:
    """s = m^alpha, normalised by sqrt(max(s) * min(s)) so the scales straddle 1."""
    s = act_absmean.float().clamp_min(MEAN_FLOOR).pow(alpha)
    return s / (s.max() * s.min()).sqrt()


def scaled_quant_error(
    weight: torch.Tensor, scales: torch.Tensor, rows: torch.Tensor, bits: int, group_size: int | None,
    symmetric: bool,
) -> float:
    """|| Q(W diag(s)) (X / s)^T - W X^T ||^2 in float32 (X: calibration rows, one per row)."""
    w = weight.detach().float()
    x = rows.float().to(w.device)
    s = scales.float().to(w.device)
    quantized = fake_quant_weight(w * s, bits, group_size, symmetric)
    return ((x / s) @ quantized.t() - x @ w.t()).pow(2).sum().item()


def search_scales(
    weight: torch.Tensor, act_absmean: torch.Tensor, rows: torch.Tensor, bits: int, group_size: int | None,
    symmetric: bool = False, alphas: tuple[float, ...] = ALPHAS,
) -> ScaleSearch:
    """The alpha of `alphas` with the smallest `scaled_quant_error` (the first on ties), and its scales."""
    act_absmean = act_absmean.to(weight.device)
    errors: dict[float, float] = {}
    for alpha in alphas:
        errors[alpha] = scaled_quant_error(weight, awq_scales(act_absmean, alpha), rows, bits, group_size, symmetric)
    best = min(errors, key=errors.__getitem__)  # min keeps the first of equal errors
    ones = torch.ones(weight.shape[-1], device=weight.device)
    rtn = errors[0.0] if 0.0 in errors else scaled_quant_error(weight, ones, rows, bits, group_size, symmetric)
    return ScaleSearch(awq_scales(act_absmean, best), float(best), errors[best], rtn)
