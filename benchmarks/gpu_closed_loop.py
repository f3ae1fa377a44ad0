"""Closed-loop episodes per hour for one LIBERO cell on one GPU node, against the simulator-only bound.

One process, one policy (pi0.5 at full size with seeded random weights, bf16, the captured sampler,
no quantization unless `--preset`), the real runner (`LiberoVectorEnv` workers executing whole
chunks, `runner.loop.run_episodes` overlapping the policy with stepping). For each N of
`--num-envs`, on one set of N workers:

  - `simulator_bound`: the same tasks and init states driven by a zero-cost policy (small random
    actions drawn from each episode's stream in microseconds): what the simulator alone allows on this
    machine for those actions; measured
    first and, for N in `--bound-after`, again last (`simulator_bound_after`): the ratio divides by
    the mean of the two, so that a drift of the machine during the runs does not favour either side;
    with `--repeats R`, R - 1 further pairs of a policy run and a bound run follow (`repeats`), each
    policy run's ratio is to the mean of the bounds just before and after it (`pairs`), and
    `vs_simulator_bound` is the median of the pairs' ratios: single runs' ratios spread by 0.06 on
    one machine whose speed drifts by up to 21% within minutes;
  - `simulator_bound_replay` (N in `--replay-bound`): after each policy run, a zero-cost policy
    returning, episode by episode, the chunks that run's policy returned (`ReplayPolicy`): the
    simulator alone on the very episodes the policy drove, whose steps can cost more CPU than the
    random actions' (`benchmarks/HISTORY.md`); `same_actions` says every episode executed the same
    actions (`actions_sha256`, over the episodes' digests); `replay_pairs` has each policy run's ratio
    to its replay, `vs_replay_bound` their median;
  - `policy`: N x `--rounds` episodes (at least `--min-episodes`) driven by the policy, once per
    `--min-batch` value (`runner.loop.run_episodes`' `min_batch`; `policy` is the first,
    `policy_by_min_batch` has them all);
  - `latency_model` (N in `--latency-model`): the same episodes driven by a policy that computes
    nothing on the GPU and sleeps, per call, as long as a policy call of that batch took in the warm-up
    (same padding): the policy's latency without its GPU work and host CPU, which tells how much of
    the policy's cost is latency and how much is contention with the simulator (EGL renders share the GPU);
  - `lockstep` (N in `--lockstep`): the same episodes, every slot's chunk collected before the next
    policy call (`overlap=False`): the policy's time is not hidden;
  - `policy_reniced` (with `--renice`): the policy again, the workers at that niceness.

Every run records the machine's busy cores (/proc/stat) and the main process's CPU (all its
threads), and each policy call's batch, graph plan (`captured.graph_plan`), wall and GPU time. The main process runs
`--torch-threads` intra-op threads (1, as a cell: `ExecutionConfig.torch_threads`).

Episodes go task-major as in a cell (task 0's init states 0, 1, ..., then task 1's); each slot's
first task environment is built before timing, so every run meets the same builds. Random weights
never succeed: every episode runs to the step limit (the suite's, or `--max-steps`). Worker
start-up, the first capture of each graph size (`captured.GRAPH_SIZES`: the captured sampler runs a
batch as the cheapest cover of its rows by these sizes, `graph_plan`; the CUDA cache is emptied
afterwards, for the workers' EGL contexts) and one short simulator
warm-up episode are timed apart and excluded. Writes after every N, so a run cut short keeps what
it measured.

    MUJOCO_GL=egl python benchmarks/gpu_closed_loop.py --num-envs 1 16 32 --out benchmarks/results/closed_loop_gpu.json
    .venv/bin/python benchmarks/gpu_closed_loop.py --device cpu --variant demo --dtype float32 --num-envs 1 2 \\
        --lockstep 2 --max-steps 20 --camera-size 64 --out /tmp/closed_loop_cpu.json   # CPU smoke run
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
from vlaquantbench.models.pi05.fast.captured import GRAPH_SIZES, graph_plan
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


def cpu_ticks(worker_pids: list[int]) -> dict[str, int]:
    """CPU ticks since boot: the machine's, summed over cores and split by kind (/proc/stat), and the
    workers' (/proc/PID/stat, user and system)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    user, nice, system, idle, iowait, irq, softirq = fields[:7]
    workers = 0
    for pid in worker_pids:
        stat = Path(f"/proc/{pid}/stat").read_text()
        workers += sum(int(v) for v in stat[stat.rindex(")") + 2:].split()[11:13])  # utime, stime
    return {"total": sum(fields), "busy": sum(fields) - idle - iowait, "user": user + nice, "system": system,
            "irq": irq + softirq, "workers": workers}


def cores_used(before: dict[str, int], after: dict[str, int]) -> dict[str, float]:
    """Cores busy between two `cpu_ticks` readings, in total and by kind."""
    scale = (os.cpu_count() or 1) / max(after["total"] - before["total"], 1)
    return {key: round(scale * (after[key] - before[key]), 2) for key in before if key != "total"}


class CallLog:
    """Batch, wall ms and GPU ms of every policy call; summarized by graph plan ("12+1": the sizes replayed)."""

    def __init__(self):
        self.calls: list[tuple[int, float]] = []

    def wrap(self, fn):
        def timed(observations, generators):
            began = time.perf_counter()
            result = fn(observations, generators)
            self.calls.append((len(observations), 1e3 * (time.perf_counter() - began)))
            return result

        return timed

    def summary(self, gpu_ms: list[float] | None) -> dict:
        by_size = defaultdict(lambda: {"calls": 0, "rows": 0, "ms": 0.0, "gpu_ms": 0.0})
        for index, (batch, ms) in enumerate(self.calls):
            entry = by_size["+".join(map(str, graph_plan(batch)))]
            entry["calls"] += 1
            entry["rows"] += batch
            entry["ms"] += ms
            entry["gpu_ms"] += gpu_ms[index] if gpu_ms else 0.0
        return {plan: {"calls": e["calls"], "mean_batch": round(e["rows"] / e["calls"], 2),
                            "mean_ms": round(e["ms"] / e["calls"], 2),
                            **({"mean_gpu_ms": round(e["gpu_ms"] / e["calls"], 2)} if gpu_ms else {})}
                for plan, e in sorted(by_size.items(), key=lambda item: sum(map(int, item[0].split("+"))))}


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


class LatencyModelPolicy(ZeroCostPolicy):
    """The zero-cost policy that sleeps, per call, the warm-up's wall times of the graphs its batch
    replays (`graph_plan`): the real policy's latency without its GPU work or its host CPU."""

    def __init__(self, executed_chunk: int, predicted_chunk: int, call_s_by_size: dict[int, float]):
        super().__init__(executed_chunk, predicted_chunk)
        self.call_s_by_size = call_s_by_size

    def act(self, observations, generators) -> np.ndarray:
        time.sleep(sum(self.call_s_by_size[size] for size in graph_plan(len(observations))))
        return super().act(observations, generators)


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


class GpuMeter:
    """GPU time of the adapter's sampling (CUDA events around `_sample`, read after the run): what
    part of a policy call the GPU spends, the rest being the main process's own work and waits."""

    def __init__(self):
        self.events: list[tuple] = []

    def wrap(self, fn):
        def timed(*args, **kwargs):
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            result = fn(*args, **kwargs)
            end.record()
            self.events.append((start, end))
            return result

        return timed

    def milliseconds(self) -> list[float]:
        torch.cuda.synchronize()
        return [start.elapsed_time(end) for start, end in self.events]

    def summary(self) -> dict:
        ms = self.milliseconds()
        return {"calls": len(ms), "mean_ms": round(float(np.mean(ms)), 2) if ms else None,
                "seconds": round(sum(ms) / 1e3, 3)}


def build_first_tasks(env: LiberoVectorEnv, specs: list) -> None:
    """Reset each slot once with the episode it starts with, so no timed run pays the task build."""
    env.reset([specs[i] if i < len(specs) else None for i in range(env.num_envs)])
    for slot in range(env.num_envs):
        env.release(slot)


def measure(policy, env: LiberoVectorEnv, specs: list, max_steps: int, overlap: bool, min_batch: int = 1) -> dict:
    calls, waits, log = Meter(), Meter(), CallLog()
    real_act, real_collect = policy.act, env.collect
    policy.act = calls.wrap(log.wrap(real_act), items=lambda observations, generators: len(observations))
    env.collect = waits.wrap(real_collect)
    gpu = GpuMeter() if hasattr(policy, "_sample") and torch.cuda.is_available() else None
    if gpu:
        policy._sample = gpu.wrap(policy._sample)  # an instance attribute over the class's method
    records: list[dict] = []
    try:
        ticks = cpu_ticks(env.worker_pids)
        cpu0 = time.process_time()
        began = time.perf_counter()
        run_episodes(policy, env, specs, max_steps, on_finished=records.extend, overlap=overlap, min_batch=min_batch)
        wall = time.perf_counter() - began
        cpu = time.process_time() - cpu0
        cores = cores_used(ticks, cpu_ticks(env.worker_pids))
    finally:
        policy.act, env.collect = real_act, real_collect
        if gpu:
            del policy._sample
    steps = int(sum(r["steps"] for r in records))
    extra = {"policy_gpu": gpu.summary()} if gpu else {}
    return {**extra,
        "min_batch": min_batch,
        "busy_cores": cores.pop("busy"),
        "main_process_cores": round(cpu / wall, 2),
        "cores": cores,  # the machine's busy cores by kind (user, system, irq) and the workers' share
        "calls_by_graph_plan": log.summary(gpu.milliseconds() if gpu else None),
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
    parser.add_argument("--lockstep", type=int, nargs="*", default=[], help="N also measured without overlap")
    parser.add_argument("--min-batch", type=int, nargs="+", default=[1],
                        help="run_episodes' min_batch values measured at each N (the first is `policy`)")
    parser.add_argument("--latency-model", type=int, nargs="*", default=[],
                        help="N also driven by the sleeping stand-in for the policy (`latency_model`)")
    parser.add_argument("--bound-after", type=int, nargs="*", default=[],
                        help="N whose simulator bound is measured again after the policy runs")
    parser.add_argument("--replay-bound", type=int, nargs="*", default=[],
                        help="N whose every policy run is followed by a zero-cost run replaying its actions")
    parser.add_argument("--repeats", type=int, default=1,
                        help="policy runs per N of --bound-after, each followed by a bound run (ratio: the median)")
    parser.add_argument("--renice", type=int, default=None,
                        help="finally, the workers at this niceness (vs the worker's own) with the first min_batch (`policy_reniced`)")
    parser.add_argument("--torch-threads", type=int, default=1, help="intra-op threads of this process, as a cell's")
    parser.add_argument("--rounds", type=int, default=1, help="episodes per slot")
    parser.add_argument("--min-episodes", type=int, default=2)
    parser.add_argument("--max-steps", type=int, default=None, help="default: the suite's limit for pi0.5")
    parser.add_argument("--camera-size", type=int, default=256)
    parser.add_argument("--captures", type=int, nargs="*", default=None,
                        help="batch sizes run once before timing, capturing their plans' graphs (default: GRAPH_SIZES; "
                             "--latency-model needs every graph size its batches use)")
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
    sizes = sorted(GRAPH_SIZES if args.captures is None else args.captures)
    warmups = {b: warm_up(adapter, suite, args.camera_size, b) for b in sizes}
    # Once every size is captured, the whole `act` per size on the idle machine: the latency model's call times.
    for b in sizes:
        warmups[b]["call_ms"] = round(1e3 * float(np.median([stand_in_call(adapter, suite, args.camera_size, b)
                                                               for _ in range(3)])), 2)
    memory = None
    if on_cuda(adapter):
        # What the captures' uncaptured first runs left cached goes back to the driver: the workers'
        # EGL contexts need it (64 workers beside 115.9 GiB reserved could not create theirs).
        torch.cuda.empty_cache()
        memory = gpu_memory()
    print(f"policy load {load_s:.1f} s, first chunk per batch size (capture) {warmups}; after empty_cache {memory}",
          flush=True)
    zero_cost = ZeroCostPolicy(adapter.executed_chunk, adapter.predicted_chunk)
    latency_model = LatencyModelPolicy(adapter.executed_chunk, adapter.predicted_chunk,
                                       {b: w["call_ms"] / 1e3 for b, w in warmups.items()})

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
        warm = measure(adapter, env, episode_order(suite, 1), 2 * adapter.executed_chunk, overlap=True)
    result["simulator_warmup_s"] = warm["wall_s"]
    for n in args.num_envs:
        specs = episode_order(suite, max(n * args.rounds, args.min_episodes))
        began = time.perf_counter()
        with LiberoVectorEnv(suite, n, camera_size=args.camera_size) as env:
            build_first_tasks(env, specs)
            run = {"num_envs": n, "worker_startup_s": round(time.perf_counter() - began, 2)}

            def policy_and_replay() -> dict:
                """A policy run with the first min_batch; for N in --replay-bound, the replay of its chunks next."""
                if n not in args.replay_bound:
                    return {"policy": measure(adapter, env, specs, max_steps, overlap=True, min_batch=args.min_batch[0])}
                with ChunkRecorder(adapter) as recorder:
                    policy = measure(adapter, env, specs, max_steps, overlap=True, min_batch=args.min_batch[0])
                replay = ReplayPolicy(adapter.executed_chunk, adapter.predicted_chunk, recorder.chunks)
                replayed = measure(replay, env, specs, max_steps, overlap=True)
                replayed["same_actions"] = replayed["actions_sha256"] == policy["actions_sha256"]
                return {"policy": policy, "simulator_bound_replay": replayed}

            run["simulator_bound"] = measure(zero_cost, env, specs, max_steps, overlap=True)
            run |= policy_and_replay()
            by_min_batch = {args.min_batch[0]: run["policy"]} | {
                k: measure(adapter, env, specs, max_steps, overlap=True, min_batch=k) for k in args.min_batch[1:]}
            if len(by_min_batch) > 1:
                run["policy_by_min_batch"] = {str(k): v for k, v in by_min_batch.items()}
            if n in args.latency_model:
                run["latency_model"] = measure(latency_model, env, specs, max_steps, overlap=True)
            if n in args.lockstep:
                run["lockstep"] = measure(adapter, env, specs, max_steps, overlap=False)
            if n in args.bound_after:
                run["simulator_bound_after"] = measure(zero_cost, env, specs, max_steps, overlap=True)
                for _ in range(args.repeats - 1):
                    repeat = policy_and_replay()
                    repeat["simulator_bound"] = measure(zero_cost, env, specs, max_steps, overlap=True)
                    run.setdefault("repeats", []).append(repeat)
            if args.renice is not None:
                for pid in env.worker_pids:
                    os.setpriority(os.PRIO_PROCESS, pid, args.renice)
                run["policy_reniced"] = measure(adapter, env, specs, max_steps, overlap=True, min_batch=args.min_batch[0])
                run["policy_reniced"]["niceness"] = args.renice
        bounds = [run[k]["episodes_per_hour"] for k in ("simulator_bound", "simulator_bound_after") if k in run]
        bound = round(float(np.mean(bounds)), 1)
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
        for variant in [*run.get("policy_by_min_batch", {}).values(), run.get("policy_reniced"), run.get("latency_model")]:
            if variant:
                variant["vs_simulator_bound"] = round(variant["episodes_per_hour"] / bound, 3)
        if "lockstep" in run:
            run["overlap_vs_lockstep"] = round(run["policy"]["episodes_per_hour"] /
                                               run["lockstep"]["episodes_per_hour"], 3)
        result["runs"].append(run)
        print(f"num_envs={n}: policy {run['policy']['episodes_per_hour']} episodes/h "
              f"(batch {run['policy']['policy_call']['mean_items']}, {run['policy']['policy_call']['mean_ms']} ms/call, "
              f"GPU {run['policy'].get('policy_gpu', {}).get('mean_ms')} ms/call), "
              f"simulator bound {run['simulator_bound_episodes_per_hour']} ({' and '.join(map(str, bounds))}) -> {run['vs_simulator_bound']}"
              + (f"; lockstep {run['lockstep']['episodes_per_hour']}" if "lockstep" in run else ""), flush=True)
        if len(run["pairs"]) > 1:
            print(f"  pairs (policy, bounds before and after, ratio): {run['pairs']}", flush=True)
        if "replay_pairs" in run:
            print(f"  replaying each policy run's actions: {run['replay_pairs']} -> {run['vs_replay_bound']}", flush=True)
            if not all(pair["same_actions"] for pair in run["replay_pairs"]):
                print("  WARNING: a replay executed other actions than its policy run (same_actions false): "
                      "its ratio compares different episodes", flush=True)
        for label, variant in [*((f"min_batch {k}", v) for k, v in run.get("policy_by_min_batch", {}).items()),
                               *([("latency model", run["latency_model"])] if "latency_model" in run else []),
                               *([("workers reniced", run["policy_reniced"])] if "policy_reniced" in run else []),
                               ("simulator bound", run["simulator_bound"]),
                               *([("simulator bound after", run["simulator_bound_after"])] if "simulator_bound_after" in run else [])]:
            print(f"  {label}: {variant['episodes_per_hour']} episodes/h ({variant.get('vs_simulator_bound', 1.0)}), "
                  f"busy cores {variant['busy_cores']} {variant['cores']}, main process {variant['main_process_cores']}, "
                  f"calls {variant['policy_call']['calls']}, by graph plan {variant['calls_by_graph_plan']}", flush=True)
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

    print(f"\n{'N':>4}{'episodes':>9}{'eps/h':>9}{'bound eps/h':>12}{'ratio':>7}{'replay':>7}{'lockstep':>10}"
          f"{'batch':>7}{'call ms':>9}{'steps/s':>9}")
    for run in result["runs"]:
        policy = run["policy"]
        print(f"{run['num_envs']:>4}{policy['episodes']:>9}{policy['episodes_per_hour']:>9}"
              f"{run['simulator_bound_episodes_per_hour']:>12}{run['vs_simulator_bound']:>7}"
              f"{run.get('vs_replay_bound', '-'):>7}"
              f"{run.get('lockstep', {}).get('episodes_per_hour', '-'):>10}{policy['policy_call']['mean_items']:>7}"
              f"{policy['policy_call']['mean_ms']:>9}{policy['env_steps_per_s']:>9}")
    print(f"best: {result['best']}")
    print(f"camera {args.camera_size} px, {os.cpu_count()} cores, {gpu or args.device}, {result['machine']['versions']}")
    return Path(args.out)


if __name__ == "__main__":
    main()
