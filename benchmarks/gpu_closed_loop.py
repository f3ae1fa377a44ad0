"""Closed-loop episodes per hour for one LIBERO cell: the batched runner vs one environment at a time.

One process, one policy (pi0.5 at full size with seeded random weights, bf16, the captured sampler),
the real runner pieces (`LiberoVectorEnv` workers, `runner.loop.run_episodes`), no quantization
unless `--preset`. First S episodes with num_envs=1, then M episodes with num_envs=N for each N.
Episodes go task by task within each init state (tasks 0-9 of init state 0, then of init state 1,
...), so both runs meet every task (and a worker rebuilds its environment at nearly every
episode; a real cell runs a task's episodes one after another). Random weights never succeed:
every episode runs to the step limit (the suite's, or `--max-steps`). Worker start-up, the first
capture of each batch size and one short simulator warm-up episode (numba compiles) are timed
apart and excluded from episodes per hour.

    python benchmarks/gpu_closed_loop.py                         # GPU: cuda, random, bf16
    python benchmarks/gpu_closed_loop.py --num-envs 16 32 --batched-episodes 64
    .venv/bin/python benchmarks/gpu_closed_loop.py --device cpu --variant demo --dtype float32 \\
        --sequential-episodes 1 --batched-episodes 2 --num-envs 2 --max-steps 20 --camera-size 64 \\
        --out /tmp/closed_loop_cpu.json                          # CPU smoke run
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import torch
import transformers

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.runner.loop import run_episodes
from vlaquantbench.runner.provenance import versions


class Meter:
    """Calls, items and seconds of one wrapped method (the runner calls it; we only count)."""

    def __init__(self):
        self.calls, self.items, self.seconds = 0, 0, 0.0

    def wrap(self, fn, items=lambda *args: 1):
        def timed(*args):
            began = time.perf_counter()
            result = fn(*args)
            self.seconds += time.perf_counter() - began
            self.calls += 1
            self.items += items(*args)
            return result

        return timed

    def summary(self) -> dict:
        return {
            "calls": self.calls,
            "seconds": round(self.seconds, 3),
            "mean_ms": round(1e3 * self.seconds / self.calls, 2) if self.calls else None,
            "mean_items": round(self.items / self.calls, 2) if self.calls else None,
        }


def episode_order(suite: LiberoSuite, count: int) -> list:
    per_task = -(-count // suite.n_tasks)
    return [suite.episode_spec(t, e) for e in range(per_task) for t in range(suite.n_tasks)][:count]


def warm_up(adapter, suite: LiberoSuite, camera_size: int, batch: int) -> float:
    """One chunk at `batch` on stand-in observations: captures that batch size's graph."""
    blank = np.zeros((camera_size, camera_size, 3), np.uint8)
    obs = {"agentview": blank, "wrist": blank, "state": np.zeros(8, np.float32),
           "instruction": suite.tasks[0].instruction}
    began = time.perf_counter()
    adapter.act([obs] * batch, [adapter.reset(i) for i in range(batch)])
    return time.perf_counter() - began


def measure(adapter, suite, num_envs: int, episodes: int, max_steps: int, camera_size: int) -> dict:
    specs = episode_order(suite, episodes)
    began = time.perf_counter()
    env = LiberoVectorEnv(suite, num_envs, camera_size=camera_size)
    startup = time.perf_counter() - began
    policy, steps, resets = Meter(), Meter(), Meter()
    real_act = adapter.act
    adapter.act = policy.wrap(real_act, items=lambda observations, generators: len(observations))
    env.step = steps.wrap(env.step, items=lambda actions: sum(env.live))
    env.reset = resets.wrap(env.reset, items=lambda slots: sum(s is not None for s in slots))
    records: list[dict] = []
    try:
        began = time.perf_counter()
        run_episodes(adapter, env, specs, max_steps, on_finished=records.extend)
        wall = time.perf_counter() - began
    finally:
        adapter.act = real_act
        env.close()
    run = {
        "num_envs": num_envs,
        "episodes": len(records),
        "policy_steps": int(sum(r["steps"] for r in records)),
        "successes": int(sum(r["success"] for r in records)),
        "worker_startup_s": round(startup, 2),
        "wall_s": round(wall, 2),
        "episodes_per_hour": round(3600 * len(records) / wall, 1),
        "policy_chunk": policy.summary(),  # mean_items = mean batch of a chunk call
        "env_step": steps.summary(),  # one call steps every live slot in parallel
        "env_reset": resets.summary(),
    }
    print(f"num_envs={num_envs}: {run['episodes']} episodes in {wall:.1f} s -> {run['episodes_per_hour']} episodes/h "
          f"(policy {run['policy_chunk']['mean_ms']} ms/chunk call, env step {run['env_step']['mean_ms']} ms)",
          flush=True)
    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--suite", default="libero_spatial")
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--variant", default="random", choices=["random", "demo"])
    parser.add_argument("--dtype", default="bfloat16")
    parser.add_argument("--sampler", default="captured", choices=["captured", "eager"])
    parser.add_argument("--preset", default=None, help="e.g. W4A4: end-to-end fake quantization via quantize_")
    parser.add_argument("--sequential-episodes", type=int, default=4, help="S, run with num_envs=1")
    parser.add_argument("--batched-episodes", type=int, default=None, help="M per batched run (default 2 x num_envs)")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[16])
    parser.add_argument("--max-steps", type=int, default=None, help="default: the suite's limit for pi0.5")
    parser.add_argument("--camera-size", type=int, default=256)
    parser.add_argument("--out", default="benchmarks/results/closed_loop_gpu.json")
    args = parser.parse_args()

    suite = LiberoSuite(args.suite)
    max_steps = args.max_steps or suite.max_steps("pi05")
    began = time.perf_counter()
    adapter = make_adapter(AdapterConfig(model="pi05", variant=args.variant, device=args.device, dtype=args.dtype,
                                         sampler=args.sampler))
    adapter.load()
    load_s = time.perf_counter() - began
    report, quant_header = None, None
    if args.preset:
        from vlaquantbench.quant import QuantConfig, quantize_

        report = quantize_(adapter.model, QuantConfig.from_preset(args.preset, scope="e2e"),
                           components=adapter.components)
        quant_header = report.to_header()["quant_report"]
    inference = adapter.prepare_inference(report)
    warmups = {b: round(warm_up(adapter, suite, args.camera_size, b), 2) for b in sorted({1, *args.num_envs})}
    print(f"policy load {load_s:.1f} s, first chunk per batch size (capture) {warmups}", flush=True)

    # One short untimed episode first: robosuite's numba kernels compile (and cache) on first use,
    # which would otherwise fall on the first timed run only.
    simulator_warmup = measure(adapter, suite, 1, 1, 2 * adapter.executed_chunk, args.camera_size)
    sequential = measure(adapter, suite, 1, args.sequential_episodes, max_steps, args.camera_size)
    batched = [measure(adapter, suite, n, args.batched_episodes or 2 * n, max_steps, args.camera_size)
               for n in args.num_envs]
    for run in batched:
        run["episodes_per_hour_vs_sequential"] = round(run["episodes_per_hour"] / sequential["episodes_per_hour"], 2)

    hooks = None
    if report is not None:
        hooks = {key: report.to_header()["hooks"][key] for key in ("selected", "fired")}
    gpu = torch.cuda.get_device_name() if torch.device(args.device).type == "cuda" else None
    result = {
        "suite": args.suite,
        "model": "pi05",
        "variant": args.variant,
        "dtype": args.dtype,
        "preset": args.preset or "BASELINE",
        "quant_report": quant_header,
        "hooks": hooks,  # fused into the captured graph on CUDA, where Python hooks no longer fire
        "inference": inference,
        "max_steps": max_steps,
        "executed_chunk": adapter.executed_chunk,
        "camera_size": args.camera_size,
        "policy_load_s": round(load_s, 2),
        "first_chunk_s_by_batch": warmups,
        "simulator_warmup_s": round(simulator_warmup["worker_startup_s"] + simulator_warmup["wall_s"], 2),
        "batched_vs_sequential_episodes_per_hour": max(r["episodes_per_hour_vs_sequential"] for r in batched),
        "sequential": sequential,
        "batched": batched,
        "machine": {
            "device": args.device,
            "gpu": gpu,
            "cpus": os.cpu_count(),
            "platform": platform.platform(),
            "versions": {**versions(), "transformers": transformers.__version__},
            "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        },
    }
    print(f"\n{'runner':<14}{'episodes':>9}{'wall s':>9}{'episodes/h':>12}{'ratio':>7}"
          f"{'chunk ms':>10}{'batch':>7}{'step ms':>9}{'start s':>9}")
    for name, run in [("sequential", sequential)] + [(f"batched x{r['num_envs']}", r) for r in batched]:
        print(f"{name:<14}{run['episodes']:>9}{run['wall_s']:>9}{run['episodes_per_hour']:>12}"
              f"{run.get('episodes_per_hour_vs_sequential', 1.0):>7}{run['policy_chunk']['mean_ms']:>10}"
              f"{run['policy_chunk']['mean_items']:>7}{run['env_step']['mean_ms']:>9}{run['worker_startup_s']:>9}")
    print(f"camera {args.camera_size} px, {os.cpu_count()} cores, {gpu or args.device}, {result['machine']['versions']}")
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
