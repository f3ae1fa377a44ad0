"""Which layer names a scope and include/exclude patterns select, on names alone (no torch).

`quant.scope.select_layers` applies it to a built model's linear layers; the workflow applies it to
the committed layer-name index (`models.layer_index`) to refuse a pattern that matches nothing while
it builds the DAG. Patterns are shell globs (`fnmatch`, case-sensitive) on qualified module names.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Iterable, Mapping, Sequence

from vlaquantbench.errors import UserError

# The scope grammar's components, in canonical order: vision encoder, multimodal projector,
# language model, action head.
COMPONENT_NAMES = ("ve", "mp", "llm", "ah")


def scope_components(scope: str, components: Iterable[str]) -> list[str]:
    """Components named by a scope: one of `ve|mp|llm|ah`, `e2e` (all), or an underscore join
    such as `ve_mp_llm`. Components the model lacks (X-VLA has no MP) are dropped from `e2e`."""
    if scope == "e2e":
        present = set(components)
        return [c for c in COMPONENT_NAMES if c in present]
    names = scope.split("_")
    unknown = [n for n in names if n not in COMPONENT_NAMES]
    if unknown or not names:
        raise UserError(f"unknown scope {scope!r}; use one of {', '.join(COMPONENT_NAMES)}, e2e, or a join like ve_mp_llm")
    return [c for c in COMPONENT_NAMES if c in names]


def select_names(
    names: Mapping[str, Sequence[str]],
    scope: str,
    only: Sequence[str] | None = None,
    exclude: Sequence[str] | None = None,
) -> dict[str, list[str]]:
    """Names in `scope` (from `names`, by component) matching any `only` pattern (all when None) and
    no `exclude` pattern, by component.

    Raises UserError when the scope holds no name, when any single pattern matches no name of the
    scope, or when the patterns together leave nothing selected.
    """
    in_scope = {c: list(names.get(c, ())) for c in scope_components(scope, names)}
    flat = [n for group in in_scope.values() for n in group]
    if not flat:
        raise UserError(f"scope {scope!r} selects no linear layer in this model")
    for kind, patterns in (("--only", only), ("--exclude", exclude)):
        for pattern in patterns or ():
            if not any(fnmatch.fnmatchcase(n, pattern) for n in flat):
                raise UserError(f"pattern {kind} {pattern!r} matches no linear layer in scope {scope!r}")

    def keep(name: str) -> bool:
        included = only is None or any(fnmatch.fnmatchcase(name, p) for p in only)
        return included and not any(fnmatch.fnmatchcase(name, p) for p in exclude or ())

    selected = {c: [n for n in group if keep(n)] for c, group in in_scope.items()}
    if not any(selected.values()):
        raise UserError(f"patterns only={list(only or [])} exclude={list(exclude or [])} leave scope {scope!r} empty")
    return selected
