"""Pre-quantization transforms: rewrite selected layers, without changing what they compute, before
a method quantizes them. `QuantConfig.transforms` is an ordered list; `quantize_` applies each in turn,
then runs the method on the transformed weights.

A transform changes weights in place and returns, per layer it changed, the step the layer's input
must take first (a callable on the input tensor, e.g. `InputTransform(smooth=d, clip=c)`): with it, the
layer's output is unchanged up to the transform's own approximation (clipping). Methods that compose
with transforms (`rtn`, `gptq`) run those steps, in order, ahead of their activation quantization
(`input_steps`); the others refuse a non-empty list.

    Smoothing   rollout smoothing and clipping (paper `app:calib`): W diag(d), x / d clipped at the
                calibrated quantile, on the layers of the calibrated components
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from vlaquantbench.quant.calibration import FLOOR, CalibrationSettings, CalibrationStats, smoothing_factors
from vlaquantbench.quant.hooks import InputTransform
from vlaquantbench.quant.methods import ABSMAX
from vlaquantbench.quant.presets import Preset

if TYPE_CHECKING:
    from vlaquantbench.quant.scope import Selection


@dataclass(frozen=True)
class Smoothing:
    """SmoothQuant-style migration from rollout statistics, d_j = max(a_j^alpha / w_j^(1-alpha), 1e-5)
    (`quant.calibration.smoothing_factors`), and clipping of x / d at quantile_j / d_j (none when the
    settings' quantile is None: then an exact identity before quantization)."""

    settings: CalibrationSettings
    statistics = frozenset({ABSMAX})

    def apply(self, selection: Selection, stats: CalibrationStats | None) -> dict[str, Callable]:
        steps = {}
        for name, layer in selection.flat().items():
            layer_stats = stats.layers.get(name) if selection.component_of(name) in self.settings.components else None
            if layer_stats is None:  # layers never observed during calibration stay untransformed
                continue
            with torch.no_grad():
                smooth = smoothing_factors(layer_stats.absmax, layer.weight, self.settings.alpha)
                clip = None
                if self.settings.quantile is not None:
                    clip = (layer_stats.quantile.float().to(smooth.device) / smooth).clamp_min(FLOOR)
                layer.weight.copy_((layer.weight.float() * smooth).to(layer.weight.dtype))
            steps[name] = InputTransform(smooth=smooth, clip=clip)
        return steps


def input_steps(steps: Sequence[Callable], preset: Preset) -> Callable:
    """One layer's input transform: the transforms' steps in order, then the preset's activation
    quantization. A single smoothing step folds into one `InputTransform` (the form the fast paths
    and the paper's order know: divide, clip, quantize)."""
    quantize = InputTransform(act_bits=preset.act_bits, act_format=preset.act_format)
    if not steps:
        return quantize
    if len(steps) == 1 and isinstance(steps[0], InputTransform) and steps[0].act_bits is None:
        return InputTransform(smooth=steps[0].smooth, clip=steps[0].clip, act_bits=preset.act_bits,
                              act_format=preset.act_format)
    return _Chain((*steps, quantize))


@dataclass(frozen=True)
class _Chain:
    """Several input steps applied in order."""

    steps: tuple[Callable, ...]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        for step in self.steps:
            x = step(x)
        return x

    @property
    def is_identity(self) -> bool:
        return False
