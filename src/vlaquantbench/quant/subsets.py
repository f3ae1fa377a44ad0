"""Named layer subsets (`config/scopes.yaml`): the `<subset>` part of a cell name such as
`ablate-W4A4-ah-onlyself_attn`, resolved to a scope plus include/exclude patterns."""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

from vlaquantbench.config import load_yaml
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
    path = Path(str(resources.files("vlaquantbench").joinpath("config/scopes.yaml")))
    return {
        model: {
            name: Subset(
                name=name,
                model=model,
                scope=entry["scope"],
                only=tuple(entry["only"]) if entry.get("only") else None,
                exclude=tuple(entry["exclude"]) if entry.get("exclude") else None,
                layers=entry["layers"],
                params=entry.get("params"),
            )
            for name, entry in entries.items()
        }
        for model, entries in load_yaml(path, "scopes").items()
    }


def subsets_for(model: str) -> dict[str, Subset]:
    return dict(_load().get(model, {}))


def get_subset(model: str, name: str) -> Subset:
    known = subsets_for(model)
    if name not in known:
        raise UserError(f"unknown subset {name!r} for model {model!r}; known: {', '.join(sorted(known)) or 'none'}")
    return known[name]
