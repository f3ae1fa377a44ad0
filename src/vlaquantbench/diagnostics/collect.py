"""Collect per-layer diagnostics on recorded full-precision trajectories.

The policy runs at released precision on exactly the recorded observations (as in the replay);
forward hooks on the layers a scope selects compute, per call, what the preset's quantizer would
do to that layer alone (`diagnostics.measures`), averaged over calls. The output file has the
authors' `diagnostics/v2` layout, with the recording's provenance.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import torch
from torch import nn
from tqdm import tqdm

from vlaquantbench.atomic import write_text
from vlaquantbench.diagnostics.measures import MEASURES, layer_measures
from vlaquantbench.envs.registry import get_benchmark
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import parse_preset, select_layers
from vlaquantbench.quant.input_transform import InputTransform
from vlaquantbench.replay.record import load_records, recorded_calls
from vlaquantbench.runner.provenance import code_revision, versions


class DiagnosticsObserver:
    """Forward hooks accumulating the diagnostics of each selected layer over its calls."""

    def __init__(self, layers: dict[str, nn.Linear], preset: str):
        self.preset = parse_preset(preset)
        self.layers = layers
        grid = self.preset.weight
        self._qweight = {n: grid.quantize_weight(m.weight.detach()) if grid else m.weight.detach()
                         for n, m in layers.items()}
        self._quantize_input = InputTransform(act_bits=self.preset.act_bits, act_format=self.preset.act_format)
        self.sums = {n: dict.fromkeys(MEASURES, 0.0) for n in layers}
        self.calls = dict.fromkeys(layers, 0)
        self._handles = []

    def __enter__(self) -> "DiagnosticsObserver":
        self._handles = [m.register_forward_hook(self._hook(n)) for n, m in self.layers.items()]
        return self

    def __exit__(self, *exc) -> None:
        for h in self._handles:
            h.remove()

    def _hook(self, name: str):
        def hook(module: nn.Linear, args, output):
            x = args[0].detach()
            qx = self._quantize_input(x)
            for key, value in layer_measures(x, module.weight.detach(), module.bias, qx, self._qweight[name]).items():
                self.sums[name][key] += value
            self.calls[name] += 1

        return hook

    def result(self) -> dict[str, dict]:
        out = {}
        for name, layer in self.layers.items():
            n = self.calls[name]
            out[name] = {**{k: v / n if n else float("nan") for k, v in self.sums[name].items()}, "calls": n,
                         "in_features": layer.in_features, "out_features": layer.out_features,
                         "params": layer.weight.numel()}
        return out


def collect(records_json: str | Path, trajectories: list[str | Path], model: str, scope: str, preset: str,
            output: str | Path, checkpoint_dir: str | None = None) -> dict:
    """Snakemake entry: diagnostics of every layer in `scope` under `preset` on the recording
    (`records.json` and its trajectory files)."""
    meta, trajectories = load_records(records_json, trajectories)
    if meta["model"] != model:
        raise UserError(f"diagnostics for {model!r} asked of a recording of {meta['model']!r} ({records_json})")
    adapter = make_adapter(AdapterConfig(model=meta["model"], variant=meta["variant"], checkpoint=meta["checkpoint"],
                                         revision=meta["revision"],
                                         checkpoint_dir=checkpoint_dir, executed_chunk=meta["chunk"]["executed"],
                                         device=meta["device"], flow_steps=meta["flow_steps"],
                                         cameras=dict(get_benchmark(meta["benchmark"]).cameras)))
    adapter.load()
    layers = select_layers(adapter.model, adapter.components, scope).flat()
    torch.set_num_threads(meta["torch_threads"])
    with DiagnosticsObserver(layers, preset) as observer, torch.no_grad():
        for rec in tqdm(meta["records"], desc=f"diagnostics {scope} {preset}", unit="trajectory"):
            for _, obs, generator in recorded_calls(adapter, trajectories[rec["record"]], rec["record"], meta["benchmark"]):
                adapter.act([obs], [generator])
    unfired = [n for n, c in observer.calls.items() if c == 0]
    if unfired:
        raise RuntimeError(f"diagnostic hooks never fired on {len(unfired)} layers: {', '.join(unfired)}")
    result = {
        "model": meta["model"], "suite": meta["suite"], "scope": scope, "preset": preset,
        "spec": observer.preset.describe(),
        "provenance": {
            "checkpoint": meta["checkpoint"], "checkpoint_revision": meta["revision"], "variant": meta["variant"],
            "seed": meta["run_seed"], "tasks": sorted({r["task_id"] for r in meta["records"]}),
            "init_states": meta["init_states"], "episodes_from": min(meta["init_states"]),
            "episodes": len(meta["init_states"]), "vqb_commit": code_revision(),
            "recording_code_revision": meta["code_revision"], "mujoco": meta["versions"]["mujoco"],
            "torch": versions()["torch"], "lerobot": versions()["lerobot"], "python": versions()["python"],
            "gpu": torch.cuda.get_device_name() if torch.cuda.is_available() else None,
            "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        },
        "layers": observer.result(),
    }
    write_text(output, json.dumps(result, indent=1))
    return result
