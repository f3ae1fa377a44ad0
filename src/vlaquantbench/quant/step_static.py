"""`step_static`: RTN weights and static activation scales, per denoising (flow) step where a layer runs
inside flow steps (the action head of a flow-matching policy; Ω-QVLA's per-step activation scales).

A flow-matching head sees inputs whose range changes with the flow time t (noise at the first step,
nearly clean actions at the last), so one static scale per layer must cover every step's range. Here
each layer that ran inside flow steps during the rollout calibration (`quant.calibration`:
`step_absmax`, max |x| per step) quantizes its input on the symmetric `act_bits` grid of the step
the policy is computing, which its flow-step clock says (`quant.steps`); every other layer (the prefix
pass, the vision tower, a model without a flow loop) on the grid of its per-layer max |x|. Scales are
per tensor (one number per layer and step): what a static integer product can apply.

    s = max(max|x| of the step (or layer), 1e-8) / (2^(b-1) - 1)
    x_hat = s * clip(round(x / s), -2^(b-1), 2^(b-1) - 1)

Values beyond the calibrated range saturate. A step the calibration never saw (a cell running more
flow steps than its calibration; they share a calibration only with equal `runner.flow_steps`) is
an error, never another step's scale.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from vlaquantbench.quant.apply import MethodResult, QuantConfig, layer_statistics
from vlaquantbench.quant.grid import SCALE_FLOOR, RowGrid
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.scope import Selection
from vlaquantbench.quant.steps import FlowStepClock, flow_clock


def static_grid(absmax: torch.Tensor, bits: int, device: torch.device | str = "cpu") -> RowGrid:
    """The symmetric `bits`-bit grid whose largest level is `absmax` (a 0-d tensor), on `device`."""
    q_max = 2 ** (bits - 1) - 1
    scale = absmax.float().to(device).clamp_min(SCALE_FLOOR) / q_max
    return RowGrid(scale, torch.zeros_like(scale), -(q_max + 1), q_max)


@dataclass(frozen=True)
class StepStaticQuantizer:
    """One layer's input on the static grid of the running flow step (`step_grids`), or of the layer
    (`layer_grid`) outside steps or for a layer that never ran inside one."""

    name: str
    clock: FlowStepClock | None
    layer_grid: RowGrid
    step_grids: tuple[RowGrid, ...] = ()

    def grid(self) -> RowGrid:
        step = self.clock.step if self.clock is not None and self.step_grids else None
        if step is None:
            return self.layer_grid
        if step >= len(self.step_grids):
            raise RuntimeError(f"{self.name}: flow step {step} is running, but the calibration saw "
                               f"{len(self.step_grids)} steps; calibrate with the cell's runner.flow_steps")
        return self.step_grids[step]

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return self.grid().quantize(x).to(x.dtype)


def step_static(model: nn.Module, selection: Selection, config: QuantConfig) -> MethodResult:
    """RTN weights (as `quant.apply.rtn`) and `StepStaticQuantizer` input hooks on every selected layer."""
    preset = config.preset
    layers = layer_statistics(selection, config, "step_static", "calibration statistics (input absmax)",
                              "collect them in the rollout calibration of its cell (calibration step_scales)")
    clock = flow_clock(model)
    result = MethodResult(format=f"RTN weights {preset.weight.describe()}; activations {preset.act_bits}-bit "
                                 "symmetric, static per-tensor scales per flow step (per layer outside flow steps)")
    per_step = 0
    with torch.no_grad():
        for name, layer in selection.flat().items():
            layer.weight.copy_(preset.weight.quantize_weight(layer.weight))
            stats, device = layers[name], layer.weight.device
            steps = () if stats.step_absmax is None else tuple(
                static_grid(a, preset.act_bits, device) for a in stats.step_absmax)
            per_step += bool(steps)
            result.hooks[name] = CountingHook(layer, StepStaticQuantizer(
                name, clock, static_grid(stats.absmax.max(), preset.act_bits, device), steps))
    result.calibrated = set(result.hooks)
    flow_steps = max((len(s.step_absmax) for s in layers.values() if s.step_absmax is not None), default=0)
    result.details["step_static"] = {"per_step_layers": per_step, "per_layer_layers": len(layers) - per_step,
                                     "flow_steps": flow_steps}
    return result
