"""LIBERO env steps per second with 1 vs N worker processes, side by side in one run (CPU rendering).

    .venv/bin/python benchmarks/bench_libero_cpu.py [--workers 1 2] [--steps 30] [--camera-size 256]

Times only the `step()` loop after reset and settling (policy time excluded). Wall time depends on
what else runs on the machine, so the workers' CPU seconds per env step are reported beside it.
Writes `benchmarks/results/libero_cpu.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import numpy as np
import psutil

from vlaquantbench.envs.libero import LiberoSuite, LiberoVectorEnv

RESULTS = Path(__file__).resolve().parent / "results" / "libero_cpu.json"


def measure(suite: LiberoSuite, num_envs: int, steps: int, camera_size: int) -> dict:
    specs = [suite.episode_spec(task_id=slot, episode=0) for slot in range(num_envs)]
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.2, 0.2, size=(steps, num_envs, 7))
    actions[..., 6] = -1.0
    with LiberoVectorEnv(suite, num_envs, camera_size=camera_size) as env:
        started = time.perf_counter()
        env.reset(specs)
        reset_s = time.perf_counter() - started
        workers = [psutil.Process(pid) for pid in env.worker_pids]
        cpu_before = sum(sum(w.cpu_times()[:2]) for w in workers)
        started = time.perf_counter()
        for action in actions:
            env.step(action)
        step_s = time.perf_counter() - started
        worker_cpu_s = sum(sum(w.cpu_times()[:2]) for w in workers) - cpu_before
    return {
        "num_envs": num_envs,
        "steps": steps,
        "first_reset_s": round(reset_s, 2),
        "batched_step_s": round(step_s / steps, 4),
        "env_steps_per_s": round(num_envs * steps / step_s, 3),
        "worker_cpu_s_per_env_step": round(worker_cpu_s / (num_envs * steps), 4),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--workers", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--camera-size", type=int, default=256)
    parser.add_argument("--suite", default="libero_spatial")
    args = parser.parse_args()

    suite = LiberoSuite(args.suite)
    load_before = os.getloadavg()
    runs = [measure(suite, n, args.steps, args.camera_size) for n in args.workers]
    base = runs[0]["env_steps_per_s"]
    for run in runs:
        run["speedup_vs_first"] = round(run["env_steps_per_s"] / base, 2)
        print(
            f"{run['num_envs']} worker(s): {run['env_steps_per_s']:.2f} env steps/s "
            f"({run['batched_step_s'] * 1000:.0f} ms per batched step, "
            f"{run['worker_cpu_s_per_env_step'] * 1000:.0f} worker CPU ms per env step), x{run['speedup_vs_first']:.2f}"
        )
    report = {
        "what": "LIBERO env steps/s (simulation + 2 camera renders, no policy), CPU EGL rendering",
        "suite": args.suite,
        "camera_size": args.camera_size,
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "load_average_before": [round(x, 2) for x in load_before],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
        "runs": runs,
    }
    RESULTS.parent.mkdir(parents=True, exist_ok=True)
    RESULTS.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {RESULTS}")


if __name__ == "__main__":
    main()
