"""Closed-loop episodes per hour for one LIBERO cell on one GPU node, against the simulator-only bound.

One process, one policy (pi0.5 at full size with seeded random weights, bf16, the captured sampler,
no quantization unless `--preset`), the real runner (`LiberoVectorEnv` workers executing whole
chunks, `runner.loop.run_episodes` overlapping the policy with stepping). For each N of
`--num-envs`, on one set of N workers:

  - `simulator_bound`: the same tasks and init states driven by a zero-cost policy (small random
    actions drawn from each episode's stream in microseconds), measured first and, for N in `--bound-after`,
    again last (`simulator_bound_after`): the ratio divides by the mean of the two, against drift;
    with `--repeats R`, R - 1 further pairs of a policy run and a bound run follow, each policy run's
    ratio to the bounds around it in `pairs`, `vs_simulator_bound` their median;
  - `simulator_bound_replay` (N in `--replay-bound`): after each policy run, a zero-cost policy
    returning that run's chunks episode by episode (`ReplayPolicy`): the simulator alone on the very
    episodes the policy drove; `same_actions` says they executed the same actions; `replay_pairs` has
    each policy run's ratio to its replay, `vs_replay_bound` their median;
  - `policy`: N x `--rounds` episodes (at least `--min-episodes`) driven by the policy.

Every run records each policy call's batch and wall time and the main process's waits for the simulator;
the main process runs `--torch-threads` intra-op threads (1, as a cell). Episodes go task-major as in a
cell. Random weights never succeed: every episode runs to the step limit. Worker start-up, the first capture
of each graph size (`captured.GRAPH_SIZES`) and one short warm-up episode are timed apart and excluded.
Writes after every N, so a run cut short keeps what it measured.

    MUJOCO_GL=egl python benchmarks/gpu_closed_loop.py --num-envs 32 --bound-after 32 --replay-bound 32 --repeats 2 \\
        --out benchmarks/results/closed_loop_gpu_32_replay.json
    .venv/bin/python benchmarks/gpu_closed_loop.py --device cpu --variant demo --dtype float32 --num-envs 1 2 \\
        --max-steps 20 --camera-size 64 --out /tmp/closed_loop_cpu.json   # CPU smoke run
"""

from __future__ import annotations

import argparse
import datetime
import hashlib
import json
import os
import platform
import time
from collections import defaultdict
from pathlib import Path

import numpy as np
import torch
import transformers

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, episode_generator, make_adapter
from vlaquantbench.models.client import step_limit
from vlaquantbench.models.pi05.fast.captured import GRAPH_SIZES
from vlaquantbench.runner.loop import run_episodes
from vlaquantbench.runner.provenance import versions

# The paper's corpus (sec. 3): 409 evaluation runs, 94,574 simulation episodes.
GRID_RUNS, GRID_EPISODES = 409, 94_574


class Meter:
    """Calls, items and seconds of one wrapped method (the runner calls it; we only count)."""

    def __init__(self):
        self.calls, self.items, self.seconds = 0, 0, 0.0

    def wrap(self, fn, items=lambda *args, **kwargs: 1):
        def timed(*args, **kwargs):
            began = time.perf_counter()
            result = fn(*args, **kwargs)
            self.seconds += time.perf_counter() - began
            self.calls += 1
            self.items += items(*args, **kwargs)
            return result

        return timed

    def summary(self) -> dict:
        return {
            "calls": self.calls,
            "seconds": round(self.seconds, 3),
            "mean_ms": round(1e3 * self.seconds / self.calls, 2) if self.calls else None,
            "mean_items": round(self.items / self.calls, 2) if self.calls else None,
        }


class ZeroCostPolicy:
    """The adapter interface at no cost: small random arm motions, gripper open, from each episode's stream."""

    def __init__(self, executed_chunk: int, predicted_chunk: int):
        self.executed_chunk, self.predicted_chunk = executed_chunk, predicted_chunk

    def reset(self, seed: int) -> torch.Generator:
        return episode_generator(seed)

    def act(self, observations, generators) -> np.ndarray:
        chunks = np.stack([(torch.rand(self.predicted_chunk, 7, generator=g) - 0.5).numpy() * 0.4 for g in generators])
        chunks[:, :, 6] = -1.0
        return chunks


class ChunkRecorder:
    """Records, while installed on a policy, the chunks it returns for each episode (by seed)."""

    def __init__(self, policy):
        self.policy, self.chunks, self.seed_of = policy, defaultdict(list), {}

    def __enter__(self):
        real_reset, real_act = self.policy.reset, self.policy.act

        def reset(seed):
            generator = real_reset(seed)
            self.seed_of[id(generator)] = seed
            self.chunks[seed] = []
            return generator

        def act(observations, generators):
            chunks = real_act(observations, generators)
            for generator, chunk in zip(generators, chunks):
                self.chunks[self.seed_of[id(generator)]].append(np.array(chunk, copy=True))
            return chunks

        self.policy.reset, self.policy.act = reset, act  # instance attributes over the class's methods
        return self

    def __exit__(self, *exc):
        del self.policy.reset, self.policy.act


class ReplayPolicy(ZeroCostPolicy):
    """The zero-cost policy returning, episode by episode, the chunks a policy run returned
    (`ChunkRecorder`): the simulator alone on that run's very episodes (same actions, so the same
    physics), where `ZeroCostPolicy`'s small random actions make episodes of their own."""

    def __init__(self, executed_chunk: int, predicted_chunk: int, chunks_by_seed: dict[int, list[np.ndarray]]):
        super().__init__(executed_chunk, predicted_chunk)
        self.chunks_by_seed = chunks_by_seed

    def reset(self, seed: int):
        return seed, iter(self.chunks_by_seed[seed])

    def act(self, observations, generators) -> np.ndarray:
        chunks = []
        for seed, recorded in generators:
            chunk = next(recorded, None)
            if chunk is None:
                raise RuntimeError(f"the replay of episode seed {seed} asks for more chunks than its policy run returned "
                                   f"({len(self.chunks_by_seed[seed])}): the simulator did not repeat the episode")
            chunks.append(chunk)
        return np.stack(chunks)


def episode_order(suite: LiberoSuite, count: int, per_task: int = 50) -> list:
    return [suite.episode_spec(t, e) for t in range(suite.n_tasks) for e in range(per_task)][:count]


def stand_in_call(adapter, suite: LiberoSuite, camera_size: int, batch: int) -> float:
    """Seconds of one policy call on `batch` blank observations."""
    blank = np.zeros((camera_size, camera_size, 3), np.uint8)
    obs = {"agentview": blank, "wrist": blank, "state": np.zeros(8, np.float32),
           "instruction": suite.tasks[0].instruction}
    began = time.perf_counter()
    adapter.act([obs] * batch, [adapter.reset(i) for i in range(batch)])
    return time.perf_counter() - began


def on_cuda(adapter) -> bool:
    return torch.cuda.is_available() and adapter.model is not None and next(adapter.model.parameters()).is_cuda


def gpu_memory() -> dict:
    return {"allocated_gib": round(torch.cuda.memory_allocated() / 2**30, 2),
            "reserved_gib": round(torch.cuda.memory_reserved() / 2**30, 2),
            "peak_gib": round(torch.cuda.max_memory_allocated() / 2**30, 2)}


def warm_up(adapter, suite: LiberoSuite, camera_size: int, batch: int) -> dict:
    """One chunk at `batch` on stand-in observations: captures that batch size's graph. Returns its
    time and, on CUDA, the GPU memory afterwards (every captured graph keeps memory in proportion to
    its batch: `captured.GRAPH_SIZES`)."""
    result = {"s": round(stand_in_call(adapter, suite, camera_size, batch), 2)}
    return result | gpu_memory() if on_cuda(adapter) else result


def build_first_tasks(env: LiberoVectorEnv, specs: list) -> None:
    """Reset each slot once with the episode it starts with, so no timed run pays the task build."""
    env.reset([specs[i] if i < len(specs) else None for i in range(env.num_envs)])
    for slot in range(env.num_envs):
        env.release(slot)


def measure(policy, env: LiberoVectorEnv, specs: list, max_steps: int) -> dict:
    calls, waits = Meter(), Meter()
    real_act, real_collect = policy.act, env.collect
    policy.act = calls.wrap(real_act, items=lambda observations, generators: len(observations))
    env.collect = waits.wrap(real_collect)
    records: list[dict] = []
    try:
        began = time.perf_counter()
        run_episodes(policy, env, specs, max_steps, on_finished=records.extend, overlap=True)
        wall = time.perf_counter() - began
    finally:
        policy.act, env.collect = real_act, real_collect
    steps = int(sum(r["steps"] for r in records))
    return {
        "episodes": len(records),
        "policy_steps": steps,
        "successes": int(sum(r["success"] for r in records)),
        "wall_s": round(wall, 2),
        "episodes_per_hour": round(3600 * len(records) / wall, 1),
        # Over every episode's executed actions, in seed order: equal runs executed the same actions.
        "actions_sha256": hashlib.sha256("".join(r["actions_sha256"] for r in sorted(records, key=lambda r: r["seed"]))
                                         .encode()).hexdigest(),
        "env_steps_per_s": round(steps / wall, 1),
        "policy_call": calls.summary(),  # mean_items = mean batch of one policy call
        "collect_wait": waits.summary(),  # the main process waiting for the simulator
    }


def main() -> Path:
    """Runs the measurements; returns the path written (`--out`)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="libero_spatial")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--variant", default="random", choices=["random", "demo"])
    parser.add_argument("--dtype", default="bfloat16")
    parser.add_argument("--sampler", default="captured", choices=["captured", "eager"])
    parser.add_argument("--preset", default=None, help="e.g. W4A4: end-to-end fake quantization via quantize_")
    parser.add_argument("--method", default="rtn", help="quantization method of --preset, e.g. fp8 (W8A8): real FP8 kernels")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 16, 32, 64])
    parser.add_argument("--bound-after", type=int, nargs="*", default=[],
                        help="N whose simulator bound is measured again after the policy runs")
    parser.add_argument("--replay-bound", type=int, nargs="*", default=[],
                        help="N whose every policy run is followed by a zero-cost run replaying its actions")
    parser.add_argument("--repeats", type=int, default=1,
                        help="policy runs per N of --bound-after, each followed by a bound run (ratio: the median)")
    parser.add_argument("--torch-threads", type=int, default=1, help="intra-op threads of this process, as a cell's")
    parser.add_argument("--rounds", type=int, default=1, help="episodes per slot")
    parser.add_argument("--min-episodes", type=int, default=2)
    parser.add_argument("--max-steps", type=int, default=None, help="default: the suite's limit for pi0.5")
    parser.add_argument("--camera-size", type=int, default=256)
    parser.add_argument("--out", default="benchmarks/results/closed_loop_gpu.json")
    args = parser.parse_args()
    if args.repeats < 1 or (args.repeats > 1 and not args.bound_after):
        parser.error("--repeats needs a positive count, and above 1 the N it repeats in --bound-after")
    torch.set_num_threads(args.torch_threads)

    suite = LiberoSuite(args.suite)
    max_steps = args.max_steps or step_limit("pi05", "libero", args.suite)
    began = time.perf_counter()
    adapter = make_adapter(AdapterConfig(model="pi05", variant=args.variant, device=args.device, dtype=args.dtype,
                                         sampler=args.sampler))
    adapter.load()
    load_s = time.perf_counter() - began
    report, quant_header = None, None
    if args.preset:
        from vlaquantbench.quant import QuantConfig, quantize_

        config = QuantConfig.from_preset(args.preset, scope="e2e", method=args.method)
        report = quantize_(adapter.model, config, config.select(adapter.model, adapter.components))
        quant_header = report.to_header()["quant_report"]
    inference = adapter.prepare_inference(report)
    probe = adapter.fast_path_probe()  # the fast path against the eager policy, as a cell checks it before any episode
    if probe is not None:
        inference = {**inference, "fast_path_probe": probe}
        print("fast path probe:", probe, flush=True)
    warmups = {b: warm_up(adapter, suite, args.camera_size, b) for b in sorted(GRAPH_SIZES)}
    memory = None
    if on_cuda(adapter):
        # What the captures' uncaptured first runs left cached goes back to the driver: the workers'
        # EGL contexts need it (64 workers beside 115.9 GiB reserved could not create theirs).
        torch.cuda.empty_cache()
        memory = gpu_memory()
    print(f"policy load {load_s:.1f} s, first chunk per batch size (capture) {warmups}; after empty_cache {memory}",
          flush=True)
    zero_cost = ZeroCostPolicy(adapter.executed_chunk, adapter.predicted_chunk)

    gpu = torch.cuda.get_device_name() if torch.device(args.device).type == "cuda" else None
    result = {
        "suite": args.suite, "model": "pi05", "variant": args.variant, "dtype": args.dtype,
        "preset": args.preset or "BASELINE", "method": args.method if args.preset else None, "quant_report": quant_header, "inference": inference,
        "max_steps": max_steps, "executed_chunk": adapter.executed_chunk, "camera_size": args.camera_size,
        "torch_threads": args.torch_threads,
        "policy_load_s": round(load_s, 2), "first_chunk_s_by_batch": warmups, "gpu_memory_after_warmup": memory,
        "runs": [],
        "machine": {
            "device": args.device, "gpu": gpu, "cpus": os.cpu_count(), "platform": platform.platform(),
            "versions": {**versions(), "transformers": transformers.__version__},
            "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        },
    }
    # robosuite's numba kernels compile (and cache) on first use: one short untimed episode first.
    with LiberoVectorEnv(suite, 1, camera_size=args.camera_size) as env:
        warm = measure(adapter, env, episode_order(suite, 1), 2 * adapter.executed_chunk)
    result["simulator_warmup_s"] = warm["wall_s"]
    for n in args.num_envs:
        specs = episode_order(suite, max(n * args.rounds, args.min_episodes))
        began = time.perf_counter()
        with LiberoVectorEnv(suite, n, camera_size=args.camera_size) as env:
            build_first_tasks(env, specs)
            run = {"num_envs": n, "worker_startup_s": round(time.perf_counter() - began, 2)}

            def policy_and_replay() -> dict:
                """A policy run; for N in --replay-bound, the replay of its chunks next."""
                if n not in args.replay_bound:
                    return {"policy": measure(adapter, env, specs, max_steps)}
                with ChunkRecorder(adapter) as recorder:
                    policy = measure(adapter, env, specs, max_steps)
                replay = ReplayPolicy(adapter.executed_chunk, adapter.predicted_chunk, recorder.chunks)
                replayed = measure(replay, env, specs, max_steps)
                replayed["same_actions"] = replayed["actions_sha256"] == policy["actions_sha256"]
                return {"policy": policy, "simulator_bound_replay": replayed}

            run["simulator_bound"] = measure(zero_cost, env, specs, max_steps)
            run |= policy_and_replay()
            if n in args.bound_after:
                run["simulator_bound_after"] = measure(zero_cost, env, specs, max_steps)
                for _ in range(args.repeats - 1):
                    repeat = policy_and_replay()
                    repeat["simulator_bound"] = measure(zero_cost, env, specs, max_steps)
                    run.setdefault("repeats", []).append(repeat)
        bounds = [run[k]["episodes_per_hour"] for k in ("simulator_bound", "simulator_bound_after") if k in run]
        policies = [run["policy"]["episodes_per_hour"]]
        for repeat in run.get("repeats", []):
            bounds.append(repeat["simulator_bound"]["episodes_per_hour"])
            policies.append(repeat["policy"]["episodes_per_hour"])
        run["pairs"] = [{"policy": policy, "bounds": bounds[i : i + 2],
                         "ratio": round(policy / float(np.mean(bounds[i : i + 2])), 3)}
                        for i, policy in enumerate(policies)]
        run["simulator_bound_episodes_per_hour"] = round(float(np.mean(bounds)), 1)
        run["vs_simulator_bound"] = round(float(np.median([pair["ratio"] for pair in run["pairs"]])), 3)
        if "simulator_bound_replay" in run:
            replays = [run, *run.get("repeats", [])]
            run["replay_pairs"] = [{"policy": r["policy"]["episodes_per_hour"],
                                    "replay": r["simulator_bound_replay"]["episodes_per_hour"],
                                    "same_actions": r["simulator_bound_replay"]["same_actions"],
                                    "ratio": round(r["policy"]["episodes_per_hour"] /
                                                   r["simulator_bound_replay"]["episodes_per_hour"], 3)} for r in replays]
            run["vs_replay_bound"] = round(float(np.median([pair["ratio"] for pair in run["replay_pairs"]])), 3)
        result["runs"].append(run)
        print(f"num_envs={n}: policy {run['policy']['episodes_per_hour']} episodes/h "
              f"(batch {run['policy']['policy_call']['mean_items']}, {run['policy']['policy_call']['mean_ms']} ms/call), "
              f"simulator bound {run['simulator_bound_episodes_per_hour']} ({' and '.join(map(str, bounds))}) -> "
              f"{run['vs_simulator_bound']}", flush=True)
        if len(run["pairs"]) > 1:
            print(f"  pairs (policy, bounds before and after, ratio): {run['pairs']}", flush=True)
        if "replay_pairs" in run:
            print(f"  replaying each policy run's actions: {run['replay_pairs']} -> {run['vs_replay_bound']}", flush=True)
            if not all(pair["same_actions"] for pair in run["replay_pairs"]):
                print("  WARNING: a replay executed other actions than its policy run (same_actions false): "
                      "its ratio compares different episodes", flush=True)
        best = max(result["runs"], key=lambda r: r["policy"]["episodes_per_hour"])
        result["best"] = {
            "num_envs": best["num_envs"], "episodes_per_hour": best["policy"]["episodes_per_hour"],
            "vs_simulator_bound": best["vs_simulator_bound"],
            **({"vs_replay_bound": best["vs_replay_bound"]} if "vs_replay_bound" in best else {}),
            # Every episode here runs to the step limit; the grid's successful episodes end earlier.
            "grid_gpu_hours_upper_bound": round(GRID_EPISODES / best["policy"]["episodes_per_hour"], 1),
            "grid": f"{GRID_RUNS} runs, {GRID_EPISODES} episodes at {max_steps} steps each, one GPU node",
        }
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")

    print(f"best: {result['best']}")
    print(f"camera {args.camera_size} px, {os.cpu_count()} cores, {gpu or args.device}, {result['machine']['versions']}")
    return Path(args.out)


if __name__ == "__main__":
    main()
