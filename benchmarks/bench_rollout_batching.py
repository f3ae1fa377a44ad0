"""Closed-loop episodes per minute with N batched LIBERO slots vs one slot at a time (CPU, demo pi0.5).

The same episodes (LIBERO-Spatial tasks 0-1, init states 0-1, a short step limit) run through
`runner.loop.run_episodes` with num_envs = 1 and N in one process, alternately, on one demo policy:
each slot's LIBERO worker steps in its own process while the policy handles the slots that need a
chunk in one batched call. Also checks that every episode's action digest is identical in both.

    .venv/bin/python benchmarks/bench_rollout_batching.py [--num-envs 2] [--steps 30] [--rounds 2]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import time
from pathlib import Path

import torch

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.runner.loop import run_episodes


def timed_run(adapter, suite, specs, num_envs: int, steps: int, camera_size: int) -> tuple[float, dict]:
    records: list[dict] = []
    with LiberoVectorEnv(suite, num_envs, camera_size=camera_size) as env:  # worker start-up not timed
        began = time.perf_counter()
        run_episodes(adapter, env, specs, steps, on_finished=records.extend)
        elapsed = time.perf_counter() - began
    return elapsed, {(r["task_id"], r["episode"]): r["actions_sha256"] for r in records}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--camera-size", type=int, default=128)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", default="benchmarks/results/rollout_batching_cpu.json")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    suite = LiberoSuite("libero_spatial")
    specs = [suite.episode_spec(task, episode) for task in (0, 1) for episode in (0, 1)]
    adapter = make_adapter(AdapterConfig(model="pi05", variant="demo"))
    adapter.load()
    single, batched = [], []
    for _ in range(args.rounds):
        t1, digests_1 = timed_run(adapter, suite, specs, 1, args.steps, args.camera_size)
        tn, digests_n = timed_run(adapter, suite, specs, args.num_envs, args.steps, args.camera_size)
        assert digests_1 == digests_n, "batched episodes executed different actions"
        single.append(t1)
        batched.append(tn)
    ratio = statistics.median(s / b for s, b in zip(single, batched))
    result = {
        "episodes": len(specs),
        "steps_per_episode": args.steps,
        "num_envs": args.num_envs,
        "seconds_num_envs_1": single,
        f"seconds_num_envs_{args.num_envs}": batched,
        "speedup_median": round(ratio, 3),
        "identical_actions": True,
        "cpus": os.cpu_count(),
        "torch_threads": args.threads,
        "load_average_at_end": os.getloadavg(),
        "machine": platform.platform(),
    }
    print(json.dumps(result, indent=2))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
