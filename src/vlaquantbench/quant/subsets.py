"""Named layer subsets (`config/scopes.yaml`): the `<subset>` part of a cell name such as
`ablate-W4A4-ah-onlyself_attn`, resolved to a scope plus include/exclude patterns."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources

import yaml

from vlaquantbench.errors import UserError


@dataclass(frozen=True)
class Subset:
    name: str
    model: str
    scope: str
    only: tuple[str, ...] | None
    exclude: tuple[str, ...] | None
    layers: int  # the paper's layer count for this subset: selection must reproduce it
    params: int | None = None


@functools.cache
def _load() -> dict[str, dict[str, Subset]]:
    text = resources.files("vlaquantbench").joinpath("config/scopes.yaml").read_text()
    table: dict[str, dict[str, Subset]] = {}
    for model, entries in yaml.safe_load(text).items():
        table[model] = {}
        for name, entry in entries.items():
            unknown = set(entry) - {"scope", "only", "exclude", "layers", "params"}
            if unknown or "scope" not in entry or "layers" not in entry:
                raise ValueError(f"config/scopes.yaml {model}.{name}: needs scope and layers, got {sorted(entry)}")
            table[model][name] = Subset(
                name=name,
                model=model,
                scope=entry["scope"],
                only=tuple(entry["only"]) if entry.get("only") else None,
                exclude=tuple(entry["exclude"]) if entry.get("exclude") else None,
                layers=int(entry["layers"]),
                params=entry.get("params"),
            )
    return table


def subsets_for(model: str) -> dict[str, Subset]:
    return dict(_load().get(model, {}))


def get_subset(model: str, name: str) -> Subset:
    known = subsets_for(model)
    if name not in known:
        raise UserError(f"unknown subset {name!r} for model {model!r}; known: {', '.join(sorted(known)) or 'none'}")
    return known[name]
