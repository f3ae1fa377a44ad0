"""Replay one configuration on recorded trajectories (paper App. `app:pi05_replay`).

The policy is loaded afresh and quantized through `quantize_` with the subset patterns of the
matching closed-loop cell; its selected layer count must equal the study's. Per trajectory the
policy is reset with the recorded episode seed, and each call receives exactly the recorded
observation; the generator state entering every call must equal the recorded one, so the flow
noise is identical. Quantized policies never drive the simulator here.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from tqdm import tqdm

from vlaquantbench.envs.registry import get_benchmark
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig, get_subset, quantize_
from vlaquantbench.replay.composition import DOWNPROJ_COLUMNS
from vlaquantbench.replay.probe import PolicyProbe
from vlaquantbench.replay.record import load_records, recorded_calls
from vlaquantbench.replay.run import ReplayRun
from vlaquantbench.runner.provenance import code_revision, versions

BASELINE = "BASELINE"


def quant_config(study: dict, name: str, preset: str) -> tuple[QuantConfig, int]:
    """The QuantConfig of a study configuration at `preset`, and the layer count it must select."""
    if preset == BASELINE:
        return QuantConfig.from_preset(BASELINE), 0
    conf = study["configurations"].get(name)
    if conf is None:
        raise UserError(f"replay study has no configuration {name!r}; known: {', '.join(study['configurations'])}")
    only = exclude = None
    if conf.get("subset"):
        subset = get_subset(study["model"], conf["subset"])
        only, exclude = subset.only, subset.exclude
    return QuantConfig.from_preset(preset, scope=conf["scope"], only=only, exclude=exclude), conf["layers"]


def replay_configuration(records_json, trajectories, study: dict, name: str, preset: str, checkpoint_dir=None) -> ReplayRun:
    """Replay configuration `name` at `preset` on a recording (`records.json` and its trajectory files)."""
    meta, trajectories = load_records(records_json, trajectories)
    cfg, expected_layers = quant_config(study, name, preset)
    adapter = make_adapter(AdapterConfig(model=meta["model"], variant=meta["variant"], checkpoint=meta["checkpoint"],
                                         revision=meta["revision"],
                                         checkpoint_dir=checkpoint_dir, executed_chunk=meta["chunk"]["executed"],
                                         device=meta["device"], flow_steps=meta["flow_steps"],
                                         cameras=dict(get_benchmark(meta["benchmark"]).cameras)))
    adapter.load()
    report = quantize_(adapter.model, cfg, cfg.select(adapter.model, adapter.components))
    layers = sum(c["layers"] for c in report.components.values()) if expected_layers else 0
    if layers != expected_layers:
        raise UserError(f"replay configuration {name!r} at {preset} selects {layers} layers; the study expects {expected_layers}")
    torch.set_num_threads(meta["torch_threads"])  # same kernels' blocking as the recording
    probe = PolicyProbe(adapter.model, meta["observe"], get_benchmark(meta["benchmark"]).action_dim)
    arrays, records = {}, []
    with probe:
        for rec in tqdm(meta["records"], desc=f"replay {name}", unit="trajectory"):
            arrays[rec["record"]], dev = _replay_trajectory(adapter, probe, trajectories[rec["record"]], rec["record"],
                                                               meta["benchmark"])
            records.append({**rec, "dev_from_recorded_actions": dev})
    report.check_hooks_fired()
    summary = {
        "config": name, "model": meta["model"], "variant": meta["variant"], "suite": meta["suite"],
        "preset": preset, "scope": cfg.scope, "only": list(cfg.only) if cfg.only else None,
        "exclude": list(cfg.exclude) if cfg.exclude else None, "quantized_layers": layers,
        **report.to_header(), "checkpoint": meta["checkpoint"], "revision": meta["revision"],
        "downproj_layers": list(probe.layers), "downproj_columns": list(DOWNPROJ_COLUMNS),
        "records": records, "recording": {"code_revision": meta["code_revision"], "created": meta["created"]},
        "versions": versions(), "vqb_commit": code_revision(), "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
    }
    return ReplayRun(summary, arrays)


def _replay_trajectory(adapter, probe: PolicyProbe, data: dict, record: str, benchmark: str) -> tuple[dict, float]:
    chunks, states, inputs, actions = [], [], [], []
    for j, obs, generator in recorded_calls(adapter, data, record, benchmark):
        with probe.call():
            chunk = adapter.act([obs], [generator])[0]
        captured = probe.take(0)
        chunks.append(captured["chunk"])
        states.append(captured["flow_states"])
        inputs.append(captured["inputs"])
        actions.append(chunk[: int(data["executed"][j])])
    actions = np.concatenate(actions)
    dev = float(np.abs(actions - data["actions"]).mean())
    return {"chunks": np.stack(chunks), "actions": actions, "flow_states": np.stack(states),
            "downproj": np.concatenate(inputs)}, dev

def replay_to(records_json, trajectories, study: dict, name: str, preset: str, summary_out, arrays_out,
              checkpoint_dir=None) -> ReplayRun:
    """Snakemake entry: replay configuration `name` at `preset`; writes `summary_out` and `arrays_out`."""
    run = replay_configuration(records_json, trajectories, study, name, preset, checkpoint_dir)
    run.save(summary_out, arrays_out)
    return run
