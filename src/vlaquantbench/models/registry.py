"""The model registry: every policy the project knows, by the name cell references use.

A model is a folder `vlaquantbench/models/<name>/` (`MODELS` maps the name to it) holding
`components.py` with a module-level `SPEC` (a `ModelSpec`: component scopes and builders of the real
architecture), `linears.json` (its linear-layer names per component, `models.layer_index`) and, when
the runner can drive it in closed loop, `adapter.py` with a module-level `ADAPTER` class. Folders are
imported on first use, so looking up one model imports no other model's library, and this module
imports no torch: the workflow checks model names while it builds the DAG.

A `ModelSpec` is the only place that knows a policy's module layout. Quantization code
(`vlaquantbench.quant`) asks it for component roots and exclusions and never names a model's
modules itself.
"""

from __future__ import annotations

import fnmatch
import importlib
import importlib.util
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from vlaquantbench.errors import UserError, lookup
from vlaquantbench.quant.patterns import COMPONENT_NAMES

__all__ = ["COMPONENT_NAMES", "Component", "ModelSpec", "adapter_class", "demo_build", "get_model_spec", "model_label",
           "model_names", "randomize_linears", "rollout_models", "seeded_build"]

if TYPE_CHECKING:
    import torch
    from torch import nn

MODELS = {
    "pi05": "vlaquantbench.models.pi05",
    "pi0": "vlaquantbench.models.pi0",
    "openvla_oft": "vlaquantbench.models.openvla_oft",
    "xvla": "vlaquantbench.models.xvla",
    "metaworld_expert": "vlaquantbench.models.metaworld_expert",
}


@dataclass(frozen=True)
class Component:
    """One component scope: the module roots it owns and the layers it never quantizes.

    `roots` are qualified module names (relative to the built model); a layer belongs to the
    component when its name equals a root or lies below one. `never` holds glob patterns for
    linear layers that stay at released precision whatever the user selects (vocabulary heads).
    `residual_streams(model)`, where given, declares the component's residual streams whose norms
    fold (`quant.rotation.ResidualStream`: writers, RMSNorms and their readers), which a Hadamard
    rotation rotates offline; a component without one is rotated online only.
    """

    roots: tuple[str, ...]
    never: tuple[str, ...] = ()
    residual_streams: Callable[[nn.Module], tuple] | None = field(default=None, repr=False, compare=False)

    def owns(self, qualified_name: str) -> bool:
        inside = any(qualified_name == r or qualified_name.startswith(r + ".") for r in self.roots)
        return inside and not any(fnmatch.fnmatchcase(qualified_name, p) for p in self.never)


@dataclass(frozen=True)
class ModelSpec:
    """A policy family: component scopes plus builders of its real architecture.

    `builders["full"](device, seed)` builds the released configuration (use device="meta" to count
    layers without memory); `builders["demo"](device, seed)` builds a reduced-width instance of the
    same classes, with the same module names and depths, and seeded random weights.
    """

    name: str
    components: dict[str, Component]
    builders: dict[str, Callable[[torch.device, int], nn.Module]] = field(repr=False)

    def build(self, variant: str = "full", device: str | torch.device = "meta", seed: int = 0) -> nn.Module:
        import torch

        return lookup(self.builders, variant, f"{self.name} variant")(torch.device(device), seed)


def model_names() -> list[str]:
    return sorted(MODELS)


def model_package(name: str) -> str:
    """The package of model `name`; UserError listing the known models otherwise."""
    return lookup(MODELS, name, "model")


def model_label(name: str) -> str | None:
    """How the paper's tables name model `name` (`LABEL` of its package; None for a model they do not show)."""
    return getattr(importlib.import_module(model_package(name)), "LABEL", None)


def get_model_spec(name: str) -> ModelSpec:
    return importlib.import_module(f"{model_package(name)}.components").SPEC


def rollout_models() -> list[str]:
    """Models the runner can drive in closed loop: those whose folder has an `adapter.py`."""
    return [name for name in model_names() if importlib.util.find_spec(f"{MODELS[name]}.adapter") is not None]


def adapter_class(name: str) -> type:
    """The rollout adapter class of model `name` (its folder's `adapter.py` defines `ADAPTER`)."""
    model_package(name)
    if name not in rollout_models():
        raise UserError(f"no rollout adapter for model {name!r}; adapters exist for {', '.join(rollout_models())}")
    return importlib.import_module(f"{MODELS[name]}.adapter").ADAPTER


def seeded_build(construct: Callable[[], nn.Module], device: torch.device, seed: int) -> nn.Module:
    """Construct a module on `device` with its random initialisation drawn from `seed` only.

    The global RNG state is restored afterwards so building a demo model never shifts the
    caller's random streams.
    """
    import torch

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        with device:
            return construct()


def demo_build(construct: Callable[[], nn.Module], device: torch.device, seed: int) -> nn.Module:
    """A model's `demo` variant: `construct()` seeded by `seed` (`seeded_build`), every linear layer
    given seeded random weights (`randomize_linears`), in eval mode."""
    model = seeded_build(construct, device, seed)
    randomize_linears(model, seed)
    return model.eval()


def randomize_linears(model: "nn.Module", seed: int) -> None:
    """Give every linear layer seeded random weights, including those a library zero-initialises
    (pi0.5's adaRMS `dense` modulations), so every selectable layer affects a demo model's output."""
    import torch
    from torch import nn

    generator = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, nn.Linear):
                std = module.in_features**-0.5
                module.weight.copy_(torch.randn(module.weight.shape, generator=generator) * std)
                if module.bias is not None:
                    module.bias.copy_(torch.randn(module.bias.shape, generator=generator) * 0.02)
