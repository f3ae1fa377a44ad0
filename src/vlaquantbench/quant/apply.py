"""`quantize_(model, config, selection)`: apply one quantization to a policy, torchao style.

    cfg = QuantConfig.from_preset("W4A4", scope="ah", only=["*self_attn*"], method="gptq", stats=stats)
    report = quantize_(model, cfg, cfg.select(model, adapter.components))  # or get_model_spec("pi05").components
    ...  # run episodes
    report.check_hooks_fired()          # raises HooksNotFired naming layers whose hooks never ran
    header.update(report.to_header())

Three independent parts make a quantization:
- the selection (`quant.scope`), a predicate on layer names: it happens, and fails on bad scopes or
  patterns, before any weight changes; `quantize_` receives the selected layers and knows no model
  (each model declares its component scopes in its own folder);
- the pre-quantization transforms (`quant.transforms`, `QuantConfig.transforms`), applied in order;
- the method, a typed `MethodConfig` of the registry `quant.methods`: `rtn` (this module)
  fake-quantizes weights in place and installs counting activation hooks, `gptq` (`quant.gptq`)
  does the same after GPTQ's error-compensating rounding, real-kernel methods live in `quant.kernels`.
Weight changes are in place and not undone.

Where the calibration statistics hold sampled input rows of a layer (methods that collect `rows`),
the report's `mean_rel_mse` of its component is the mean over its layers of
||layer_q(X) - layer(X)||^2 / ||layer(X)||^2 on those rows: the quantized layer with its input
transform against the released one (None where no layer of the component has rows).
"""

from __future__ import annotations

from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace

import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.calibration import CalibrationSettings, CalibrationStats, ChannelStats
from vlaquantbench.quant.hooks import CountingHook
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.quant.methods import MethodConfig, get_method
from vlaquantbench.quant.presets import Preset, parse_preset
from vlaquantbench.quant.patterns import scope_components
from vlaquantbench.quant.rotation import is_offline
from vlaquantbench.quant.scope import LayerOwner, Selection, select_layers
from vlaquantbench.quant.transforms import Smoothing, Transform, input_steps


@dataclass(frozen=True)
class QuantConfig:
    preset: Preset
    scope: str = "e2e"
    only: tuple[str, ...] | None = None
    exclude: tuple[str, ...] | None = None
    method: MethodConfig = field(default_factory=lambda: get_method("rtn"))
    calibration: CalibrationSettings | None = None
    stats: CalibrationStats | None = None
    transforms: tuple[Transform, ...] = ()  # pre-quantization transforms (`quant.transforms`), applied in order

    @classmethod
    def from_preset(
        cls,
        preset: str,
        scope: str = "e2e",
        only: Sequence[str] | None = None,
        exclude: Sequence[str] | None = None,
        method: str | MethodConfig = "rtn",
        calibration: CalibrationSettings | None = None,
        stats: CalibrationStats | None = None,
        transforms: Sequence[Transform] | None = None,
    ) -> QuantConfig:
        """`method`: a registered name or a method config; `transforms` None: rollout smoothing
        (`Smoothing(calibration)`) where the calibration settings smooth and the method composes,
        then the transforms the method's entry names (`MethodConfig.transforms`)."""
        if calibration is not None and stats is None:
            raise UserError("calibration settings given without calibration statistics (stats=...)")
        method = get_method(method) if isinstance(method, str) else method
        if transforms is None:
            smooths = calibration is not None and calibration.alpha is not None and method.composes
            transforms = ((Smoothing(calibration),) if smooths else ()) + method.named_transforms()
        return cls(
            preset=parse_preset(preset),
            scope=scope,
            only=tuple(only) if only else None,
            exclude=tuple(exclude) if exclude else None,
            method=method,
            calibration=calibration,
            stats=stats,
            transforms=tuple(transforms),
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
    mean_rel_mse: dict[str, float | None] = field(default_factory=dict)  # by component

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
            quant_report[comp] = {**counts, "mean_rel_mse": self.mean_rel_mse.get(comp)}
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
    `config` says and return the report: the transforms in order, then the method. The selection's
    components must be those of `config.scope`, which the report records."""
    method = config.method
    in_scope = scope_components(config.scope, selection.layers)
    if list(selection.layers) != in_scope:
        raise UserError(f"selection of components {list(selection.layers)} given for scope {config.scope!r} ({in_scope})")
    if config.preset.is_baseline and config.calibration is None and not config.transforms:
        empty = Selection({comp: {} for comp in selection.layers})
        return QuantReport(config, empty, MethodResult(format="released precision"))
    if config.transforms and not method.composes:
        raise UserError(f"method {method.name!r} does not run after pre-quantization transforms "
                        f"({', '.join(type(t).__name__ for t in config.transforms)})")
    for index, transform in enumerate(config.transforms):  # refusals first: no weight has changed yet
        transform.check_after(config.transforms[:index], selection, config.stats)
    errors = _OutputErrors(selection, config.stats)
    inputs: dict[str, tuple] = {}
    for transform in config.transforms:
        for name, steps in transform.apply(replace(selection, inputs=inputs), config.stats).items():
            inputs[name] = (*inputs.get(name, ()), *steps)
    result = method.resolve()(model, replace(selection, inputs=inputs), config)
    result.format += "".join(f"; {t.description}" for t in config.transforms if t.description)
    result.calibrated |= {name for name, steps in inputs.items() if any(isinstance(s, InputTransform) for s in steps)}
    return QuantReport(config, selection, result, errors.measure(model, result, inputs))


def layer_statistics(selection: Selection, config: QuantConfig, method: str, what: str, how: str,
                     usable=lambda stats: True) -> dict[str, ChannelStats]:
    """The calibration statistics of every selected layer; UserError before any weight changes."""
    layers = config.stats.layers if config.stats is not None else {}
    found = {n: layers[n] for n in selection.flat() if n in layers and usable(layers[n])}
    missing = [n for n in selection.flat() if n not in found]
    if missing:
        raise UserError(f"method {method!r} needs {what} for {len(missing)} selected layers, e.g. {missing[0]}: {how}")
    return found


def install_input_hooks(result: MethodResult, selection: Selection, preset: Preset) -> None:
    """Per selected layer, a counting hook running its transforms' input steps and then the preset's
    activation quantization (none where that does nothing)."""
    for name, layer in selection.flat().items():
        transform = input_steps(selection.inputs.get(name, ()), preset)
        if not transform.is_identity:
            result.hooks[name] = CountingHook(layer, transform)


class _OutputErrors:
    """Each selected layer's outputs on its sampled calibration rows, kept before quantization, and
    the mean relative squared error of the quantized layers on the same rows, by component."""

    def __init__(self, selection: Selection, stats: CalibrationStats | None):
        self.selection = selection
        self.rows: dict[str, torch.Tensor] = {}
        self.reference: dict[str, torch.Tensor] = {}
        layers = stats.layers if stats is not None else {}
        with torch.no_grad():
            for name, layer in selection.flat().items():
                observed: ChannelStats | None = layers.get(name)
                if observed is None or observed.samples is None:
                    continue
                rows = observed.samples.to(layer.weight.device, layer.weight.dtype)
                self.rows[name], self.reference[name] = rows, layer(rows).float()

    def measure(self, model: nn.Module, result: MethodResult,
                inputs: Mapping[str, tuple]) -> dict[str, float | None]:
        """`inputs`: the transforms' steps by layer; offline ones (an offline rotation's) map the rows
        observed on the untransformed model into the layer's new input space, and its reference
        outputs into its new output space."""
        errors: dict[str, list[float]] = {comp: [] for comp in self.selection.layers}
        with torch.no_grad():
            for name, rows in self.rows.items():
                offline = [step for step in inputs.get(name, ()) if is_offline(step)]
                reference = self.reference[name]
                for step in offline:
                    rows, reference = step.map_rows(rows), step.map_output(reference)
                quantized = model.get_submodule(name)  # a kernel method may have replaced the layer
                hook = result.hooks.get(name)
                calls = hook.calls if hook is not None else 0
                out = quantized(rows).float()  # through the layer's input hook, as in an episode
                if hook is not None:
                    hook.quantizer.calls = calls  # this is no evidence that an episode quantized the layer
                errors[self.selection.component_of(name)].append(
                    ((out - reference).pow(2).sum() / reference.pow(2).sum().clamp_min(1e-30)).item())
        return {comp: sum(values) / len(values) if values else None for comp, values in errors.items()}


def rtn(model: nn.Module, selection: Selection, config: QuantConfig) -> MethodResult:
    """Round-to-nearest fake quantization (paper `app:quant-prelim`), after the transforms (rollout
    smoothing and clipping, `app:calib`, on the layers of the calibrated components)."""
    preset = config.preset
    result = MethodResult(format=_rtn_format(preset, config.calibration))
    if preset.weight is not None:
        with torch.no_grad():
            for layer in selection.flat().values():
                layer.weight.copy_(preset.weight.quantize_weight(layer.weight))
    install_input_hooks(result, selection, preset)
    return result


def _rtn_format(preset: Preset, calibration: CalibrationSettings | None) -> str:
    smooths = calibration is not None and calibration.alpha is not None  # else its statistics only measure errors
    calib = f"; rollout smoothing alpha={calibration.alpha}, clip q={calibration.quantile}" if smooths else ""
    return f"RTN {preset.describe()}{calib}"
