"""Which linear layers a quantization touches: component scope, then include/exclude patterns.

Only `nn.Linear` weights are candidates, so embeddings, the non-linear parts of norms and the
attention matrix products are never selected; each model's `Component.never` removes its
vocabulary heads. Patterns are shell globs (`fnmatch`, case-sensitive) on qualified module names
relative to the model passed in (e.g. `paligemma_with_expert.gemma_expert.model.layers.0.mlp.up_proj`).
"""

from __future__ import annotations

import fnmatch
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

from torch import nn

from vlaquantbench.errors import UserError

# The scope grammar's components, in canonical order: vision encoder, multimodal projector,
# language model, action head.
COMPONENT_NAMES = ("ve", "mp", "llm", "ah")


class LayerOwner(Protocol):
    """What quantization needs of a component scope: which qualified layer names it owns (each
    model declares its own, `vlaquantbench.models.registry.Component`)."""

    def owns(self, qualified_name: str) -> bool: ...


@dataclass(frozen=True)
class Selection:
    """The layers one quantization acts on, grouped by component (every component in scope is a key)."""

    layers: dict[str, dict[str, nn.Linear]]

    def flat(self) -> dict[str, nn.Linear]:
        return {name: layer for group in self.layers.values() for name, layer in group.items()}

    def component_of(self, name: str) -> str:
        return next(c for c, group in self.layers.items() if name in group)

    def counts(self) -> dict[str, dict[str, int]]:
        return {
            comp: {"layers": len(group), "params": sum(m.weight.numel() for m in group.values())}
            for comp, group in self.layers.items()
        }


def scope_components(scope: str, components: Mapping[str, LayerOwner]) -> list[str]:
    """Components named by a scope: one of `ve|mp|llm|ah`, `e2e` (all), or an underscore join
    such as `ve_mp_llm`. Components the model lacks (X-VLA has no MP) are dropped from `e2e`."""
    if scope == "e2e":
        return [c for c in COMPONENT_NAMES if c in components]
    names = scope.split("_")
    unknown = [n for n in names if n not in COMPONENT_NAMES]
    if unknown or not names:
        raise UserError(f"unknown scope {scope!r}; use one of {', '.join(COMPONENT_NAMES)}, e2e, or a join like ve_mp_llm")
    return [c for c in COMPONENT_NAMES if c in names]


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
    wanted = scope_components(scope, components)
    eligible = eligible_linears(model, components)
    in_scope = {c: eligible.get(c, {}) for c in wanted}
    names = [n for group in in_scope.values() for n in group]
    if not names:
        raise UserError(f"scope {scope!r} selects no linear layer in this model")
    for kind, patterns in (("--only", only), ("--exclude", exclude)):
        for pattern in patterns or ():
            if not any(fnmatch.fnmatchcase(n, pattern) for n in names):
                raise UserError(f"pattern {kind} {pattern!r} matches no linear layer in scope {scope!r}")

    def keep(name: str) -> bool:
        included = only is None or any(fnmatch.fnmatchcase(name, p) for p in only)
        return included and not any(fnmatch.fnmatchcase(name, p) for p in exclude or ())

    selected = {c: {n: m for n, m in group.items() if keep(n)} for c, group in in_scope.items()}
    if not any(selected.values()):
        raise UserError(f"patterns only={list(only or [])} exclude={list(exclude or [])} leave scope {scope!r} empty")
    return Selection(selected)
