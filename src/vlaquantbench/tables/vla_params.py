"""Paper `tab:vla_params`: each model's end-to-end scope, counted per component on its real
architecture built on the meta device (no checkpoint, no weights in memory)."""

from __future__ import annotations

from pathlib import Path

from vlaquantbench.tables.booktabs import Booktabs

MODELS = {"pi05": r"$\pi_{0.5}$", "pi0": r"$\pi_0$", "openvla_oft": "OpenVLA-OFT", "xvla": "X-VLA"}
COMPONENTS = ("ve", "mp", "llm", "ah")
CAPTION = (
    "Selected linear-layer counts / weight parameters in millions for the LIBERO-Spatial W4 end-to-end scopes. "
    "Excluded modules are not counted. These are quantized linear weights, not total model parameters or memory "
    "measurements. Zero denotes an empty separate scope."
)


def e2e_counts(model: str) -> dict[str, dict[str, int]]:
    """Component -> {layers, params} of `model`'s e2e scope (imports torch and the model's builder)."""
    from vlaquantbench.models import get_model_spec
    from vlaquantbench.quant.scope import select_layers

    spec = get_model_spec(model)
    return select_layers(spec.build("full", device="meta"), spec.components, "e2e").counts()


def vla_params_table(notes: list[str] | None = None) -> Booktabs:
    rows = []
    for model, label in MODELS.items():
        counts = e2e_counts(model)
        cells = [counts.get(c, {"layers": 0, "params": 0}) for c in COMPONENTS]  # absent: an empty separate scope
        rows.append([label, *(f"{c['layers']} / {c['params'] / 1e6:.1f}" for c in cells)])
    return Booktabs(align="lrrrr", header=[["Model", "VE", "MP", "LLM", "AH"]], rows=rows, caption=CAPTION,
                    label="tab:vla_params", size="small", notes=notes or [])


def write_vla_params(output: str | Path, html_output: str | Path | None = None) -> Path:
    return vla_params_table(["Counted on the model builders on the meta device; no checkpoint."]).write(
        output, html_output)
