"""Which linear layers a quantization touches: component scope, then include/exclude patterns.

Only `nn.Linear` weights are candidates, so embeddings, the non-linear parts of norms and the
attention matrix products are never selected; each model's `Component.never` removes its
vocabulary heads. Patterns (`quant.patterns`) are shell globs on qualified module names relative to
the model passed in (e.g. `paligemma_with_expert.gemma_expert.model.layers.0.mlp.up_proj`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol

from torch import nn

from vlaquantbench.quant.patterns import COMPONENT_NAMES, select_names

__all__ = ["COMPONENT_NAMES", "LayerOwner", "Selection", "declared_streams", "eligible_linears", "select_layers"]


class LayerOwner(Protocol):
    """What quantization needs of a component scope: which qualified layer names it owns (each
    model declares its own, `vlaquantbench.models.registry.Component`)."""

    def owns(self, qualified_name: str) -> bool: ...


def declared_streams(model: nn.Module, components: Mapping[str, LayerOwner]) -> tuple:
    """The residual streams (`quant.rotation.ResidualStream`) that `model`'s components declare
    foldable (`residual_streams(model)` of a component that has one), in component order."""
    return tuple(stream for comp in components.values()
                 for stream in (comp.residual_streams(model) if getattr(comp, "residual_streams", None) else ()))


@dataclass(frozen=True)
class Selection:
    """The layers one quantization acts on, grouped by component (every component in scope is a key),
    and what the pre-quantization transforms (`quant.transforms`) left each layer's input to do before
    it is quantized (steps in order, e.g. divide by the smoothing vector and clip), by layer name,
    and the residual streams the model's components declare foldable (`declared_streams`), which a
    rotation may rotate offline (`quant.transforms.Hadamard`)."""

    layers: dict[str, dict[str, nn.Linear]]
    inputs: dict[str, tuple[Callable, ...]] = field(default_factory=dict)
    streams: tuple = ()

    def flat(self) -> dict[str, nn.Linear]:
        return {name: layer for group in self.layers.values() for name, layer in group.items()}

    def component_of(self, name: str) -> str:
        return next(c for c, group in self.layers.items() if name in group)

    def counts(self) -> dict[str, dict[str, int]]:
        return {
            comp: {"layers": len(group), "params": sum(m.weight.numel() for m in group.values())}
            for comp, group in self.layers.items()
        }


def eligible_linears(model: nn.Module, components: Mapping[str, LayerOwner]) -> dict[str, dict[str, nn.Linear]]:
    """Every quantizable linear layer of `model`, grouped by the component that owns it."""
    grouped: dict[str, dict[str, nn.Linear]] = {c: {} for c in components}
    for name, module in model.named_modules():
        if not isinstance(module, nn.Linear):
            continue
        owners = [c for c, comp in components.items() if comp.owns(name)]
        if len(owners) > 1:
            raise AssertionError(f"component roots overlap at {name}: {owners}")
        if owners:
            grouped[owners[0]][name] = module
    return grouped


def select_layers(
    model: nn.Module,
    components: Mapping[str, LayerOwner],
    scope: str,
    only: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
) -> Selection:
    """Layers in `scope` matching any `only` pattern (all when None) and no `exclude` pattern.

    Raises UserError when the scope holds no linear layer, when any single pattern matches no
    layer of the scope, or when the patterns together leave nothing selected.
    """
    eligible = eligible_linears(model, components)
    names = select_names({c: list(group) for c, group in eligible.items()}, scope, only, exclude)
    return Selection({c: {n: eligible[c][n] for n in group} for c, group in names.items()},
                     streams=declared_streams(model, components))
