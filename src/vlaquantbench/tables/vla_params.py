"""Paper `tab:vla_params`: each model's end-to-end scope, counted per component on its committed layer index
(`models/<model>/linears.json`: every eligible linear layer of the real architecture built on the meta
device, with its weight parameters; no checkpoint; tests/test_scopes_counts.py rebuilds the architectures
and compares). Reading the index instead of building four models keeps torch out of this workflow job. The
caption is data: the table's definition (`config/layer_index_tables/vla_params.yaml`, schema
`layer_index_table`)."""

from __future__ import annotations

from pathlib import Path

from vlaquantbench.config import load_yaml
from vlaquantbench.models.layer_index import selected_counts
from vlaquantbench.models.registry import MODELS, model_label
from vlaquantbench.tables.booktabs import Booktabs

COMPONENTS = ("ve", "mp", "llm", "ah")


def vla_params_table(definition: str | Path, notes: list[str] | None = None) -> Booktabs:
    """The table with the caption its definition file `definition` gives."""
    caption = load_yaml(definition, "layer_index_table")["caption"]
    rows = []
    # The models the paper names (a `LABEL` in their folder), in the registry's order.
    for model, label in ((model, model_label(model)) for model in MODELS):
        if label is None:
            continue
        counts = selected_counts(model, "e2e")
        cells = [counts.get(c, {"layers": 0, "params": 0}) for c in COMPONENTS]  # absent: an empty separate scope
        rows.append([label, *(f"{c['layers']} / {c['params'] / 1e6:.1f}" for c in cells)])
    return Booktabs(align="lrrrr", header=[["Model", "VE", "MP", "LLM", "AH"]], rows=rows, caption=caption,
                    label="tab:vla_params", size="small", notes=notes or [])


def write_vla_params(definition: str | Path, output: str | Path, html_output: str | Path | None = None) -> Path:
    return vla_params_table(definition, ["Counted on the models' layer index, built from the architectures on the meta "
                                         "device; no checkpoint."]).write(output, html_output)
