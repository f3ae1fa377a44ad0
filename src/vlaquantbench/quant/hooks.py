"""Activation pre-hooks on linear layers that count their own calls.

The count is the evidence that a layer's input was really transformed during a run (paper
`sec:pitfalls`, "Activation coverage"): a hook installed on a module that the forward path never
calls leaves the run silently weight-only for that layer.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from vlaquantbench.quant.grid import fake_quant_activation
from vlaquantbench.quant.presets import FloatFormat


@dataclass(frozen=True)
class InputTransform:
    """What a hook does to a linear input, in the paper's order: divide by the smoothing vector,
    clip at the per-channel threshold, then quantize: per token on an integer grid (`act_bits`) or
    in a floating-point format (`act_format`, per block / token / sample). Every step is optional."""

    smooth: torch.Tensor | None = None  # d_j, shape [in_features]
    clip: torch.Tensor | None = None  # post-smoothing threshold, shape [in_features]
    act_bits: int | None = None
    act_format: FloatFormat | None = None

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.smooth is not None:
            x = (x.float() / self.smooth).to(x.dtype)
        if self.clip is not None:
            x = torch.maximum(torch.minimum(x.float(), self.clip), -self.clip).to(x.dtype)
        if self.act_bits is not None:
            x = fake_quant_activation(x, self.act_bits)
        if self.act_format is not None:
            x = self.act_format.quantize_activation(x)
        return x

    @property
    def is_identity(self) -> bool:
        return self.smooth is None and self.clip is None and self.act_bits is None and self.act_format is None


class CountingHook:
    """A forward pre-hook applying `transform` to a linear layer's input and counting calls."""

    def __init__(self, layer: nn.Linear, transform: InputTransform):
        self.transform = transform
        self.calls = 0
        self.handle = layer.register_forward_pre_hook(self)

    def __call__(self, module: nn.Module, args: tuple) -> tuple:
        self.calls += 1
        return (self.transform(args[0]), *args[1:])

    def remove(self) -> None:
        self.handle.remove()
