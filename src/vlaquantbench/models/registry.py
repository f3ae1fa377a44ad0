"""Model specs: which modules form each component scope, and how to build the real architecture.

A `ModelSpec` is the only place that knows a policy's module layout. Quantization code
(`vlaquantbench.quant`) asks it for component roots and exclusions and never names a model's
modules itself. Specs live in `vlaquantbench.models.<model>.components` as a module-level `SPEC`
and are imported on first use, so looking up one model does not import the others' libraries.
"""

from __future__ import annotations

import fnmatch
import importlib
from collections.abc import Callable
from dataclasses import dataclass, field

import torch
from torch import nn

from vlaquantbench.errors import UserError
from vlaquantbench.quant.scope import COMPONENT_NAMES

__all__ = ["COMPONENT_NAMES", "Component", "ModelSpec", "get_model_spec", "model_names", "seeded_build"]

_SPEC_MODULES = {
    "pi05": "vlaquantbench.models.pi05.components",
    "pi0": "vlaquantbench.models.pi0.components",
    "openvla_oft": "vlaquantbench.models.openvla_oft.components",
    "xvla": "vlaquantbench.models.xvla.components",
}


@dataclass(frozen=True)
class Component:
    """One component scope: the module roots it owns and the layers it never quantizes.

    `roots` are qualified module names (relative to the built model); a layer belongs to the
    component when its name equals a root or lies below one. `never` holds glob patterns for
    linear layers that stay at released precision whatever the user selects (vocabulary heads).
    """

    roots: tuple[str, ...]
    never: tuple[str, ...] = ()

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
        if variant not in self.builders:
            raise UserError(f"model {self.name!r} has no variant {variant!r}; choose one of {sorted(self.builders)}")
        return self.builders[variant](torch.device(device), seed)


def model_names() -> list[str]:
    return sorted(_SPEC_MODULES)


def get_model_spec(name: str) -> ModelSpec:
    if name not in _SPEC_MODULES:
        raise UserError(f"unknown model {name!r}; known models: {', '.join(model_names())}")
    return importlib.import_module(_SPEC_MODULES[name]).SPEC


def seeded_build(construct: Callable[[], nn.Module], device: torch.device, seed: int) -> nn.Module:
    """Construct a module on `device` with its random initialisation drawn from `seed` only.

    The global RNG state is restored afterwards so building a demo model never shifts the
    caller's random streams.
    """
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        with device:
            return construct()
