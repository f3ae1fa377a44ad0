"""The quantization method registry: every method `quantize_` can run, by name, without importing it.

    METHODS["fp8"].resolve()          # -> vlaquantbench.quant.kernels.fp8 (imported on first use)
    register_method("mine", fn)       # a method defined at run time (tests, plugins)

Cell names draw their methods from this table (`vlaquantbench.cells`), so every registered method is
reachable from a cell, and the workflow can check a cell's method while it builds the DAG without
importing torch. `statistics` says what a method needs from the calibration episodes: None (nothing),
{} (per-channel input statistics, e.g. FP8 static activation scales), {"alpha": a} (those statistics
and smoothing with migration strength a, SmoothQuant) or {"sample_rows": n} (AWQ's scale search on n
sampled input rows per layer, the paper's 128 calibration samples).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from vlaquantbench.errors import UserError, lookup
from vlaquantbench.quant.presets import Preset, WeightGrid


@dataclass(frozen=True)
class Method:
    implementation: str | Callable  # "module:function", imported by `resolve`, or the function itself
    statistics: dict[str, Any] | None = None
    # Presets the method implements: (weight bits, activation bits or None) of an integer preset,
    # WEIGHT_ONLY (any integer weight grid, activations unquantized), or None (every preset).
    presets: tuple[int, int | None] | str | None = None

    def check_preset(self, name: str, preset: Preset) -> None:
        """UserError when method `name` cannot run `preset` (the cell grammar checks it at DAG build)."""
        if self.presets is None:
            return
        integer = isinstance(preset.weight, WeightGrid) and preset.act_format is None
        if self.presets == WEIGHT_ONLY:
            if not integer or preset.act_bits is not None:
                raise UserError(f"method {name!r} is weight-only (W<b>[G<g>]); preset {preset.name!r} does not match")
            return
        bits, act_bits = self.presets
        if not integer or preset.weight.bits != bits or preset.act_bits != act_bits:
            want = f"W{bits}" + (f"A{act_bits}" if act_bits else "")
            raise UserError(f"method {name!r} implements {want}; preset {preset.name!r} does not match")

    def resolve(self) -> Callable:
        if callable(self.implementation):
            return self.implementation
        module, _, function = self.implementation.partition(":")
        return getattr(importlib.import_module(module), function)


WEIGHT_ONLY = "weight-only"
_KERNELS = "vlaquantbench.quant.kernels"
METHODS: dict[str, Method] = {
    "rtn": Method("vlaquantbench.quant.apply:rtn"),
    "nf4": Method(f"{_KERNELS}:nf4", presets=(4, None)),
    "int8": Method(f"{_KERNELS}:llm_int8", presets=(8, None)),
    "int4wo": Method(f"{_KERNELS}:int4_weight_only", presets=(4, None)),
    "awq": Method(f"{_KERNELS}:awq", statistics={"sample_rows": 128}, presets=WEIGHT_ONLY),
    # SmoothQuant's per-channel migration is the method: alpha 0.85 (the paper's deployment setting)
    "smoothquant": Method(f"{_KERNELS}:smoothquant", statistics={"alpha": 0.85}, presets=(8, 8)),
    "int8_dynamic": Method(f"{_KERNELS}:int8_dynamic", presets=(8, 8)),
    "fp8": Method(f"{_KERNELS}:fp8", presets=(8, 8)),
    "fp8_tensor": Method(f"{_KERNELS}:fp8_tensorwise", presets=(8, 8)),
    "fp8_static": Method(f"{_KERNELS}:fp8_static", statistics={}, presets=(8, 8)),
}


def register_method(name: str, fn: Callable, statistics: dict[str, Any] | None = None,
                    presets: tuple[int, int | None] | str | None = None) -> None:
    """Make `QuantConfig(method=name)` dispatch to `fn(model, selection, config) -> MethodResult`."""
    METHODS[name] = Method(fn, statistics, presets)


def registered_methods() -> list[str]:
    return sorted(METHODS)


def get_method(name: str) -> Method:
    return lookup(METHODS, name, "quantization method")
