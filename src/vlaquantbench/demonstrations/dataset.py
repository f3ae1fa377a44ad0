"""A benchmark's scripted expert recorded as a LeRobotDataset: what the trained policy learns from. The
benchmark (`demonstrations.benchmark`) declares its expert and what the dataset holds
(`envs.registry.ScriptedExpert`); one without an expert is refused when the config is read.

`write_demonstrations(config, out_dir, workers)` writes under `out_dir`:
  - `dataset/`: a LeRobotDataset (lerobot 0.6.1's `LeRobotDataset.create` / `add_frame` /
    `save_episode`, local, no hub) with the features a one-camera lerobot env gives a policy:
    `observation.image` (the benchmark's main camera at `image_size` pixels, as the closed loop renders it),
    `observation.state`, `action` (the expert's, clipped to lerobot's action space [-1, 1]), their components
    named as the benchmark declares them, and
    the task's instruction as each frame's `task`. Images are stored as PNG inside the
    parquet files (`use_videos=False`): no video codec is needed to write or read them, and a frame
    reads back exactly as rendered.
  - `demonstrations.json`: the settings, the versions, and per task every attempted episode: its
    variation, the variation's seed, the object and goal placement it drew, success, steps, and
    the dataset episode it became (null: not kept).
  - `manifest.tsv`: the SHA-256 of every file above (`manifest.write_file_manifest`).

Episodes: the expert acts through the closed-loop runner (`runner.loop.run_episodes`) on the
benchmark's vector env, so a demonstration sees what an evaluated policy sees. Task variation v of a
task is drawn from the suite's `variation_seed(task, v)`; closed-loop evaluation episode e starts from
variation e (the suite's `episode_spec`), so the demonstrations take variations from `first_variation` on
(default 500), and `overlap.check_disjoint_from_evaluation` refuses a config that would evaluate
or calibrate on one of them. Only successful episodes are kept: a task gets attempts on consecutive
variations until `episodes_per_task` succeed (each round tries as many as are still missing), so the kept episodes
are the first successes in variation order whatever the number of workers, and the dataset's
episodes are in a fixed order (round, task, variation).

Writing is parallel: each worker process records blocks of one task's variations into a
LeRobotDataset of its own (lerobot's writer encodes PNGs and computes image statistics there, beside
its simulator), and lerobot's `aggregate_datasets` merges them in that fixed order
(benchmarks/results/gpu_demonstrations_h200/ holds a measured rate).
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
import os
import subprocess
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from vlaquantbench.config import validate
from vlaquantbench.envs import BENCHMARK_SUITES, check_step_limit
from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.registry import ScriptedExpert, get_benchmark
from vlaquantbench.errors import UserError, lookup
from vlaquantbench.models.client import step_limit as model_step_limit

log = logging.getLogger(__name__)

DATASET_DIR = "dataset"
SUMMARY_FILE = "demonstrations.json"
MANIFEST_FILE = "manifest.tsv"


def scripted_expert(benchmark: str) -> ScriptedExpert:
    """The scripted expert `benchmark` declares; UserError naming `demonstrations.benchmark` when the benchmark is
    unknown or has no expert (read from its light declaration: no simulator is imported)."""
    lookup(BENCHMARK_SUITES, benchmark, "benchmark (demonstrations.benchmark)")
    expert = get_benchmark(benchmark).scripted_expert
    if expert is None:
        declaring = [name for name in BENCHMARK_SUITES if get_benchmark(name).scripted_expert is not None]
        raise UserError(f"demonstrations.benchmark: {benchmark} declares no scripted expert to record demonstrations "
                        f"from (benchmarks with one: {', '.join(declaring) or 'none'})")
    return expert


@dataclass(frozen=True)
class DemonstrationConfig:
    """The `demonstrations` section of a workflow config (the schema says what is allowed). `from_dict` fills
    what the section leaves out: `dir`, `suite` and `repo_id` from its benchmark, the other defaults here."""

    tasks: tuple[str, ...]  # task names of the suite, e.g. "drawer-close-v3"
    benchmark: str  # whose scripted expert is recorded (its declaration's `scripted_expert`)
    dir: str  # the rule's output folder; default results/demonstrations/<benchmark>
    suite: str  # where the task names, instructions and variation seeds come from; default the expert's suite
    repo_id: str  # default vlaquantbench/<benchmark>_expert_demonstrations
    episodes_per_task: int = 50  # successful episodes kept per task
    max_attempts_per_task: int = 100  # episodes tried per task at most before the job fails
    first_variation: int = 500  # variations first_variation.. (evaluation episode e uses variation e)
    image_size: int = 224  # rendered camera size: the policy's input size
    max_steps: int | None = None  # policy steps before an episode fails; None: the expert's limit on the suite
    image_writer_threads: int = 4  # lerobot's PNG writer threads

    @classmethod
    def from_dict(cls, raw: dict[str, Any] | None, where: str = "workflow config") -> DemonstrationConfig:
        """The typed section; UserError `<where>: <field>: ...` for a value the schema refuses, and UserError naming
        `demonstrations.benchmark` for a benchmark without a scripted expert."""
        raw = dict(raw or {})
        validate(raw, "config", where, subschema=("demonstrations",))
        benchmark = raw["benchmark"]
        derived = {"dir": f"results/demonstrations/{benchmark}", "suite": scripted_expert(benchmark).suite,
                   "repo_id": f"vlaquantbench/{benchmark}_expert_demonstrations"}
        return cls(**{**derived, **raw, "tasks": tuple(raw["tasks"])})

    def __post_init__(self):
        # The episodes' steps fit the simulator's: an episode past its horizon dies inside the simulator.
        lookup(BENCHMARK_SUITES[self.benchmark], self.suite, f"{self.benchmark} suite (demonstrations.suite)")
        check_step_limit("demonstrations.max_steps", self.step_limit, self.benchmark, self.suite)

    @property
    def expert(self) -> ScriptedExpert:
        return scripted_expert(self.benchmark)

    @property
    def step_limit(self) -> int:
        """Policy steps before an episode fails: `max_steps`, else the expert's limit on the suite."""
        return self.max_steps or model_step_limit(self.expert.model, self.benchmark, self.suite)

    @property
    def last_variation(self) -> int:
        return self.first_variation + self.max_attempts_per_task - 1


def _available_rgb_encoder():
    """A video encoder config this machine's FFmpeg can build. The dataset stores no video
    (`use_videos=False`), but lerobot 0.6.1's writer still builds its default encoder config, which
    refuses a codec the PyAV build lacks (the GPU machine's PyAV has no libsvtav1, lerobot's default)."""
    from lerobot.configs.video import HW_VIDEO_CODECS, RGBEncoderConfig
    from lerobot.datasets import detect_available_encoders_pyav

    preference = ["libsvtav1", "h264", "hevc", "libaom-av1", *HW_VIDEO_CODECS]
    available = detect_available_encoders_pyav(preference)
    if not available:
        raise RuntimeError(f"PyAV's FFmpeg offers none of lerobot's video encoders ({', '.join(preference)})")
    return RGBEncoderConfig(vcodec=available[0])


def _features(config: DemonstrationConfig) -> dict[str, dict]:
    """lerobot's feature spec of the dataset, named as a one-camera lerobot env names them for policies; the
    state's and action's components as the benchmark declares them (lerobot's `add_frame` refuses a frame
    whose shapes differ)."""
    from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

    expert, size = config.expert, config.image_size
    return {
        OBS_IMAGE: {"dtype": "image", "shape": (size, size, 3), "names": ["height", "width", "channels"]},
        OBS_STATE: {"dtype": "float32", "shape": (len(expert.state_names),), "names": list(expert.state_names)},
        ACTION: {"dtype": "float32", "shape": (len(expert.action_names),), "names": list(expert.action_names)},
    }


@dataclass(frozen=True)
class _Shard:
    """Consecutive variations of one task in one round, recorded by one worker process into a
    LeRobotDataset of its own (`root`); the shards are merged in (round, task, variation) order."""

    task_id: int
    variations: tuple[int, ...]
    root: Path


def _plan_shards(config: DemonstrationConfig, attempts: dict[int, list[dict]], workers: int, round_dir: Path) -> list[_Shard]:
    """The next round: per task, the next variations as many as successes are still missing, split into
    blocks so that every worker has about two (a worker's shard costs a dataset of its own)."""
    wanted = {}
    for task_id, tried in attempts.items():
        missing = config.episodes_per_task - sum(r["success"] for r in tried)
        count = min(missing, config.max_attempts_per_task - len(tried))
        wanted[task_id] = [config.first_variation + len(tried) + i for i in range(count)]
    active = sum(1 for v in wanted.values() if v)
    per_task = max(1, -(-2 * workers // max(active, 1)))
    shards = []
    for task_id, variations in wanted.items():
        size = max(1, -(-len(variations) // per_task))
        shards += [_Shard(task_id, tuple(variations[i:i + size]), round_dir / f"task{task_id:03d}-v{variations[i]:04d}")
                   for i in range(0, len(variations), size)]
    return shards


def _run_worker(config: DemonstrationConfig, shards: list[_Shard]) -> list[list[dict]]:
    """`_record_shards` in a fresh interpreter (as the simulator workers are, `envs.workers`: a spawned child
    would re-execute a Snakemake `script:`): each shard's records, or RuntimeError naming the shards."""
    if not shards:
        return []
    job = json.dumps({"config": {**asdict(config), "tasks": list(config.tasks)},
                      "shards": [{"task_id": s.task_id, "variations": list(s.variations), "root": str(s.root)} for s in shards]})
    run = subprocess.run([sys.executable, "-c", WORKER_MAIN, job], stdout=subprocess.PIPE, stderr=None, text=True)
    files = [_records_file(shard) for shard in shards]
    if run.returncode != 0 or not all(f.is_file() for f in files):
        recording = ", ".join(f"task {s.task_id} variations {s.variations[0]}..{s.variations[-1]}" for s in shards)
        raise RuntimeError(f"demonstrations: the worker recording {recording} failed (exit {run.returncode}; its "
                           "traceback is in the log above)")
    return [json.loads(f.read_text()) for f in files]


WORKER_MAIN = "import sys; from vlaquantbench.demonstrations.dataset import worker_main; worker_main(sys.argv[1])"


def _records_file(shard: _Shard) -> Path:
    return shard.root.parent / f"{shard.root.name}.json"


def worker_main(job: str) -> None:
    """A demonstration worker's entry point: `job` is `_run_worker`'s JSON; each shard's records go to
    `_records_file(shard)`."""
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    raw = json.loads(job)
    config = DemonstrationConfig(**{**raw["config"], "tasks": tuple(raw["config"]["tasks"])})
    shards = [_Shard(s["task_id"], tuple(s["variations"]), Path(s["root"])) for s in raw["shards"]]
    _record_shards(config, shards)


def _record_shards(config: DemonstrationConfig, shards: list[_Shard]) -> None:
    """Run the expert on each shard's variations, one simulator for all, and save each shard's successful
    episodes into its own LeRobotDataset; write every attempt's record to `_records_file(shard)`, with
    `dataset_episode` the episode's index within the shard (None: not kept)."""
    import torch
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

    from vlaquantbench.envs import make_env, make_suite
    from vlaquantbench.envs.registry import STATE
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter
    from vlaquantbench.runner.loop import run_episodes

    torch.set_num_threads(1)  # one core a worker: a scripted expert computes its action from the state, no network
    suite = make_suite(config.benchmark, config.suite)
    image = get_benchmark(config.benchmark).cameras["main"]  # the observation key of the camera recorded
    expert = make_adapter(AdapterConfig(model=config.expert.model, variant="full"))
    expert.load()
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def on_actions(spec: EpisodeSpec, observation: dict, actions: np.ndarray) -> None:
        if len(actions) != 1:
            raise ValueError(f"a demonstration records one action per observation; the policy sent {len(actions)}")
        # The action within lerobot's action space, [-1, 1], as the env clips it: a scripted expert's gains may
        # overshoot it, and a policy learns targets within it.
        frames.append((observation[image], observation[STATE].astype(np.float32),
                       np.clip(actions[0], -1, 1).astype(np.float32)))

    # One env: episodes run one after another, so `frames` holds exactly the running episode's.
    with make_env(config.benchmark, suite, 1, camera_size=config.image_size) as env:
        for shard in shards:
            dataset = LeRobotDataset.create(
                config.repo_id, fps=config.expert.fps, features=_features(config), root=shard.root,
                robot_type=config.expert.robot_type, use_videos=False, image_writer_threads=config.image_writer_threads,
                rgb_encoder=_available_rgb_encoder())
            instruction = suite.task(shard.task_id).instruction
            records: list[dict] = []

            def on_finished(finished: list[dict]) -> None:
                for record in finished:
                    episode = None
                    if record["success"]:
                        if len(frames) != record["steps"]:  # one recorded frame per executed action
                            raise RuntimeError(f"{record['task_name']} variation {record['init_state_id']}: "
                                               f"{len(frames)} frames recorded for {record['steps']} steps")
                        for image, state, action in frames:
                            dataset.add_frame({OBS_IMAGE: image, OBS_STATE: state, ACTION: action, "task": instruction})
                        dataset.save_episode()
                        episode = dataset.meta.total_episodes - 1
                    frames.clear()
                    log.info("%s variation %d: %s after %d steps", record["task_name"], record["init_state_id"],
                             "success" if record["success"] else "FAILED (not kept)", record["steps"])
                    records.append({**record, "dataset_episode": episode})

            specs = [suite.episode_spec(shard.task_id, variation) for variation in shard.variations]
            run_episodes(expert, env, specs, config.step_limit, on_finished, on_actions=on_actions)
            dataset.finalize()
            _records_file(shard).write_text(json.dumps(records))


def write_demonstrations(config: DemonstrationConfig, out_dir: str | Path, workers: int) -> dict[str, Any]:
    """Record the experts' demonstrations under `out_dir` (see the module doc); return the summary.

    `workers` processes each record a shard (a block of one task's variations, with its own simulator)
    into a LeRobotDataset of its own; lerobot's `aggregate_datasets` merges the shards in (round, task,
    variation) order, so the dataset does not depend on the number of workers. Writing (PNG encoding,
    image statistics) runs in every worker, beside its own simulator, instead of serially in one process.

    UserError, before any worker starts, for an unknown task or a variation range past the seeds of a
    task; after writing, for a task whose experts fell short of `episodes_per_task` successes within
    `max_attempts_per_task` episodes (the log lists every attempt)."""
    import shutil
    from concurrent.futures import ThreadPoolExecutor

    from lerobot.datasets.aggregate import aggregate_datasets
    from lerobot.datasets.lerobot_dataset import LeRobotDatasetMetadata

    from vlaquantbench.envs import make_suite, simulator_versions
    from vlaquantbench.manifest import write_file_manifest
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter

    suite = make_suite(config.benchmark, config.suite)
    task_ids = [suite.task_id(name) for name in config.tasks]
    variations = BENCHMARK_SUITES[config.benchmark][config.suite].init_states
    if config.last_variation >= variations:
        raise UserError(f"demonstrations: first_variation {config.first_variation} + max_attempts_per_task "
                        f"{config.max_attempts_per_task} reaches variation {config.last_variation}; a task has "
                        f"variations 0..{variations - 1}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    shards_dir = out / "shards"
    shutil.rmtree(shards_dir, ignore_errors=True)
    expert = make_adapter(AdapterConfig(model=config.expert.model, variant="full"))
    expert.load()  # its provenance, for the summary

    attempts: dict[int, list[dict]] = {t: [] for t in task_ids}
    merged: list[Path] = []  # shards holding kept episodes, in the dataset's order
    kept: dict[tuple[int, int], int] = {}  # (task, variation) -> dataset episode index
    started = time.perf_counter()
    # Each thread waits on one worker interpreter (`_run_worker`).
    with ThreadPoolExecutor(max(1, workers)) as pool:
        for round_index in range(config.max_attempts_per_task):
            shards = _plan_shards(config, attempts, workers, shards_dir / f"round{round_index}")
            if not shards:
                break
            # Worker w records shards w, w + workers, ...: each interpreter and simulator starts once a round.
            assigned = [shards[w::workers] for w in range(workers)]
            results = pool.map(_run_worker, [config] * workers, assigned)
            by_shard = {shard: records for mine, theirs in zip(assigned, results) for shard, records in zip(mine, theirs)}
            for shard in shards:  # the dataset takes the shards in the round's order
                records = by_shard[shard]
                attempts[shard.task_id] += records
                shard_kept = [r for r in records if r["dataset_episode"] is not None]
                for record in shard_kept:
                    kept[(shard.task_id, record["init_state_id"])] = len(kept)
                if shard_kept:
                    merged.append(shard.root)
            done = sum(map(len, attempts.values()))
            log.info("%d episodes tried, %d kept, %.1f episodes/minute with %d workers",
                     done, len(kept), done / _minutes_since(started), workers)
    merging = time.perf_counter()
    # One data file per shard: packing them appends every shard to the growing file, re-reading and
    # re-embedding every PNG already in it (quadratic in the shards; 100.7 s for 42 shards on the H200).
    aggregate_datasets([config.repo_id] * len(merged), config.repo_id, roots=merged, aggr_root=out / DATASET_DIR,
                       concatenate_data=False)
    shutil.rmtree(shards_dir)
    meta = LeRobotDatasetMetadata(config.repo_id, root=out / DATASET_DIR)
    log.info("%d episodes kept in %.1f s (%.1f a minute), merged in %.1f s", meta.total_episodes, merging - started,
             meta.total_episodes / _minutes_since(started), time.perf_counter() - merging)

    summary = {
        "settings": {**asdict(config), "tasks": list(config.tasks), "max_steps": config.step_limit},
        "dataset": {"dir": DATASET_DIR, "repo_id": config.repo_id, "fps": config.expert.fps, "use_videos": False,
                    "features": list(_features(config)), "episodes": meta.total_episodes,
                    "frames": meta.total_frames},
        "expert": expert.checkpoint_provenance,
        "versions": {**simulator_versions(config.benchmark), "lerobot": importlib.metadata.version("lerobot")},
        "renderer": os.environ.get("MUJOCO_GL", "egl"),  # what the workers set when unset
        "workers": workers,
        "tasks": [_task_summary(suite, task_id, attempts[task_id], kept) for task_id in task_ids],
    }
    (out / SUMMARY_FILE).write_text(json.dumps(summary, indent=1) + "\n")
    write_file_manifest(out, out / MANIFEST_FILE)
    short = [f"{t['task']} ({t['kept']} of {t['tried']} tried)" for t in summary["tasks"]
             if t["kept"] < config.episodes_per_task]
    if short:
        raise UserError(f"the experts kept fewer than demonstrations.episodes_per_task {config.episodes_per_task} "
                        f"episodes within max_attempts_per_task {config.max_attempts_per_task}: {', '.join(short)}")
    return summary


def _minutes_since(started: float) -> float:
    return (time.perf_counter() - started) / 60


def _task_summary(suite, task_id: int, records: list[dict], kept: dict[tuple[int, int], int]) -> dict[str, Any]:
    task = suite.task(task_id)
    episodes = [
        {"variation": r["init_state_id"], "variation_seed": suite.variation_seed(task_id, r["init_state_id"]),
         "success": r["success"], "steps": r["steps"], "dataset_episode": kept.get((task_id, r["init_state_id"])),
         "task_variation": r["task_variation"]}
        for r in sorted(records, key=lambda r: r["init_state_id"])
    ]
    return {"task": task.name, "instruction": task.instruction, "tried": len(episodes),
            "kept": sum(e["dataset_episode"] is not None for e in episodes), "episodes": episodes}

