"""What a counting hook (`quant.hooks`) does to a linear's input: `InputTransform`, the reference
that the fused kernels (`quant.fused_kernel`) reproduce and the transforms (`quant.transforms`) build."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from vlaquantbench.quant.grid import fake_quant_activation
from vlaquantbench.quant.presets import FloatFormat


@dataclass(frozen=True)
class InputTransform:
    """What a hook does to a linear input, in the paper's order: rotate (an orthonormal rotation
    folded into the weight, `quant.hadamard.BlockHadamard`), divide by the smoothing vector,
    clip at the per-channel threshold, then quantize: per token on an integer grid (`act_bits`) or
    in a floating-point format (`act_format`, per block / token / sample). Every step is optional."""

    smooth: torch.Tensor | None = None  # d_j, shape [in_features]
    clip: torch.Tensor | None = None  # post-smoothing threshold, shape [in_features]
    act_bits: int | None = None
    act_format: FloatFormat | None = None
    # x -> R x, equal (and hashed) by what it computes, so layers sharing an input share it
    rotation: Callable[[torch.Tensor], torch.Tensor] | None = None

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        if self.rotation is not None:
            x = self.rotation(x)
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
        return (self.smooth is None and self.clip is None and self.act_bits is None and self.act_format is None
                and self.rotation is None)
