"""Record full-precision trajectories in any benchmark for same-observation replay (suite, episode specs, step
limit, env and action size from the benchmark seam, `vlaquantbench.envs`; the env settings those of the study's
cells: the model's client's controller mode and MuJoCo pin, the study's `runner`, the benchmark's defaults).

One `<record>.npz` per trajectory (`t<task>_e<init state>.npz`) holds everything the policy saw and
did at each call: the image of every camera the benchmark declares (`envs.registry.Benchmark.cameras`,
under its observation key), the state, the instruction, the episode's RNG seed and the
generator state entering the call, the predicted normalized chunk, the flow states entering each
denoising step, how many of the chunk's actions were executed, and the executed actions.
`records.json` beside them carries the provenance. The rule `replay_record` declares every one of
these files as an output (`RecordSettings.trajectory_files`).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from vlaquantbench.atomic import atomic_write, write_text
from vlaquantbench.envs import benchmark_settings, env_settings, make_env, make_suite, simulator_versions
from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.registry import get_benchmark
from vlaquantbench.envs.workers import WorkerVectorEnv
from vlaquantbench.errors import UserError
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.models.client import client_conventions, step_limit
from vlaquantbench.replay.probe import PolicyProbe, torch_rng_state
from vlaquantbench.replay.study import RecordSettings
from vlaquantbench.runner.provenance import code_revision, versions
from vlaquantbench.textfiles import read_parsed


def adapter_config(settings: RecordSettings) -> AdapterConfig:
    return AdapterConfig(model=settings.model, variant=settings.variant, checkpoint=settings.checkpoint,
                         revision=settings.revision,
                         checkpoint_dir=settings.checkpoint_dir, device=settings.device,
                         executed_chunk=settings.executed_chunk, flow_steps=settings.flow_steps,
                         cameras=dict(get_benchmark(settings.benchmark).cameras))


def _record_one(adapter, probe: PolicyProbe, env: WorkerVectorEnv, spec: EpisodeSpec, max_steps: int,
                observed: tuple[str, ...]) -> dict:
    calls: dict[str, list] = {k: [] for k in (*observed, "rng_state", "chunk", "flow_states", "executed")}
    actions: list[np.ndarray] = []
    generator = adapter.reset(spec.seed)
    obs, success = env.reset([spec])[0], False
    while not success and len(actions) < max_steps:
        calls["rng_state"].append(torch_rng_state(generator))
        with probe.call():
            chunk = adapter.act([obs], [generator])[0]
        captured = probe.take(0)
        for view in observed:
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


def record(settings: RecordSettings, records_json: str | Path, trajectories: list[str | Path]) -> dict:
    """Roll out the full-precision policy from each (task, init state) and store the trajectories at
    `trajectories` (named as `settings.trajectory_files()`, beside `records_json`) and their provenance."""
    records_json, trajectories = Path(records_json), [Path(p) for p in trajectories]
    expected = [records_json.parent / name for name in settings.trajectory_files()]
    if trajectories != expected:
        raise UserError(f"recording {records_json}: trajectory files {[str(p) for p in trajectories]} are not the "
                        f"recording's {[str(p) for p in expected]}")
    suite = make_suite(settings.benchmark, settings.suite)
    # Trajectory i of a task starts from init state i; bad task ids / init states fail here, before the model loads.
    specs = [suite.episode_spec(t, i, settings.run_seed) for t in settings.tasks for i in settings.init_states]
    # The cells' env settings, so that the policy observes what it observes in them: the model's released
    # client's controller mode and MuJoCo pin, then what the study sets for its cells (e.g. a trained
    # checkpoint's camera size), the benchmark's declared defaults elsewhere.
    client = client_conventions(settings.model, settings.benchmark)
    env_options = env_settings(benchmark_settings(settings.benchmark, settings.runner,
                                                  {key: f"replay study runner.{key}" for key in settings.runner},
                                                  conventions=client.runner()))
    simulator = simulator_versions(settings.benchmark, pinned=client.mujoco)
    max_steps = settings.max_steps or step_limit(settings.model, settings.benchmark, settings.suite)
    torch.set_num_threads(settings.threads)
    adapter = make_adapter(adapter_config(settings))
    adapter.load()
    records_json.parent.mkdir(parents=True, exist_ok=True)
    records = []
    action_dim = get_benchmark(settings.benchmark).action_dim  # what the probe keeps of the policy's padded chunk
    with make_env(settings.benchmark, suite, 1, **env_options) as env, \
            PolicyProbe(adapter.model, settings.observe, action_dim) as probe:
        for spec, path in tqdm(list(zip(specs, trajectories)), desc="record", unit="trajectory"):
            data = _record_one(adapter, probe, env, spec, max_steps, get_benchmark(settings.benchmark).observed)
            with atomic_write(path, "wb") as handle:
                np.savez_compressed(handle, **data)
            records.append({"record": path.name, "task_id": spec.task_id, "episode": spec.init_state_id,
                            "seed": spec.seed, "n_steps": len(data["actions"]), "n_chunks": len(data["chunk"]),
                            "flow_steps": settings.flow_steps, "recorded_success": bool(data["success"])})
    meta = {
        "model": settings.model, "variant": settings.variant, "benchmark": settings.benchmark, "suite": settings.suite,
        "checkpoint": settings.checkpoint, "revision": settings.revision,
        "init_states": settings.init_states, "run_seed": settings.run_seed, "max_steps": max_steps,
        "weights_seed": adapter.config.seed,
        "chunk": {"predicted": adapter.predicted_chunk, "executed": adapter.executed_chunk},
        "observe": settings.observe, "env_settings": env_options, "versions": {**versions(), **simulator},
        "device": settings.device, "flow_steps": settings.flow_steps,
        "torch_threads": torch.get_num_threads(), "code_revision": code_revision(),
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"), "records": records,
    }
    write_text(records_json, json.dumps(meta, indent=1))
    return meta


def load_records(records_json: str | Path, trajectories: list[str | Path]) -> tuple[dict, dict[str, dict[str, np.ndarray]]]:
    """The provenance `records_json` and the arrays of every trajectory it names (`trajectories`: their
    files, which must be exactly the ones it names), keyed by record name."""
    records_json = Path(records_json)
    if not records_json.is_file():
        raise UserError(f"no recording: {records_json} is missing")
    meta = read_parsed(records_json, json.loads, "JSON")
    if "benchmark" not in meta:  # its trajectories' observation keys are that benchmark's (`recorded_calls`)
        raise UserError(f"recording {records_json} names no benchmark (recorded before issue 50); record it again")
    given = {Path(p).name: Path(p) for p in trajectories}
    named = [rec["record"] for rec in meta["records"]]
    if sorted(given) != sorted(named):
        raise UserError(f"recording {records_json} names trajectories {named}; given {sorted(given)}")
    data = {}
    for name in named:
        if not given[name].is_file():
            raise UserError(f"recording {records_json} names {name}, which is missing ({given[name]})")
        with np.load(given[name]) as npz:
            data[name] = {k: npz[k] for k in npz.files}
    return meta, data


def record_to(study: dict, options: dict | None, records_json: str | Path, trajectories: list[str | Path]) -> dict:
    """Snakemake entry: record the study's trajectories (the rule's declared outputs)."""
    return record(RecordSettings.from_study(study, options), records_json, trajectories)


def recorded_calls(adapter, data: dict[str, np.ndarray], record: str, benchmark: str):
    """Feed a recorded trajectory of `benchmark` to a policy: resets it with the recorded episode seed and yields
    `(call index, observation, generator)` per call, checking that the generator state entering
    each call equals the recorded one (identical flow noise)."""
    observed = get_benchmark(benchmark).observed
    generator = adapter.reset(int(data["seed"]))
    instruction = str(data["instruction"])
    for j in range(len(data["chunk"])):
        if not np.array_equal(torch_rng_state(generator), data["rng_state"][j]):
            raise RuntimeError(f"{record} call {j}: the policy's random stream diverged from the recording")
        obs = {**{view: data[view][j] for view in observed}, "instruction": instruction}
        yield j, obs, generator
