"""The quantization method registry: one typed config per method, by name, without importing torch.

    METHODS["gptq"]                   # GPTQ(name="gptq", damp=0.01, act_order=False, ...)
    METHODS["fp8"].resolve()          # -> vlaquantbench.quant.kernels.fp8.fp8 (imported on first use)
    register_method("mine", fn)       # a method defined at run time (tests, plugins)

Each entry is a frozen `MethodConfig` (torchao's `quantize_(model, config)` style): its implementation
`fn(model, selection, quant_config) -> MethodResult`, the calibration statistics it needs
(`statistics`, kinds below), the presets it implements, whether its layers can run inside a captured
CUDA graph (`uncapturable`: None, or why not), and its own options (GPTQ's damping, AWQ's sample size).
Cell names draw their methods from this table (`vlaquantbench.cells`), so every registered method is
reachable from a cell, and the workflow checks a cell's method, and what its calibration must
collect, while it builds the DAG without importing torch.

Statistics kinds (what the rollout calibration observes on a layer's input, `quant.calibration`):
    absmax       per-channel max |x| (and the clip quantile): smoothing, static FP8 scales
    rows         per-channel mean |x| and a strided sample of input rows (AWQ's search; every
                 method's `mean_rel_mse` report)
    hessian      X^T X over every observed row (GPTQ)
    step_scales  per-tensor max |x| per denoising (flow) step, on the layers that run inside the
                 steps the policy's flow-step clock marks (`quant.steps`; static per-step scales)
A method declaring a kind the calibration does not collect (a plugin's own) is refused when its
cell's config is built, naming it.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

from vlaquantbench.errors import UserError, lookup
from vlaquantbench.quant.presets import Preset, WeightGrid

ABSMAX, ROWS, HESSIAN, STEP_SCALES = "absmax", "rows", "hessian", "step_scales"
# What the rollout calibration (`quant.calibration.ActivationObserver`) can collect.
COLLECTED_STATISTICS = (ABSMAX, ROWS, HESSIAN, STEP_SCALES)
# Presets a method implements: (weight bits, activation bits or None) of an integer preset,
# WEIGHT_ONLY (any integer weight grid, activations unquantized), INTEGER_WEIGHTS (any integer weight
# grid, activations unquantized or per-token integer), or None (every preset).
WEIGHT_ONLY = "weight-only"
INTEGER_WEIGHTS = "integer-weights"
SAMPLE_ROWS = 128  # input rows per layer kept when `rows` are collected: the paper's 128 calibration samples


@dataclass(frozen=True)
class MethodConfig:
    """One quantization method: what `quantize_` runs and what it needs. Subclasses add options."""

    name: str
    implementation: str | Callable  # "module:function", imported by `resolve`, or the function itself
    statistics: frozenset[str] = field(default_factory=frozenset)
    presets: tuple[int, int | None] | str | None = None
    uncapturable: str | None = None  # why its layers cannot run inside a captured CUDA graph (None: they can)
    composes: bool = False  # runs after pre-quantization transforms (`quant.transforms`), reading `selection.inputs`
    transforms: tuple[str, ...] = ()  # transforms (`TRANSFORMS` names) a cell of this method applies first, in order

    def check_preset(self, name: str, preset: Preset) -> None:
        """UserError when method `name` cannot run `preset` (the cell grammar checks it at DAG build)."""
        if self.presets is None:
            return
        integer = isinstance(preset.weight, WeightGrid) and preset.act_format is None
        if self.presets in (WEIGHT_ONLY, INTEGER_WEIGHTS):
            if not integer or (self.presets == WEIGHT_ONLY and preset.act_bits is not None):
                what = "is weight-only (W<b>[G<g>])" if self.presets == WEIGHT_ONLY else "implements W<b>[G<g>][A<a>]"
                raise UserError(f"method {name!r} {what}; preset {preset.name!r} does not match")
            return
        bits, act_bits = self.presets
        if not integer or preset.weight.bits != bits or preset.act_bits != act_bits:
            want = f"W{bits}" + (f"A{act_bits}" if act_bits else "")
            raise UserError(f"method {name!r} implements {want}; preset {preset.name!r} does not match")

    def check_statistics(self) -> None:
        """UserError naming the method when it needs statistics the calibration cannot collect."""
        missing = sorted(self.statistics - set(COLLECTED_STATISTICS))
        if missing:
            raise UserError(f"method {self.name!r} needs calibration statistics {', '.join(missing)}, which the "
                            f"rollout calibration does not collect (it collects {', '.join(COLLECTED_STATISTICS)})")

    def calibration_fields(self) -> dict[str, Any] | None:
        """What the cell's calibration config records for this method: None (no calibration
        episodes), or the observer's options beyond the per-channel absmax every calibration keeps
        (`sample_rows`, `hessian`) and the smoothing strength the method applies (`alpha`)."""
        if not self.statistics:
            return None
        return {**({"sample_rows": SAMPLE_ROWS} if ROWS in self.statistics else {}),
                **({"hessian": True} if HESSIAN in self.statistics else {}),
                **({"step_scales": True} if STEP_SCALES in self.statistics else {})}

    def resolve(self) -> Callable:
        return _resolve(self.implementation)

    def named_transforms(self) -> tuple:
        """The transforms this method's cells apply before it, built (imported on first use)."""
        return tuple(_resolve(TRANSFORMS[name])() for name in self.transforms)


def _resolve(implementation: str | Callable) -> Callable:
    if callable(implementation):
        return implementation
    module, _, name = implementation.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class SmoothQuant(MethodConfig):
    # SmoothQuant's per-channel migration is the method: alpha 0.85 (the paper's deployment setting)
    alpha: float = 0.85

    def calibration_fields(self) -> dict[str, Any] | None:
        return {"alpha": self.alpha}


@dataclass(frozen=True)
class GPTQ(MethodConfig):
    """GPTQ (Frantar et al., 2023; `quant.gptq`): columns quantized in order, each one's error spread
    over the later columns through the inverse Hessian of the layer's calibration inputs."""

    damp: float = 0.01  # fraction of the mean Hessian diagonal added to its diagonal
    act_order: bool = False  # quantize columns in descending Hessian diagonal (groups then fixed up front)
    block_size: int = 128  # columns per lazy batch update (a grouped grid uses its group size)


@dataclass(frozen=True)
class StepStatic(MethodConfig):
    """RTN weights with static activation scales (`quant.step_static`): per flow step for the layers
    that ran inside flow steps during calibration, per layer otherwise. Its presets are integer
    weights with integer activations (static scales quantize activations; W<b> alone would be RTN)."""

    def check_preset(self, name: str, preset: Preset) -> None:
        super().check_preset(name, preset)
        if preset.act_bits is None:
            raise UserError(f"method {name!r} quantizes activations with static scales: it implements "
                            f"W<b>[G<g>]A<a>; preset {preset.name!r} does not match")


# Pre-quantization transforms a method entry may name ("module:class", built without arguments).
TRANSFORMS = {"hadamard": "vlaquantbench.quant.transforms:Hadamard"}
_KERNELS = "vlaquantbench.quant.kernels"  # a module per family
_GPTQ = "vlaquantbench.quant.gptq:gptq"
METHODS: dict[str, MethodConfig] = {
    "rtn": MethodConfig("rtn", "vlaquantbench.quant.apply:rtn", composes=True),
    "nf4": MethodConfig("nf4", f"{_KERNELS}.bnb:nf4", presets=(4, None)),
    "int8": MethodConfig("int8", f"{_KERNELS}.bnb:llm_int8", presets=(8, None),
                         uncapturable="bitsandbytes LLM.int8() synchronizes with the host on its outlier columns"),
    "int4wo": MethodConfig("int4wo", f"{_KERNELS}.int4:int4_weight_only", presets=(4, None)),
    "awq": MethodConfig("awq", f"{_KERNELS}.int4:awq", frozenset({ROWS}), presets=WEIGHT_ONLY),
    "smoothquant": SmoothQuant("smoothquant", f"{_KERNELS}.int8:smoothquant", frozenset({ABSMAX}), presets=(8, 8)),
    "int8_dynamic": MethodConfig("int8_dynamic", f"{_KERNELS}.int8:int8_dynamic", presets=(8, 8)),
    "fp8": MethodConfig("fp8", f"{_KERNELS}.fp8:fp8", presets=(8, 8)),
    "fp8_tensor": MethodConfig("fp8_tensor", f"{_KERNELS}.fp8:fp8_tensorwise", presets=(8, 8)),
    "fp8_static": MethodConfig("fp8_static", f"{_KERNELS}.fp8:fp8_static", frozenset({ABSMAX}), presets=(8, 8)),
    "gptq": GPTQ("gptq", _GPTQ, frozenset({HESSIAN, ROWS}), INTEGER_WEIGHTS, composes=True),
    "gptq_act": GPTQ("gptq_act", _GPTQ, frozenset({HESSIAN, ROWS}), INTEGER_WEIGHTS, composes=True, act_order=True),
    # Rotated inputs (QuaRot-style Hadamard, `quant.transforms.Hadamard`), then RTN or GPTQ
    "hadamard": MethodConfig("hadamard", "vlaquantbench.quant.apply:rtn", composes=True, transforms=("hadamard",)),
    "hadamard_gptq": GPTQ("hadamard_gptq", _GPTQ, frozenset({HESSIAN, ROWS}), INTEGER_WEIGHTS, composes=True,
                          transforms=("hadamard",)),
    "step_static": StepStatic("step_static", "vlaquantbench.quant.step_static:step_static",
                              frozenset({ABSMAX, STEP_SCALES}), INTEGER_WEIGHTS,
                              uncapturable="its scales follow the flow-step clock, which the eager denoise "
                                           "step advances; a captured graph replays one step's scale"),
}


def register_method(name: str, fn: Callable, statistics: Iterable[str] = (),
                    presets: tuple[int, int | None] | str | None = None, uncapturable: str | None = None,
                    composes: bool = False) -> None:
    """Make `QuantConfig.from_preset(method=name)` dispatch to `fn(model, selection, config) -> MethodResult`."""
    METHODS[name] = MethodConfig(name, fn, frozenset(statistics), presets, uncapturable, composes)


def registered_methods() -> list[str]:
    return sorted(METHODS)


def get_method(name: str) -> MethodConfig:
    return lookup(METHODS, name, "quantization method")
