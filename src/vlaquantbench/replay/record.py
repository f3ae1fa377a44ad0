"""Record full-precision trajectories in LIBERO for same-observation replay.

One `<record>.npz` per trajectory (`t<task>_e<init state>.npz`) holds everything the policy saw and
did at each call: both camera images, the state, the instruction, the episode's RNG seed and the
generator state entering the call, the predicted normalized chunk, the flow states entering each
denoising step, how many of the chunk's actions were executed, and the executed actions.
`records.json` beside them carries the provenance.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from vlaquantbench.atomic import write_text
from vlaquantbench.envs.libero import EpisodeSpec, LiberoSuite, LiberoVectorEnv, episode_seed, simulator_versions
from vlaquantbench.config.study import RunnerConfig
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.replay.probe import PolicyProbe, torch_rng_state
from vlaquantbench.runner.provenance import code_revision, versions


@dataclass(frozen=True)
class RecordSettings:
    model: str
    variant: str
    suite: str
    tasks: list[int]
    init_states: list[int]
    observe: list[str]  # layers whose inputs the probe summarizes (e.g. the expert down_proj)
    checkpoint: str | None = None
    revision: str | None = None
    checkpoint_dir: str | None = None
    max_steps: int | None = None  # default: the suite's step limit for the model
    executed_chunk: int | None = RunnerConfig.executed_chunk  # None: the model's released client
    flow_steps: int = RunnerConfig.flow_steps
    run_seed: int = 0
    device: str = RunnerConfig.device
    threads: int = 1  # CPU kernels' blocking depends on it; the replay uses the same count

    @classmethod
    def from_study(cls, study: dict, options: dict | None = None) -> "RecordSettings":
        """The study's recording, with the workflow's `replay` options (variant, tasks, init_states,
        max_steps, checkpoint, revision, checkpoint_dir, device, threads) taking precedence."""
        options = dict(options or {})
        options.pop("formats", None)
        known = set(cls.__dataclass_fields__) - {"model", "suite", "observe"}
        unknown = sorted(set(options) - known)
        if unknown:
            raise UserError(f"replay: unknown options {unknown}; known: {', '.join(sorted(known))}")
        base = {"variant": "full", "tasks": study["tasks"], "init_states": study["init_states"]}
        if options.get("variant", "full") == "full":  # a demo policy has random weights, no checkpoint
            base.update(checkpoint=study["checkpoint"], revision=study["revision"])
        return cls(model=study["model"], suite=study["suite"], observe=study["observe"], **{**base, **options})

    def adapter_config(self) -> AdapterConfig:
        return AdapterConfig(model=self.model, variant=self.variant, checkpoint=self.checkpoint,
                             checkpoint_dir=self.checkpoint_dir, device=self.device,
                             executed_chunk=self.executed_chunk, flow_steps=self.flow_steps)


def record_name(task_id: int, init_state_id: int) -> str:
    return f"t{task_id}_e{init_state_id}.npz"


def _record_one(adapter, probe: PolicyProbe, env: LiberoVectorEnv, spec: EpisodeSpec, max_steps: int) -> dict:
    calls: dict[str, list] = {k: [] for k in ("agentview", "wrist", "state", "rng_state", "chunk", "flow_states", "executed")}
    actions: list[np.ndarray] = []
    generator = adapter.reset(spec.seed)
    obs, success = env.reset([spec])[0], False
    while not success and len(actions) < max_steps:
        calls["rng_state"].append(torch_rng_state(generator))
        with probe.call():
            chunk = adapter.act([obs], [generator])[0]
        captured = probe.take(0)
        for view in ("agentview", "wrist", "state"):
            calls[view].append(obs[view])
        calls["chunk"].append(captured["chunk"])
        calls["flow_states"].append(captured["flow_states"])
        executed = 0
        for action in chunk[: adapter.executed_chunk]:
            observations, successes = env.step(action[None])
            actions.append(action)
            executed += 1
            success = successes[0]
            if success or len(actions) >= max_steps:
                break
            obs = observations[0]
        calls["executed"].append(executed)
    if not success:
        env.release(0)
    return {
        **{k: np.stack(v) for k, v in calls.items()},
        "actions": np.stack(actions),
        "instruction": np.array(obs["instruction"]),
        "seed": np.array(spec.seed),
        "task_id": np.array(spec.task_id),
        "init_state_id": np.array(spec.init_state_id),
        "success": np.array(bool(success)),
    }


def record(settings: RecordSettings, out_dir: str | Path) -> dict:
    """Roll out the full-precision policy from each (task, init state) and store the trajectories."""
    out_dir = Path(out_dir)
    suite = LiberoSuite(settings.suite)
    specs = [EpisodeSpec(t, i, init_state_id=i, seed=episode_seed(t, i, settings.run_seed))
             for t in settings.tasks for i in settings.init_states]
    for spec in specs:  # bad task ids / init states fail here, before the model loads
        suite.init_state(spec.task_id, spec.init_state_id)
    max_steps = settings.max_steps or suite.max_steps(settings.model)
    torch.set_num_threads(settings.threads)
    adapter = make_adapter(settings.adapter_config())
    adapter.load()
    out_dir.mkdir(parents=True, exist_ok=True)
    records = []
    with LiberoVectorEnv(suite, num_envs=1) as env, PolicyProbe(adapter.model, settings.observe, 7) as probe:
        for spec in tqdm(specs, desc="record", unit="trajectory"):
            data = _record_one(adapter, probe, env, spec, max_steps)
            name = record_name(spec.task_id, spec.init_state_id)
            np.savez_compressed(out_dir / name, **data)
            records.append({"record": name, "task_id": spec.task_id, "episode": spec.init_state_id,
                            "seed": spec.seed, "n_steps": len(data["actions"]), "n_chunks": len(data["chunk"]),
                            "flow_steps": settings.flow_steps, "recorded_success": bool(data["success"])})
    meta = {
        "model": settings.model, "variant": settings.variant, "suite": settings.suite,
        "checkpoint": settings.checkpoint, "revision": settings.revision,
        "init_states": settings.init_states, "run_seed": settings.run_seed, "max_steps": max_steps,
        "weights_seed": adapter.config.seed,
        "chunk": {"predicted": adapter.predicted_chunk, "executed": adapter.executed_chunk},
        "observe": settings.observe, "versions": {**versions(), **simulator_versions()},
        "device": settings.device, "flow_steps": settings.flow_steps,
        "torch_threads": torch.get_num_threads(), "code_revision": code_revision(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "records": records,
    }
    write_text(out_dir / "records.json", json.dumps(meta, indent=1))
    return meta


def load_records(records_dir: str | Path) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """The provenance (`records.json`, or the folder holding it) and every trajectory's arrays."""
    records_dir = Path(records_dir)
    if records_dir.name == "records.json":
        records_dir = records_dir.parent
    meta_path = records_dir / "records.json"
    if not meta_path.exists():
        raise UserError(f"no recording in {records_dir}: {meta_path} is missing")
    meta = json.loads(meta_path.read_text())
    data = {}
    for rec in meta["records"]:
        path = records_dir / rec["record"]
        if not path.exists():
            raise UserError(f"recording {meta_path} names {rec['record']}, which is missing")
        with np.load(path) as npz:
            data[rec["record"]] = {k: npz[k] for k in npz.files}
    return meta, data


def record_to(study: dict, options: dict | None, records_json: str | Path) -> dict:
    """Snakemake entry: record the study's trajectories beside `records_json`."""
    return record(RecordSettings.from_study(study, options), Path(records_json).parent)


def recorded_calls(adapter, data: dict[str, np.ndarray], record: str):
    """Feed a recorded trajectory to a policy: resets it with the recorded episode seed and yields
    `(call index, observation, generator)` per call, checking that the generator state entering
    each call equals the recorded one (identical flow noise)."""
    generator = adapter.reset(int(data["seed"]))
    instruction = str(data["instruction"])
    for j in range(len(data["chunk"])):
        if not np.array_equal(torch_rng_state(generator), data["rng_state"][j]):
            raise RuntimeError(f"{record} call {j}: the policy's random stream diverged from the recording")
        obs = {"agentview": data["agentview"][j], "wrist": data["wrist"][j], "state": data["state"][j],
               "instruction": instruction}
        yield j, obs, generator
