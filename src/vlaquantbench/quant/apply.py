"""`quantize_(model, config, selection)`: apply one quantization to a policy, torchao style.

    cfg = QuantConfig.from_preset("W4A4", scope="ah", only=["*self_attn*"])
    report = quantize_(model, cfg, cfg.select(model, adapter.components))  # or get_model_spec("pi05").components
    ...  # run episodes
    report.check_hooks_fired()          # raises HooksNotFired naming layers whose hooks never ran
    header.update(report.to_header())

Layer selection (`quant.scope`) happens, and fails on bad scopes or patterns, before any weight
changes; `quantize_` receives the selected layers and knows no model (each model declares its
component scopes in its own folder). The quantization itself is a *method* looked up in the registry
`quant.methods`: `rtn` (this module) fake-quantizes weights in place and installs counting activation
hooks; real-kernel methods live in `quant.kernels`. Weight changes are in place and not undone.
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field

import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.calibration import FLOOR, CalibrationSettings, CalibrationStats, smoothing_factors
from vlaquantbench.quant.hooks import CountingHook, InputTransform
from vlaquantbench.quant.methods import get_method
from vlaquantbench.quant.presets import Preset, parse_preset
from vlaquantbench.quant.patterns import scope_components
from vlaquantbench.quant.scope import LayerOwner, Selection, select_layers


@dataclass(frozen=True)
class QuantConfig:
    preset: Preset
    scope: str = "e2e"
    only: tuple[str, ...] | None = None
    exclude: tuple[str, ...] | None = None
    method: str = "rtn"
    calibration: CalibrationSettings | None = None
    stats: CalibrationStats | None = None

    @classmethod
    def from_preset(
        cls,
        preset: str,
        scope: str = "e2e",
        only: Sequence[str] | None = None,
        exclude: Sequence[str] | None = None,
        method: str = "rtn",
        calibration: CalibrationSettings | None = None,
        stats: CalibrationStats | None = None,
    ) -> QuantConfig:
        if calibration is not None and stats is None:
            raise UserError("calibration settings given without calibration statistics (stats=...)")
        return cls(
            preset=parse_preset(preset),
            scope=scope,
            only=tuple(only) if only else None,
            exclude=tuple(exclude) if exclude else None,
            method=method,
            calibration=calibration,
            stats=stats,
        )

    def select(self, model: nn.Module, components: Mapping[str, LayerOwner]) -> Selection:
        """The linears of `model` that this config's scope and patterns select, given the model's
        component scopes (its adapter's or spec's `components`): what `quantize_` receives."""
        return select_layers(model, components, self.scope, self.only, self.exclude)


@dataclass
class MethodResult:
    """What a quantization method did: a format description, its counting hooks by layer name,
    the names of layers it calibrated, and method-specific provenance for the header's
    `quant_report` (e.g. AWQ's chosen scale exponents under "awq")."""

    format: str
    hooks: dict[str, CountingHook] = field(default_factory=dict)
    calibrated: set[str] = field(default_factory=set)
    details: dict = field(default_factory=dict)


def hook_summary(installed: Iterable[str], fired: Collection[str]) -> dict:
    """A header's `hooks`: how many activation hooks were installed, how many fired, and the names of
    those that never fired (`unfired`, in installation order)."""
    installed = list(installed)
    unfired = [name for name in installed if name not in fired]
    return {"selected": len(installed), "fired": len(installed) - len(unfired), "unfired": unfired}


class HooksNotFired(RuntimeError):
    """Selected layers whose activation hooks never ran: the run was weight-only for them."""


@dataclass
class QuantReport:
    config: QuantConfig
    selection: Selection
    result: MethodResult

    @property
    def components(self) -> dict[str, dict[str, int]]:
        return self.selection.counts()

    @property
    def selected(self) -> list[str]:
        return list(self.selection.flat())

    def hook_calls(self) -> dict[str, int]:
        return {name: hook.calls for name, hook in self.result.hooks.items()}

    def unfired(self) -> list[str]:
        return [name for name, calls in self.hook_calls().items() if calls == 0]

    def check_hooks_fired(self) -> None:
        missing = self.unfired()
        if missing:
            raise HooksNotFired(
                f"{len(missing)} of {len(self.result.hooks)} activation hooks never fired: {', '.join(missing)}"
            )

    def reset_hook_calls(self) -> None:
        for hook in self.result.hooks.values():
            hook.quantizer.reset_calls()

    def remove_hooks(self) -> None:
        for hook in self.result.hooks.values():
            hook.remove()

    def to_header(self) -> dict:
        quant_report: dict = {}
        for comp, counts in self.components.items():
            quant_report[comp] = dict(counts)
            if self.config.calibration is not None:
                names = self.selection.layers[comp]
                quant_report[comp]["calibrated_layers"] = sum(n in self.result.calibrated for n in names)
        if self.config.calibration is not None:
            quant_report["act_calib"] = self.config.stats.provenance(self.config.calibration)
        quant_report.update(self.result.details)
        fired = {name for name, calls in self.hook_calls().items() if calls}
        return {
            "quant_report": quant_report,
            "quant_format": self.result.format,
            "hooks": hook_summary(self.result.hooks, fired),
            "selected_layers": self.selected,
        }


def quantize_(model: nn.Module, config: QuantConfig, selection: Selection) -> QuantReport:
    """Quantize the layers of `model` in `selection` (e.g. `config.select(model, components)`) as
    `config` says and return the report. The selection's components must be those of `config.scope`,
    which the report records."""
    method = get_method(config.method)
    in_scope = scope_components(config.scope, selection.layers)
    if list(selection.layers) != in_scope:
        raise UserError(f"selection of components {list(selection.layers)} given for scope {config.scope!r} ({in_scope})")
    if config.preset.is_baseline and config.calibration is None:
        empty = Selection({comp: {} for comp in selection.layers})
        return QuantReport(config, empty, MethodResult(format="released precision"))
    return QuantReport(config, selection, method.resolve()(model, selection, config))


def rtn(model: nn.Module, selection: Selection, config: QuantConfig) -> MethodResult:
    """Round-to-nearest fake quantization (paper `app:quant-prelim`), with optional rollout
    smoothing and clipping (`app:calib`) on the layers of the calibrated components."""
    preset = config.preset
    result = MethodResult(format=_rtn_format(preset, config.calibration))
    for name, layer in selection.flat().items():
        transform = InputTransform(act_bits=preset.act_bits, act_format=preset.act_format)
        layer_stats = _stats_for(name, selection, config)
        with torch.no_grad():
            if layer_stats is not None:
                smooth = smoothing_factors(layer_stats.absmax, layer.weight, config.calibration.alpha)
                clip = None
                if config.calibration.quantile is not None:
                    clip = (layer_stats.quantile.float().to(smooth.device) / smooth).clamp_min(FLOOR)
                layer.weight.copy_((layer.weight.float() * smooth).to(layer.weight.dtype))
                transform = InputTransform(smooth=smooth, clip=clip, act_bits=preset.act_bits, act_format=preset.act_format)
                result.calibrated.add(name)
            if preset.weight is not None:
                layer.weight.copy_(preset.weight.quantize_weight(layer.weight))
        if not transform.is_identity:
            result.hooks[name] = CountingHook(layer, transform)
    return result


def _stats_for(name: str, selection: Selection, config: QuantConfig):
    if config.calibration is None or selection.component_of(name) not in config.calibration.components:
        return None
    return config.stats.layers.get(name)  # layers never observed during calibration stay uncalibrated


def _rtn_format(preset: Preset, calibration: CalibrationSettings | None) -> str:
    calib = f"; rollout smoothing alpha={calibration.alpha}, clip q={calibration.quantile}" if calibration else ""
    return f"RTN {preset.describe()}{calib}"

