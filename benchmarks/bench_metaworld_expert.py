"""Meta-World's scripted experts through the batched env and the closed-loop runner: episodes per hour.

    .venv/bin/python benchmarks/bench_metaworld_expert.py [--workers 2] [--suite metaworld_easy]
        [--tasks 6] [--episodes 4] [--camera-size 0]

The `metaworld_expert` adapter drives `--episodes` episodes of each of the suite's first `--tasks`
tasks through `runner.loop.run_episodes` with `--workers` worker processes, rendering no image
(`--camera-size 0`, what the experts read) or one `corner2` image per step (`--camera-size N`, what
an image policy reads). This is Meta-World's simulator-only speed: the experts cost microseconds per
action. Wall time depends on what else runs on the machine, so the load average is recorded beside
it. Writes `benchmarks/results/metaworld_expert_cpu.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

from vlaquantbench.envs import make_env, make_suite
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.runner.loop import run_episodes

RESULTS = Path(__file__).resolve().parent / "results" / "metaworld_expert_cpu.json"


def measure(suite_name: str, tasks: int, episodes: int, workers: int, camera_size: int) -> dict:
    suite = make_suite("metaworld", suite_name)
    specs = suite.episodes(episodes, task_ids=list(range(min(tasks, suite.n_tasks))))
    adapter = make_adapter(AdapterConfig(model="metaworld_expert", variant="full"))
    adapter.load()
    records: list[dict] = []
    started = time.perf_counter()
    with make_env("metaworld", suite, workers, camera_size=camera_size or None) as env:
        ready = time.perf_counter()
        run_episodes(adapter, env, specs, suite.step_limit, records.extend)
    finished = time.perf_counter()
    steps = sum(r["steps"] for r in records)
    per_task = {}
    for record in records:
        outcome = per_task.setdefault(record["task_name"], {"episodes": 0, "successes": 0})
        outcome["episodes"] += 1
        outcome["successes"] += record["success"]
    return {
        "suite": suite_name,
        "workers": workers,
        "camera_size": camera_size or None,
        "episodes": len(records),
        "success_rate": round(sum(r["success"] for r in records) / len(records), 3),
        "steps": steps,
        "worker_start_s": round(ready - started, 2),
        "episodes_s": round(finished - ready, 2),
        "episodes_per_hour": round(len(records) / (finished - ready) * 3600),
        "episodes_per_hour_with_start": round(len(records) / (finished - started) * 3600),
        "env_steps_per_s": round(steps / (finished - ready), 1),
        "per_task": per_task,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--suite", default="metaworld_easy")
    parser.add_argument("--tasks", type=int, default=6)
    parser.add_argument("--episodes", type=int, default=4)
    parser.add_argument("--camera-size", type=int, nargs="+", default=[0])
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    host = {"cpus": os.cpu_count(), "machine": platform.machine(), "load_avg_before": os.getloadavg()}
    runs = [measure(args.suite, args.tasks, args.episodes, args.workers, size) for size in args.camera_size]
    result = {"host": {**host, "load_avg_after": os.getloadavg()}, "runs": runs}
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
