"""Soak: `kill -9` a running demo cell again and again at seeded random moments, then let it finish;
count lost and duplicated episodes and check the resumed records against an uninterrupted run.

    .venv/bin/python benchmarks/soak_kill9.py --kills 20 --out benchmarks/results/soak_kill9_cpu.json
    .venv/bin/python benchmarks/soak_kill9.py --kills 2 --tasks 0 --episodes-per-task 3 --max-steps 10  # CI's

Each attempt runs `runner.cell.run_cell` in a fresh process group (the runner and its LIBERO
workers). A seeded RNG picks, per attempt, when the whole group gets SIGKILL: with probability
`--startup-kill-p` at a uniform moment of the first `--startup-window` seconds after launch (policy
load, quantization, worker start-up), otherwise at a uniform moment of the `--window` seconds after
the attempt's first new journal line (mid-episode, mid-reset, mid-append). After the last kill the
cell runs to completion. Reported: kills that landed, episodes lost (in the uninterrupted run but
not in the resumed one) and duplicated (journal lines for an episode already recorded), whether
`episodes.parquet` ever appeared before the cell was complete, and whether every episode's outcome,
step count and action digest and the records themselves (timing columns aside) equal the
uninterrupted run's.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

from vlaquantbench.cells import cell_config
from vlaquantbench.records import read_cell
from vlaquantbench.runner.cell import JOURNAL

RUN_CELL = ("import json, sys; from vlaquantbench.runner.cell import run_cell; "
            "run_cell(json.loads(sys.argv[1]), sys.argv[2], num_envs=int(sys.argv[3]), progress=False)")
TIMING = ["wall_time_s", "policy_batch_latency_mean_s"]
KEY = ("task_id", "episode", "seed")


def journal_lines(folder: Path) -> list[dict]:
    path = folder / JOURNAL
    if not path.exists():
        return []
    return [json.loads(line) for line in path.read_bytes().split(b"\n")[:-1] if line]  # a torn last line is no line


def journal_episodes(folder: Path) -> list[dict]:
    return [r for r in journal_lines(folder) if r["kind"] == "episode"]


def launch(cfg: dict, folder: Path, num_envs: int) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-c", RUN_CELL, json.dumps(cfg), str(folder), str(num_envs)],
                            start_new_session=True, stderr=subprocess.DEVNULL)


def complete(cfg: dict, folder: Path, num_envs: int) -> float:
    began = time.monotonic()
    process = launch(cfg, folder, num_envs)
    if process.wait():
        raise RuntimeError(f"the cell in {folder} failed (exit {process.returncode})")
    return time.monotonic() - began


def soak(cfg: dict, folder: Path, args: argparse.Namespace) -> list[dict]:
    rng = random.Random(args.seed)
    kills = []
    while len(kills) < args.kills:
        before = len(journal_episodes(folder))
        during_startup = rng.random() < args.startup_kill_p
        delay = rng.uniform(0, args.startup_window if during_startup else args.window)
        launched = time.monotonic()
        process = launch(cfg, folder, args.num_envs)
        if not during_startup:  # count from the attempt's first new journal line (the header, at first)
            lines = len(journal_lines(folder))
            while len(journal_lines(folder)) == lines and process.poll() is None:
                time.sleep(0.05)
        time.sleep(max(0.0, launched + delay - time.monotonic()) if during_startup else delay)
        if process.poll() is not None:
            raise RuntimeError("the cell finished before its kills were done: give it more episodes")
        os.killpg(process.pid, signal.SIGKILL)
        process.wait()
        kills.append({
            "phase": "startup" if during_startup else "running",
            "at_s": round(time.monotonic() - launched, 2),
            "episodes_before": before,
            "episodes_after": len(journal_episodes(folder)),
            "parquet_present": (folder / "episodes.parquet").exists(),
        })
        print(f"kill {len(kills)}/{args.kills}: {kills[-1]}", flush=True)
    return kills


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ref", default="libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn")
    parser.add_argument("--tasks", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--episodes-per-task", type=int, default=10)
    parser.add_argument("--max-steps", type=int, default=20)
    parser.add_argument("--num-envs", type=int, default=2)
    parser.add_argument("--kills", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0, help="the RNG that times the kills")
    parser.add_argument("--window", type=float, default=15.0, help="seconds after an attempt's first new episode")
    parser.add_argument("--startup-window", type=float, default=20.0, help="seconds after launch")
    parser.add_argument("--startup-kill-p", type=float, default=0.2)
    parser.add_argument("--out", default=None, help="JSON result (default: print only)")
    args = parser.parse_args()

    study = {
        "models": {"pi05": {"variant": "demo", "checkpoint": "lerobot/pi05_libero_finetuned_v044"}},
        "tasks": args.tasks,
        "episodes_per_task": args.episodes_per_task,
        "runner": {"max_steps": args.max_steps, "camera_size": 64, "flow_steps": 2},
    }
    cfg = cell_config(args.ref, study)
    with tempfile.TemporaryDirectory(prefix="vqb-soak-") as tmp:
        reference, killed = Path(tmp) / "reference", Path(tmp) / "killed"
        reference_s = complete(cfg, reference, args.num_envs)
        began = time.monotonic()
        kills = soak(cfg, killed, args)
        final_s = complete(cfg, killed, args.num_envs)
        soak_s = time.monotonic() - began

        lines = journal_episodes(killed)
        outcome = {tuple(r[k] for k in KEY): (r["success"], r["steps"], r["actions_sha256"]) for r in lines}
        expected = {tuple(r[k] for k in KEY): (r["success"], r["steps"], r["actions_sha256"])
                    for r in journal_episodes(reference)}
        counts = Counter(tuple(r[k] for k in KEY) for r in lines)
        resumed, uninterrupted = read_cell(killed), read_cell(reference)
        records_equal = resumed.episodes.drop(columns=TIMING).equals(uninterrupted.episodes.drop(columns=TIMING))
        result = {
            "cell": args.ref,
            "episodes": len(expected),
            "kills": len(kills),
            "kills_running": sum(k["phase"] == "running" for k in kills),
            "kills_startup": sum(k["phase"] == "startup" for k in kills),
            "lost_episodes": len(expected.keys() - outcome.keys()),
            "duplicated_episodes": sum(n - 1 for n in counts.values()),
            "parquet_before_complete": any(k["parquet_present"] for k in kills),
            "outcomes_and_digests_equal": outcome == expected,
            "records_equal_but_timing": bool(records_equal),
            "headers_equal": resumed.header == uninterrupted.header,
            "reference_s": round(reference_s, 1),
            "soak_s": round(soak_s, 1),
            "final_resume_s": round(final_s, 1),
            "settings": {k: v for k, v in vars(args).items() if k != "out"},
            "kill_log": kills,
            "machine": {
                "cpus": os.cpu_count(),
                "platform": platform.platform(),
                "date_utc": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            },
        }
    print(json.dumps({k: v for k, v in result.items() if k != "kill_log"}, indent=1))
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
