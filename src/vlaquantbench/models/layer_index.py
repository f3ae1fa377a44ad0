"""Each model's quantizable linear layers per component (name -> weight parameters), committed as
`models/<name>/linears.json`.

The workflow checks every subset pattern of every cell while it builds the DAG, and must not import
torch to do so; the names come from this index instead of a built model. The index is generated from
the real architecture built on the meta device (`vqb scopes --write-index`), and a test rebuilds every
model and compares, so the index cannot drift from the builders. All variants (full, demo, random)
share their module names, so one index serves them all; the parameter counts are the full
architecture's (the paper's tables count them, e.g. the Params columns of tab:culprit).
"""

from __future__ import annotations

import functools
import json
from importlib import resources
from pathlib import Path

from vlaquantbench.models.registry import MODELS, get_model_spec, model_package
from vlaquantbench.quant.patterns import select_names

INDEX = "linears.json"


def index_path(model: str) -> Path:
    package = model_package(model)
    return Path(str(resources.files(package).joinpath(INDEX)))


@functools.cache
def linear_params(model: str) -> dict[str, dict[str, int]]:
    """The committed index of `model`: component -> {qualified name: weight parameters} of its eligible
    linear layers, in module order."""
    path = index_path(model)
    if not path.is_file():
        raise FileNotFoundError(f"{path} is missing: run `vqb scopes --write-index`")
    return json.loads(path.read_text())["components"]


def linear_names(model: str) -> dict[str, list[str]]:
    """Component -> qualified names of `model`'s eligible linear layers (the committed index)."""
    return {component: list(layers) for component, layers in linear_params(model).items()}


def selected_counts(model: str, scope: str, only=None, exclude=None) -> dict[str, dict[str, int]]:
    """Component -> {layers, params} that `scope` and the patterns select in `model`, from the index (no torch):
    what `quant.scope.Selection.counts` gives on the built model."""
    index = linear_params(model)
    selected = select_names({c: list(layers) for c, layers in index.items()}, scope, only, exclude)
    return {c: {"layers": len(names), "params": sum(index[c][name] for name in names)} for c, names in selected.items()}


def build_index(model: str) -> dict:
    """The index of `model` from its real architecture on the meta device (imports torch and lerobot)."""
    from vlaquantbench.quant.scope import eligible_linears

    spec = get_model_spec(model)
    eligible = eligible_linears(spec.build("full", device="meta"), spec.components)
    return {"model": model, "components": {c: {name: layer.weight.numel() for name, layer in group.items()}
                                           for c, group in eligible.items()}}


def write_indexes(models: list[str] | None = None) -> list[Path]:
    written = []
    for model in models or sorted(MODELS):
        path = index_path(model)
        path.write_text(json.dumps(build_index(model), indent=1) + "\n")
        written.append(path)
    linear_params.cache_clear()
    return written
