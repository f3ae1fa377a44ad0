"""Closed-loop success of the policy trained here (rule train_policy) on Meta-World, per task.

    .venv/bin/python benchmarks/trained_policy_closed_loop.py [--home checkpoints/pi05_metaworld]
        [--tasks drawer-close-v3 ...] [--episodes 5] [--first-variation 0] [--workers 2] [--device cpu]
        [--max-steps 500] [--preset W2 --scope e2e]

Loads the checkpoint from its folder `--home` through the rollout path (verified against its training.json, at
the revision it names) and runs `--episodes` episodes of each task through `runner.loop.run_episodes`, the
`corner2` camera at the checkpoint's input size, executing the `n_action_steps` it was trained with. Episode e
starts from variation `--first-variation + e`; variations the demonstrations recorded are refused (their range
from the config whose `training.output` is `--home`). `--max-steps` (default 500, the suite's limit) ends an
episode sooner as a failure (the experts need 32-93 steps). `--preset` quantizes first (round-to-nearest over
`--scope`, as cell `rtn-<preset>-<scope>`). Writes `--out` (success per task with a task-clustered 95% interval,
wall time, revision) and, with `--records`, each episode's record as it ends.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import torch
import yaml

from vlaquantbench.config import integer_option, load_workflow_config
from vlaquantbench.demonstrations import DemonstrationConfig
from vlaquantbench.demonstrations.overlap import VariationRange, check_disjoint, demonstrated_range
from vlaquantbench.envs import check_step_limit, make_env, make_suite
from vlaquantbench.errors import UserError
from vlaquantbench.models.trained_home import policy_folder
from vlaquantbench.models.adapter import AdapterConfig, make_adapter
from vlaquantbench.quant import QuantConfig, quantize_
from vlaquantbench.runner.loop import run_episodes

RESULTS = Path(__file__).resolve().parent / "results" / "trained_policy_closed_loop.json"
ROOT = Path(__file__).resolve().parents[1]
AT_LEAST_ONE, AT_LEAST_ZERO = integer_option({"minimum": 1}), integer_option({"minimum": 0})


def training_demonstrations(home: Path) -> tuple[DemonstrationConfig, Path]:
    """The demonstrations the checkpoint in `home` was trained on: the `demonstrations` section of the workflow
    config (config/*.yaml) whose `training.output` is `home`, and that config."""
    for path in sorted((ROOT / "config").glob("*.yaml")):
        raw = yaml.safe_load(path.read_text()) or {}
        output = (raw.get("training") or {}).get("output")
        if output and (ROOT / output).resolve() == home.resolve() and "demonstrations" in raw:
            config = load_workflow_config(path, ROOT / "config" / "config.yaml")
            return DemonstrationConfig.from_dict(config["demonstrations"], where=str(path)), path.resolve()
    raise UserError(f"no config/*.yaml trains {home} (its training.output), so the demonstrations' variations are unknown")


def check_arguments(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """Refuse, before the policy loads, a task the suite lacks, steps past Meta-World's limit and variations the
    demonstrations recorded, naming the argument (argparse's usage error)."""
    try:
        suite = make_suite("metaworld", args.suite)
        for task_id in map(suite.task_id, args.tasks):
            suite.episode_spec(task_id, args.first_variation + args.episodes - 1)
    except UserError as err:
        parser.error(f"argument --suite/--tasks/--first-variation: {err}")
    if args.max_steps is not None:
        try:
            check_step_limit("argument --max-steps", args.max_steps, "metaworld", args.suite)
        except UserError as err:
            parser.error(str(err))
    try:
        demonstrations, config = training_demonstrations(args.home)
    except UserError as err:
        parser.error(f"argument --home: {err}")
    evaluated = VariationRange(args.first_variation, args.first_variation + args.episodes - 1,
                               f"--first-variation {args.first_variation}, --episodes {args.episodes}")
    try:
        check_disjoint(demonstrated_range(demonstrations), [evaluated], "--first-variation")
    except UserError as err:
        parser.error(f"argument --first-variation: {err} ({config.relative_to(ROOT)})")

def evaluate(home: Path, suite_name: str, tasks: list[str], episodes: int, first_variation: int, workers: int,
             device: str, flow_steps: int, max_steps: int | None = None, preset: str | None = None,
             scope: str = "e2e", records_file: Path | None = None) -> dict:
    if device == "cpu":
        # One intra-op thread: this policy's ops are tiny (10 x 32 matmuls), and on a loaded 2-core machine
        # each op's second OpenMP thread waits for a core, ~2 ms an op: 4.5 s a chunk against 0.25 s with
        # one thread (benchmarks/results/trained_cpu/README.md). The simulator runs in its own processes.
        torch.set_num_threads(1)
    training = json.loads((home / "training.json").read_text())
    adapter = make_adapter(AdapterConfig(model="pi05", variant="full", checkpoint=training["checkpoint"],
                                         revision=training["revision"], checkpoint_dir=str(policy_folder(home)), device=device,
                                         dtype="float32", executed_chunk=training["policy"]["n_action_steps"],
                                         flow_steps=flow_steps))
    adapter.load()
    quantized = None
    if preset is not None:
        quant = QuantConfig.from_preset(preset, scope=scope)
        report = quantize_(adapter.model, quant, quant.select(adapter.model, adapter.components))
        adapter.prepare_inference(report)
        quantized = {"preset": preset, "scope": scope, "method": "rtn", "selected_layers": report.to_header()["selected_layers"],
                     "quant_report": report.to_header()["quant_report"]}
    suite = make_suite("metaworld", suite_name)
    task_ids = [suite.task_id(name) for name in tasks]
    specs = [suite.episode_spec(t, first_variation + e) for t in task_ids for e in range(episodes)]
    max_steps = suite.step_limit if max_steps is None else max_steps
    records: list[dict] = []

    def finished(batch: list[dict]) -> None:
        records.extend(batch)
        if records_file is not None:  # each episode as it ends: a run cut short keeps what it finished
            with open(records_file, "a") as f:
                f.writelines(json.dumps(r) + "\n" for r in batch)

    started = time.perf_counter()
    with make_env("metaworld", suite, workers, camera_size=adapter.policy_config.image_resolution[0]) as env:
        run_episodes(adapter, env, specs, max_steps, finished)
    per_task: dict[str, dict] = {}
    for record in records:
        outcome = per_task.setdefault(record["task_name"], {"episodes": 0, "successes": 0})
        outcome["episodes"] += 1
        outcome["successes"] += record["success"]
    return {
        "checkpoint": training["checkpoint"], "revision": training["revision"], "device": device,
        "quantized": quantized,
        "suite": suite_name, "variations": [first_variation, first_variation + episodes - 1],
        "executed_chunk": adapter.executed_chunk, "flow_steps": flow_steps, "max_steps": max_steps,
        "episodes": len(records), "success_rate": round(sum(r["success"] for r in records) / len(records), 3),
        "success_ci95_task_clustered": _clustered_interval(records),
        "per_task": per_task, "wall_s": round(time.perf_counter() - started, 1),
        "outcomes": [{"task": r["task_name"], "variation": r["init_state_id"], "success": r["success"], "steps": r["steps"]}
                     for r in sorted(records, key=lambda r: (r["task_id"], r["init_state_id"]))],
    }


def _clustered_interval(records: list[dict]) -> list[float] | None:
    """The success rate's task-clustered bootstrap 95% interval (`stats.task_clustered_mean`: tasks, then each
    task's episodes, resampled), in percent; None for one task."""
    import pandas as pd

    from vlaquantbench.stats import task_clustered_mean

    episodes = pd.DataFrame({"task_id": [r["task_id"] for r in records], "success": [float(r["success"]) for r in records]})
    if episodes["task_id"].nunique() < 2:
        return None
    interval = task_clustered_mean(episodes, "success")
    return [round(100 * interval.low, 1), round(100 * interval.high, 1)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--home", type=Path, default=Path("checkpoints/pi05_metaworld"))
    parser.add_argument("--suite", default="metaworld_mt50")
    parser.add_argument("--tasks", nargs="+", default=["drawer-close-v3", "button-press-topdown-v3", "door-open-v3"])
    parser.add_argument("--episodes", type=AT_LEAST_ONE, default=5)
    parser.add_argument("--first-variation", type=AT_LEAST_ZERO, default=0)
    parser.add_argument("--workers", type=AT_LEAST_ONE, default=2)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--flow-steps", type=AT_LEAST_ONE, default=10)
    parser.add_argument("--max-steps", type=AT_LEAST_ONE, default=None)
    parser.add_argument("--preset", default=None, help="e.g. W2, W4A4 (default: full precision)")
    parser.add_argument("--scope", default="e2e", help="component scope of --preset: e2e, ve, llm or ah")
    parser.add_argument("--out", type=Path, default=RESULTS)
    parser.add_argument("--records", type=Path, default=None, help="JSONL file each finished episode's record is appended to")
    args = parser.parse_args()
    check_arguments(parser, args)
    result = evaluate(args.home, args.suite, args.tasks, args.episodes, args.first_variation, args.workers,
                      args.device, args.flow_steps, args.max_steps, args.preset, args.scope, args.records)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
