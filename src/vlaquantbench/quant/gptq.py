"""GPTQ (Frantar et al., "GPTQ: Accurate Post-Training Quantization for Generative Pre-trained
Transformers", ICLR 2023): weights rounded one input column at a time, each column's rounding error
compensated on the columns not yet rounded, so that ||W X^T - Q X^T||^2 on the calibration inputs X
stays small, with H = X^T X (`quant.calibration`, `hessian` statistics of the rollout calibration).

Per layer, with the preset's integer weight grid (`quant.grid`):
- columns whose input never moved (H_jj = 0) are zeroed and get H_jj = 1;
- damping: H + damp * mean(diag H) * I (`GPTQ.damp`, 0.01 as in the paper);
- with `act_order`, columns are processed in descending H_jj;
- U = upper Cholesky factor of H^-1; for column j in processing order, q_j = Q(w_j) and every later
  column k gets w_k -= (w_j - q_j) U_jk / U_jj, applied lazily per block of columns (the paper's
  "lazy batch updates"; the result is the same as column by column);
- grids: per output channel, the grid of the whole (dead-zeroed) row, fixed up front; with groups
  (of consecutive input columns, as RTN's), the grid of each group is fixed when its first column is
  reached, from the group's weights updated so far (blocks are then the groups); with `act_order` and
  groups, every group's grid is fixed up front from the original weights ("static groups"), so the
  groups stay consecutive columns and the weights stay on the preset's declared grid.
Compensation runs in float64; grids and rounding in float32, exactly as RTN's, so with H = I (no
compensation) GPTQ gives RTN's weights bit for bit.

Activations, where the preset quantizes them, are quantized per token by counting hooks as in RTN.
After pre-quantization transforms (`hadamard_gptq`), each layer's Hessian is mapped into the space of
its transformed inputs by the transforms' linear input steps (`map_hessian`: R H R^T for an online
rotation, R D^-1 H D^-1 R^T for a reader of an offline-rotated stream whose norm gain D was folded
into it; `quant.rotation.FoldedInput`): the Hessians are collected on the untransformed model.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.apply import MethodResult, QuantConfig, install_input_hooks, layer_statistics
from vlaquantbench.quant.grid import RowGrid, grid_of
from vlaquantbench.quant.presets import WeightGrid
from vlaquantbench.quant.scope import Selection


@dataclass(frozen=True)
class LayerGPTQ:
    weight: torch.Tensor  # the rounded weight, [out, in] float32, on the weight grid
    dead_columns: int
    error: float  # tr((W - Q) H (W - Q)^T): squared output error on the calibration inputs
    rtn_error: float  # the same for RTN's weights on the same grid


def gptq_weight(weight: torch.Tensor, hessian: torch.Tensor, grid: WeightGrid, damp: float = 0.01,
                act_order: bool = False, block_size: int = 128) -> LayerGPTQ:
    """GPTQ-rounded `weight` ([out, in]) for the input second moment `hessian` = X^T X ([in, in])."""
    w = weight.detach().double().clone()
    columns = w.shape[1]
    h = hessian.to(w.device, torch.float64).clone()
    dead = h.diagonal() == 0
    h[dead, dead] = 1.0
    w[:, dead] = 0.0
    group = grid.group_size if grid.group_size and grid.group_size < columns else None
    fixed = _fixed_grids(w, grid, group) if group is None or act_order else None
    order = torch.argsort(h.diagonal(), descending=True, stable=True) if act_order else torch.arange(columns)
    order = order.to(w.device)
    # The processing order as host integers, read once: indexing the device tensor per column waited on the
    # GPU once per column (pi0.5's e2e: about a million columns).
    columns_in_order = order.tolist()
    if act_order:
        w, h = w[:, order], h[order][:, order]
    h.diagonal().add_(damp * h.diagonal().mean())
    upper = torch.linalg.cholesky(torch.cholesky_inverse(torch.linalg.cholesky(h)), upper=True)
    del h  # an [in, in] float64 copy fewer while rounding (2 GiB for pi0.5's 16,384-wide down_proj)
    rounded = torch.empty_like(w)
    block = group if fixed is None else block_size
    for start in range(0, columns, block):
        end = min(start + block, columns)
        pending = w[:, start:end].clone()
        errors = torch.zeros_like(pending)
        group_grid = grid_of(pending, grid.bits, grid.symmetric) if fixed is None else None  # block == group
        for i in range(end - start):
            column = columns_in_order[start + i]
            row_grid = group_grid if fixed is None else fixed[column // group if group else 0]
            q = row_grid.quantize_column(pending[:, i]).double()
            rounded[:, start + i] = q
            errors[:, i] = (pending[:, i] - q) / upper[start + i, start + i]
            pending[:, i:] -= errors[:, i : i + 1] * upper[start + i, start + i : end][None, :]
        w[:, end:] -= errors @ upper[start:end, end:]
    result = torch.empty_like(rounded)
    result[:, order] = rounded
    original = weight.detach().double()
    return LayerGPTQ(result.float(), int(dead.sum()), _output_error(original - result, hessian),
                     _output_error(original - grid.quantize_weight(weight.detach().float()).double(), hessian))


def _fixed_grids(w: torch.Tensor, grid: WeightGrid, group: int | None) -> list[RowGrid]:
    """The grid of each group of consecutive columns (one for the whole row without groups)."""
    width = group or w.shape[1]
    return [grid_of(w[:, start:start + width], grid.bits, grid.symmetric) for start in range(0, w.shape[1], width)]


def _output_error(delta: torch.Tensor, hessian: torch.Tensor) -> float:
    """||delta X^T||^2 = tr(delta H delta^T)."""
    return float(((delta @ hessian.to(delta.device, torch.float64)) * delta).sum())


def gptq(model: nn.Module, selection: Selection, config: QuantConfig) -> MethodResult:
    """The `gptq` methods: GPTQ weights on the preset's integer grid for every selected layer, from
    the calibration Hessians, then the preset's activation quantization through counting hooks."""
    method, preset = config.method, config.preset
    method.check_preset(method.name, preset)
    stats = layer_statistics(
        selection, config, method.name, "GPTQ calibration statistics (X^T X of its inputs)",
        "collect them on the unquantized policy with quant.calibration.observe(layers, sample_rows=128, hessian=True) "
        "and pass stats=... (the runner's calibrate step does this for gptq cells)",
        usable=lambda layer: layer.hessian is not None)
    grid: WeightGrid = preset.weight
    ratios, dead = [], 0
    for name in selection.flat():  # every layer's input steps and Hessian checked before any rounding
        for step in selection.inputs.get(name, ()):
            if not hasattr(step, "map_hessian"):
                raise UserError(f"method {method.name!r} cannot map layer {name}'s Hessian through the input step "
                                f"{type(step).__name__} of a pre-quantization transform (only linear steps, e.g. Hadamard)")
        # A NaN or infinite input while calibrating puts NaN or infinity into X^T X, which would round the layer
        # to NaN weights, or not, depending on where the factorization meets it. The input's absmax (a vector,
        # NaN-propagating like the Hessian's sums) shows it without reading the Hessians twice (24 GiB, mapped).
        if not torch.isfinite(stats[name].absmax).all():
            raise UserError(f"method {method.name!r}: layer {name}'s inputs held non-finite values while calibrating "
                            f"(calibration statistics {config.stats.key}.pt), so its Hessian is unusable; calibrate again")
    for name, layer in selection.flat().items():
        # One layer's float64 Hessian at a time, in the space of the inputs the transforms leave: pi0.5's e2e
        # Hessians are 24 GiB in float32 (OpenVLA-OFT's 34), which `load_stats` maps rather than reads. Made on
        # the layer's device from the mapped file's float32 (converted there: `.to(device, float64)` converts
        # on the host first), so on a GPU neither the float64 copy nor the rotations' products (`map_hessian`)
        # are host work.
        hessian = stats[name].hessian.to(layer.weight.device).double()
        for step in selection.inputs.get(name, ()):
            hessian = step.map_hessian(hessian)
        try:
            done = gptq_weight(layer.weight, hessian, grid, method.damp, method.act_order, method.block_size)
        except torch.linalg.LinAlgError as error:
            raise UserError(f"method {method.name!r}: layer {name}'s Hessian plus damping ({method.damp} of its mean "
                            f"diagonal) is not positive definite, so GPTQ cannot invert it ({error}); give the "
                            "method a larger damp or calibrate on more rows") from error
        del hessian  # before the next layer's is made
        with torch.no_grad():
            layer.weight.copy_(done.weight.to(layer.weight.dtype))
        dead += done.dead_columns
        ratios.append(done.error / done.rtn_error if done.rtn_error > 0 else 1.0)
    result = MethodResult(
        format=f"GPTQ {preset.describe()}; damp {method.damp}, act_order {method.act_order}, Hessians from rollout "
               f"calibration (cache {config.stats.key})",
        calibrated=set(selection.flat()),
        details={"gptq": {
            "damp": method.damp, "act_order": method.act_order, "block_size": method.block_size,
            "dead_columns": dead,
            # mean over layers of GPTQ's squared output error on the calibration inputs / RTN's (1.0: no gain)
            "error_vs_rtn_mean": sum(ratios) / len(ratios) if ratios else None,
            "error_vs_rtn_max": max(ratios, default=None),
            "stats_cache": f"{config.stats.key}.pt",
        }},
    )
    install_input_hooks(result, selection, preset)
    return result
