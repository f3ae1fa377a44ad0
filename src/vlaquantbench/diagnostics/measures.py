"""Per-call layer diagnostics as pure tensor functions (paper App. `app:diagnostics`).

For a linear layer with input x [tokens, features], weight W and its quantized counterparts
Q(x), Q(W) under a preset:
  act_kurtosis    fourth standardized moment of the input values (Pearson, not excess)
  act_rel_err     ‖Q(x) − x‖ / ‖x‖
  out_rel_err     ‖Q(x) Q(W)ᵀ − x Wᵀ‖ / ‖x Wᵀ‖  (local: the layer alone, on full-precision inputs)
  act_dispersion  max over tokens of the per-token absmax divided by its mean over tokens
                  (1 for a single token; large when a few tokens set the quantizer's range)
"""

from __future__ import annotations

import torch

MEASURES = ("act_kurtosis", "out_rel_err", "act_rel_err", "act_dispersion")


def kurtosis(x: torch.Tensor) -> float:
    v = x.double().flatten()
    c = v - v.mean()
    var = c.pow(2).mean()
    return float(c.pow(4).mean() / var.pow(2)) if var > 0 else float("nan")


def relative_error(approx: torch.Tensor, exact: torch.Tensor) -> float:
    norm = exact.double().norm()
    return float((approx.double() - exact.double()).norm() / norm) if norm > 0 else 0.0


def dispersion(x: torch.Tensor) -> float:
    tok_absmax = x.double().reshape(-1, x.shape[-1]).abs().amax(dim=1)
    mean = tok_absmax.mean()
    return float(tok_absmax.max() / mean) if mean > 0 else 1.0


@torch.no_grad()
def layer_measures(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None,
                   quant_x: torch.Tensor, quant_weight: torch.Tensor) -> dict[str, float]:
    """All four diagnostics of one call of one layer."""
    exact = torch.nn.functional.linear(x.double(), weight.double(), None if bias is None else bias.double())
    approx = torch.nn.functional.linear(quant_x.double(), quant_weight.double(), None if bias is None else bias.double())
    return {
        "act_kurtosis": kurtosis(x),
        "out_rel_err": relative_error(approx, exact),
        "act_rel_err": relative_error(quant_x, x),
        "act_dispersion": dispersion(x),
    }
