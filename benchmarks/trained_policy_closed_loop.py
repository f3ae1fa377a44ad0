"""Closed-loop success of the policy trained here (rule train_policy) on Meta-World, per task.

    .venv/bin/python benchmarks/trained_policy_closed_loop.py [--home checkpoints/pi05_metaworld]
        [--tasks drawer-close-v3 ...] [--episodes 5] [--first-variation 0] [--workers 2] [--device cpu]

Loads the checkpoint from the HF_HOME folder `--home` through the rollout path (the pi0.5 adapter's
released-checkpoint loader, offline, at the revision training.json names), and runs `--episodes`
episodes of each task through `runner.loop.run_episodes` with Meta-World's batched env rendering the
`corner2` camera at the checkpoint's input size. Episode e starts from task variation
`--first-variation + e`: variations below the demonstrations' `first_variation` (500) are ones the
demonstrations never used. The policy executes the `n_action_steps` it was trained with of each
predicted chunk. Writes `--out` (JSON: success per task, wall time, the checkpoint's revision).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from vlaquantbench.envs import make_env, make_suite
from vlaquantbench.hub.cache import offline_cache, repo_folder
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.runner.loop import run_episodes

RESULTS = Path(__file__).resolve().parent / "results" / "trained_policy_closed_loop.json"


def evaluate(home: Path, suite_name: str, tasks: list[str], episodes: int, first_variation: int, workers: int,
             device: str, flow_steps: int) -> dict:
    training = json.loads((home / "training.json").read_text())
    snapshot = repo_folder(home / "hub", training["checkpoint"]) / "snapshots" / training["revision"]
    adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint=training["checkpoint"],
                                         revision=training["revision"], checkpoint_dir=str(snapshot), device=device, dtype="float32",
                                         executed_chunk=training["policy"]["n_action_steps"], flow_steps=flow_steps))
    with offline_cache(home):
        adapter.load()
    suite = make_suite("metaworld", suite_name)
    task_ids = [suite.task_id(name) for name in tasks]
    specs = [suite.episode_spec(t, first_variation + e) for t in task_ids for e in range(episodes)]
    records: list[dict] = []
    started = time.perf_counter()
    with make_env("metaworld", suite, workers, camera_size=adapter.policy_config.image_resolution[0]) as env:
        run_episodes(adapter, env, specs, suite.step_limit, records.extend)
    per_task: dict[str, dict] = {}
    for record in records:
        outcome = per_task.setdefault(record["task_name"], {"episodes": 0, "successes": 0})
        outcome["episodes"] += 1
        outcome["successes"] += record["success"]
    return {
        "checkpoint": training["checkpoint"], "revision": training["revision"], "device": device,
        "suite": suite_name, "variations": [first_variation, first_variation + episodes - 1],
        "executed_chunk": adapter.executed_chunk, "flow_steps": flow_steps,
        "episodes": len(records), "success_rate": round(sum(r["success"] for r in records) / len(records), 3),
        "per_task": per_task, "wall_s": round(time.perf_counter() - started, 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--home", type=Path, default=Path("checkpoints/pi05_metaworld"))
    parser.add_argument("--suite", default="metaworld_mt50")
    parser.add_argument("--tasks", nargs="+", default=["drawer-close-v3", "button-press-topdown-v3", "door-open-v3"])
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--first-variation", type=int, default=0)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--flow-steps", type=int, default=10)
    parser.add_argument("--out", type=Path, default=RESULTS)
    args = parser.parse_args()
    result = evaluate(args.home, args.suite, args.tasks, args.episodes, args.first_variation, args.workers,
                      args.device, args.flow_steps)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
