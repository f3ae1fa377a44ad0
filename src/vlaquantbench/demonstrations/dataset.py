"""Meta-World's scripted experts recorded as a LeRobotDataset: what the trained policy learns from.

`write_demonstrations(config, out_dir, num_envs)` writes under `out_dir`:
  - `dataset/`: a LeRobotDataset (lerobot 0.6.1's `LeRobotDataset.create` / `add_frame` /
    `save_episode`, local, no hub) with the features lerobot's Meta-World env gives a policy:
    `observation.image` (the `corner2` camera at `image_size` pixels, lerobot's orientation),
    `observation.state` (`agent_pos`: hand xyz, gripper opening), `action` (the expert's, clipped to
    [-1, 1] as Meta-World applies it), and
    the task's lerobot description as each frame's `task`. Images are stored as PNG inside the
    parquet files (`use_videos=False`): no video codec is needed to write or read them, and a frame
    reads back exactly as rendered.
  - `demonstrations.json`: the settings, the versions, and per task every attempted episode: its
    variation, the variation's seed, the object and goal placement it drew, success, steps, and
    the dataset episode it became (null: not kept).
  - `manifest.tsv`: the SHA-256 of every file above (`manifest.write_file_manifest`).

Episodes: the experts act through the closed-loop runner (`runner.loop.run_episodes`) on
`MetaWorldVectorEnv`, so a demonstration sees what an evaluated policy sees. Task variation v of a
task is drawn from `variation_seed(task, v)`; closed-loop evaluation episode e starts from variation
e (`MetaWorldSuite.episode_spec`), so the demonstrations take variations from `first_variation` on
(default 500), and `check_disjoint_from_evaluation` refuses a study whose cells would evaluate one
of them. Only successful episodes are kept: a task gets attempts on consecutive variations until
`episodes_per_task` succeed (each round tries as many as are still missing), so the kept episodes
are the first successes in variation order whatever the number of workers, and the dataset's
episodes are in a fixed order (round, task, variation).
"""

from __future__ import annotations

import importlib.metadata
import json
import logging
import os
import time
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from vlaquantbench.config import validate
from vlaquantbench.envs.episodes import TASK_SEED_STRIDE, EpisodeSpec
from vlaquantbench.errors import UserError

log = logging.getLogger(__name__)

DATASET_DIR = "dataset"
SUMMARY_FILE = "demonstrations.json"
MANIFEST_FILE = "manifest.tsv"
ROBOT_TYPE = "sawyer"  # Meta-World's arm


@dataclass(frozen=True)
class DemonstrationConfig:
    """The `demonstrations` section of a workflow config (defaults live here; the schema says what is allowed)."""

    tasks: tuple[str, ...]  # Meta-World env names, e.g. "drawer-close-v3"
    dir: str = "results/demonstrations/metaworld"  # the rule's output folder
    episodes_per_task: int = 50  # successful episodes kept per task
    max_attempts_per_task: int = 100  # episodes tried per task at most before the job fails
    first_variation: int = 500  # variations first_variation.. (evaluation episode e uses variation e)
    image_size: int = 224  # rendered camera size: the policy's input size
    max_steps: int | None = None  # policy steps before an episode fails; None: Meta-World's limit (500)
    suite: str = "metaworld_mt50"  # where the task names, instructions and variation seeds come from
    repo_id: str = "vlaquantbench/metaworld_expert_demonstrations"
    image_writer_threads: int = 4  # lerobot's PNG writer threads

    @classmethod
    def from_dict(cls, raw: dict[str, Any] | None, where: str = "workflow config") -> DemonstrationConfig:
        """The typed section; UserError `<where>: <field>: ...` for a value the schema refuses."""
        raw = dict(raw or {})
        validate(raw, "config", where, subschema=("demonstrations",))
        return cls(**{**raw, "tasks": tuple(raw["tasks"])})

    @property
    def last_variation(self) -> int:
        return self.first_variation + self.max_attempts_per_task - 1


def check_disjoint_from_evaluation(config: DemonstrationConfig, cells: Iterable[dict[str, Any]]) -> None:
    """UserError naming the first Meta-World cell (canonical config, `cells.CellConfig.to_dict`) that
    evaluates or calibrates on a task variation the demonstrations may use."""
    for cell in cells:
        if cell["benchmark"] != "metaworld":
            continue
        calibration = cell.get("calibration") or {}
        used = {"episodes_per_task": cell["episodes_per_task"] - 1,
                "calibration init states": max(calibration.get("init_states") or [-1])}
        for what, highest in used.items():
            if highest >= config.first_variation:
                raise UserError(
                    f"demonstrations.first_variation {config.first_variation}: cell {cell['ref']} uses task "
                    f"variations up to {highest} ({what}), which the demonstrations may record; set "
                    f"demonstrations.first_variation above {highest}")


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


def _features(image_size: int) -> dict[str, dict]:
    """lerobot's feature spec of the dataset, named as lerobot's Meta-World env names them for policies."""
    from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

    from vlaquantbench.envs.metaworld import ACTION_DIM
    from vlaquantbench.envs.metaworld.worker import STATE_DIM

    return {
        OBS_IMAGE: {"dtype": "image", "shape": (image_size, image_size, 3), "names": ["height", "width", "channels"]},
        OBS_STATE: {"dtype": "float32", "shape": (STATE_DIM,), "names": ["hand_x", "hand_y", "hand_z", "gripper"]},
        ACTION: {"dtype": "float32", "shape": (ACTION_DIM,), "names": ["dx", "dy", "dz", "gripper"]},
    }


@dataclass
class _Attempt:
    """One expert episode: its frames until it resolves, then its outcome."""

    spec: EpisodeSpec
    frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    record: dict | None = None


class _EpisodeWriter:
    """Saves episodes to the LeRobotDataset in one thread of its own, in the order they are submitted.

    lerobot's `save_episode` encodes the PNGs and computes the image statistics (1-2 s a 224-px episode,
    benchmarks/results/gpu_demonstrations_h200/): done in the run loop, it held every worker idle, so
    it overlaps the simulation instead. One thread keeps lerobot's writer single-threaded and the
    episodes in order; a failed save is raised at the next submit or at `close`."""

    def __init__(self, dataset):
        from concurrent.futures import ThreadPoolExecutor
        from lerobot.utils.constants import ACTION, OBS_IMAGE, OBS_STATE

        self.keys = OBS_IMAGE, OBS_STATE, ACTION
        self.dataset = dataset
        self.submitted = 0
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="save_episode")
        self._saves: list = []

    def submit(self, frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]], instruction: str) -> int:
        """Queue an episode; its index in the dataset."""
        self._raise_failed()
        self._saves.append(self._executor.submit(self._save, frames, instruction))
        self.submitted += 1
        return self.submitted - 1

    def _save(self, frames, instruction: str) -> None:
        for image, state, action in frames:
            self.dataset.add_frame(dict(zip(self.keys, (image, state, action)), task=instruction))
        self.dataset.save_episode()

    def _raise_failed(self) -> None:
        for save in self._saves:
            if save.done() and save.exception() is not None:
                raise save.exception()
        self._saves = [save for save in self._saves if not save.done()]

    def close(self) -> None:
        """Wait for every queued episode; raise the first failed save."""
        self._executor.shutdown(wait=True)
        self._raise_failed()


class _Recorder:
    """Collects each episode's frames as the runner sends its actions, and queues the kept episodes
    for the dataset in the round's episode order as soon as every earlier one has resolved."""

    def __init__(self, writer: _EpisodeWriter, suite, specs: list[EpisodeSpec]):
        self.writer = writer
        self.suite = suite
        self.attempts = {(s.task_id, s.init_state_id): _Attempt(s) for s in specs}
        self.order = [(s.task_id, s.init_state_id) for s in specs]
        self.written = 0  # attempts of `order` resolved and written (or dropped)
        self.kept: dict[tuple[int, int], int] = {}  # (task, variation) -> dataset episode index

    def on_actions(self, spec: EpisodeSpec, observation: dict, actions: np.ndarray) -> None:
        if len(actions) != 1:
            raise ValueError(f"a demonstration records one action per observation; the policy sent {len(actions)}")
        # The action as Meta-World applies it: the experts' position gains overshoot (xyz up to ~5, which
        # `SawyerXYZEnv.set_xyz_action` clips to [-1, 1]; the gripper effort is +-1), and a policy learns
        # targets within lerobot's action space.
        action = np.clip(actions[0], -1, 1).astype(np.float32)
        self.attempts[(spec.task_id, spec.init_state_id)].frames.append(
            (observation["image"], observation["state"].astype(np.float32), action))

    def on_finished(self, records: list[dict]) -> None:
        for record in records:
            attempt = self.attempts[(record["task_id"], record["init_state_id"])]
            attempt.record = record
            log.info("%s variation %d: %s after %d steps", record["task_name"], record["init_state_id"],
                     "success" if record["success"] else "FAILED (not kept)", record["steps"])
        while self.written < len(self.order) and self.attempts[self.order[self.written]].record is not None:
            self._write(self.attempts[self.order[self.written]])
            self.written += 1

    def _write(self, attempt: _Attempt) -> None:
        frames, attempt.frames = attempt.frames, []
        if not attempt.record["success"]:
            return
        if len(frames) != attempt.record["steps"]:  # one recorded frame per executed action
            raise RuntimeError(f"{attempt.record['task_name']} variation {attempt.spec.init_state_id}: "
                               f"{len(frames)} frames recorded for {attempt.record['steps']} steps")
        instruction = self.suite.task(attempt.spec.task_id).instruction
        self.kept[(attempt.spec.task_id, attempt.spec.init_state_id)] = self.writer.submit(frames, instruction)


def write_demonstrations(config: DemonstrationConfig, out_dir: str | Path, num_envs: int) -> dict[str, Any]:
    """Record the experts' demonstrations under `out_dir` (see the module doc); return the summary.

    UserError, before any worker starts, for an unknown task or a variation range past the seeds of a
    task; after writing, for a task whose experts fell short of `episodes_per_task` successes within
    `max_attempts_per_task` episodes (the log lists every attempt)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.envs.configs import MetaworldEnv

    from vlaquantbench.envs import make_env, make_suite
    from vlaquantbench.envs.metaworld import STEP_LIMIT, simulator_versions
    from vlaquantbench.manifest import write_file_manifest
    from vlaquantbench.models.adapter import AdapterConfig, make_adapter
    from vlaquantbench.runner.loop import run_episodes

    suite = make_suite("metaworld", config.suite)
    task_ids = [suite.task_id(name) for name in config.tasks]
    if config.last_variation >= TASK_SEED_STRIDE:
        raise UserError(f"demonstrations: first_variation {config.first_variation} + max_attempts_per_task "
                        f"{config.max_attempts_per_task} reaches variation {config.last_variation}; a task has "
                        f"variations 0..{TASK_SEED_STRIDE - 1}")
    max_steps = config.max_steps or STEP_LIMIT
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    dataset = LeRobotDataset.create(
        config.repo_id, fps=MetaworldEnv.fps, features=_features(config.image_size), root=out / DATASET_DIR,
        robot_type=ROBOT_TYPE, use_videos=False, image_writer_threads=config.image_writer_threads,
        rgb_encoder=_available_rgb_encoder())
    expert = make_adapter(AdapterConfig(model="metaworld_expert", variant="full"))
    expert.load()

    attempts: dict[int, list[dict]] = {t: [] for t in task_ids}
    kept: dict[tuple[int, int], int] = {}
    writer = _EpisodeWriter(dataset)
    started = time.perf_counter()
    with make_env("metaworld", suite, num_envs, camera_size=config.image_size) as env:
        while True:
            # Each round tries, per task, the next variations as many as successes are still missing.
            specs = []
            for task_id in task_ids:
                missing = config.episodes_per_task - sum(r["success"] for r in attempts[task_id])
                tried = len(attempts[task_id])
                specs += [suite.episode_spec(task_id, config.first_variation + tried + i)
                          for i in range(min(missing, config.max_attempts_per_task - tried))]
            if not specs:
                break
            recorder = _Recorder(writer, suite, specs)
            run_episodes(expert, env, specs, max_steps, recorder.on_finished, on_actions=recorder.on_actions)
            kept.update(recorder.kept)
            for (task_id, variation), attempt in recorder.attempts.items():
                attempts[task_id].append(attempt.record)
            done = sum(map(len, attempts.values()))
            log.info("%d episodes tried, %d kept, %.1f episodes/minute with %d workers",
                     done, len(kept), done / _minutes_since(started), env.num_envs)
    writer.close()
    log.info("%d episodes saved, %.1f episodes/minute", writer.submitted, writer.submitted / _minutes_since(started))
    dataset.finalize()

    summary = {
        "settings": {**asdict(config), "tasks": list(config.tasks), "max_steps": max_steps},
        "dataset": {"dir": DATASET_DIR, "repo_id": config.repo_id, "fps": MetaworldEnv.fps, "use_videos": False,
                    "features": list(_features(config.image_size)), "episodes": dataset.meta.total_episodes,
                    "frames": dataset.meta.total_frames},
        "expert": expert.checkpoint_provenance,
        "versions": {**simulator_versions(), "lerobot": importlib.metadata.version("lerobot")},
        "renderer": os.environ.get("MUJOCO_GL", "egl"),  # what the workers set when unset
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

