"""Why the Hadamard rotation raises RTN's error on the policy trained here: the shape of its weights.

    .venv/bin/python benchmarks/rotation_weight_shape.py [--home checkpoints/pi05_metaworld_cpu]
        [--preset W4A8] [--scope e2e] [--out benchmarks/results/trained_cpu/rotation_weight_shape.json]

Loads the checkpoint through the rollout path (as `trained_policy_closed_loop.py` does), copies every
selected layer's weight, applies the `hadamard` method's transforms to the model (`quant.transforms.Hadamard`:
the residual streams rotated offline with their RMSNorm gains folded, every other input rotated online,
R^T folded into the weight), and compares each layer's weight before and after, without quantizing the
model:
- the relative error of the preset's weight grid, ||Q(W) - W||^2 / ||W||^2 (`WeightGrid.quantize_weight`:
  RTN's, one symmetric scale per output row for the W4 presets);
- the kurtosis of each row (1.8 for a uniform distribution, 3 for a Gaussian) and its absmax over its
  root mean square, the ratio a per-row absmax grid spends its levels on.
Two controls over the same shapes rotate their input columns by `BlockHadamard`: Gaussian rows (rotating
a Gaussian leaves it Gaussian: the error stays) and Gaussian rows with one input channel 20 times larger
(the outlier QuaRot targets: rotation spreads it and lowers the error). Prints per-component medians;
writes `--out` (JSON, per layer and per component).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import torch

from vlaquantbench.hub.cache import offline_cache, repo_folder
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig
from vlaquantbench.quant.presets import WeightGrid
from vlaquantbench.quant.hadamard import BlockHadamard

RESULTS = Path(__file__).resolve().parent / "results" / "trained_cpu" / "rotation_weight_shape.json"
OUTLIER_GAIN = 20.0


def grid_error(weight: torch.Tensor, grid: WeightGrid) -> float:
    return ((grid.quantize_weight(weight) - weight).pow(2).sum() / weight.pow(2).sum()).item()


def row_kurtosis(weight: torch.Tensor) -> float:
    centred = weight - weight.mean(dim=1, keepdim=True)
    return (centred.pow(4).mean(dim=1) / centred.pow(2).mean(dim=1).pow(2)).mean().item()


def absmax_over_rms(weight: torch.Tensor) -> float:
    return (weight.abs().amax(dim=1) / weight.pow(2).mean(dim=1).sqrt()).mean().item()


def shape_of(weight: torch.Tensor, grid: WeightGrid) -> dict:
    return {"error": grid_error(weight, grid), "kurtosis": row_kurtosis(weight), "absmax_over_rms": absmax_over_rms(weight)}


def controls(shape: torch.Size, grid: WeightGrid, generator: torch.Generator) -> dict:
    """Gaussian rows of `shape`, plain and with one outlier input channel, before and after rotating their inputs."""
    rotation = BlockHadamard(shape[1])
    gaussian = torch.randn(shape, generator=generator)
    outlier = gaussian.clone()
    outlier[:, 0] *= OUTLIER_GAIN
    return {name: {"plain": grid_error(w, grid), "rotated": grid_error(rotation.rotate(w, torch.float32), grid)}
            for name, w in (("gaussian", gaussian), ("outlier_channel", outlier))}


def measure(home: Path, preset: str, scope: str) -> dict:
    training = json.loads((home / "training.json").read_text())
    snapshot = repo_folder(home / "hub", training["checkpoint"]) / "snapshots" / training["revision"]
    adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint=training["checkpoint"],
                                         revision=training["revision"], checkpoint_dir=str(snapshot), device="cpu",
                                         dtype="float32", executed_chunk=training["policy"]["n_action_steps"]))
    with offline_cache(home):
        adapter.load()
    quant = QuantConfig.from_preset(preset, scope=scope, method="hadamard")
    grid = quant.preset.weight
    selection = quant.select(adapter.model, adapter.components)
    layers = selection.flat()
    plain = {name: layer.weight.detach().float().clone() for name, layer in layers.items()}
    with torch.no_grad():
        for transform in quant.transforms:
            transform.apply(selection, None)
    generator = torch.Generator().manual_seed(0)
    per_layer = {}
    for name, layer in layers.items():
        per_layer[name] = {"component": selection.component_of(name), "shape": list(plain[name].shape),
                           "plain": shape_of(plain[name], grid),
                           "transformed": shape_of(layer.weight.detach().float(), grid),
                           "controls": controls(plain[name].shape, grid, generator)}
    components = {}
    for component in sorted({row["component"] for row in per_layer.values()}):
        rows = [row for row in per_layer.values() if row["component"] == component]

        def median(path):
            return statistics.median(_get(row, path) for row in rows)

        components[component] = {
            "layers": len(rows),
            "error_raised_in": sum(row["transformed"]["error"] > row["plain"]["error"] for row in rows),
            **{f"median_{'_'.join(path)}": median(path) for path in (
                ("plain", "error"), ("transformed", "error"), ("plain", "kurtosis"), ("transformed", "kurtosis"),
                ("plain", "absmax_over_rms"), ("transformed", "absmax_over_rms"),
                ("controls", "gaussian", "plain"), ("controls", "gaussian", "rotated"),
                ("controls", "outlier_channel", "plain"), ("controls", "outlier_channel", "rotated"))},
        }
    return {"checkpoint": training["checkpoint"], "revision": training["revision"], "preset": preset, "scope": scope,
            "weight_grid": grid.describe(), "transforms": [type(t).__name__ for t in quant.transforms],
            "outlier_gain": OUTLIER_GAIN, "components": components, "per_layer": per_layer}


def _get(row: dict, path: tuple[str, ...]) -> float:
    for key in path:
        row = row[key]
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--home", type=Path, default=Path("checkpoints/pi05_metaworld_cpu"))
    parser.add_argument("--preset", default="W4A8")
    parser.add_argument("--scope", default="e2e")
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    started = time.perf_counter()
    result = measure(args.home, args.preset, args.scope)
    result["wall_s"] = round(time.perf_counter() - started, 1)
    print(f"{result['checkpoint']}@{result['revision'][:12]}, {args.preset} weight grid, scope {args.scope}: "
          f"per-component medians, plain -> after the hadamard method's transforms")
    print(f"{'component':>9} {'layers':>6} {'raised':>6} {'W error':>17} {'row kurtosis':>13} {'absmax/rms':>11}"
          f" {'Gaussian control':>17} {'outlier control':>17}")
    for component, c in result["components"].items():
        print(f"{component:>9} {c['layers']:>6} {c['error_raised_in']:>6} "
              f"{c['median_plain_error']:.2e} -> {c['median_transformed_error']:.2e} "
              f"{c['median_plain_kurtosis']:.2f} -> {c['median_transformed_kurtosis']:.2f} "
              f"{c['median_plain_absmax_over_rms']:.2f} -> {c['median_transformed_absmax_over_rms']:.2f} "
              f"{c['median_controls_gaussian_plain']:.2e} -> {c['median_controls_gaussian_rotated']:.2e} "
              f"{c['median_controls_outlier_channel_plain']:.2e} -> {c['median_controls_outlier_channel_rotated']:.2e}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {args.out} ({result['wall_s']} s)")


if __name__ == "__main__":
    main()
