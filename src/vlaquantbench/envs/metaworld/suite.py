"""A Meta-World suite on lerobot 0.6.1's conventions: tasks, instructions, seeded variations, step limit.

Suites: lerobot's difficulty groups (`metaworld_easy`, `metaworld_medium`, `metaworld_hard`,
`metaworld_very_hard`, its `metaworld_config.json`) and Meta-World's own MT10 and MT50 task lists
(`metaworld_mt10`, `metaworld_mt50`, in Meta-World's order). A task's instruction is lerobot's task
description. The facts are read from the installed lerobot and Meta-World, not restated here, so
they cannot drift from what lerobot's evaluation uses.

A task variation is Meta-World's random placement of the task's objects and goal (its `rand_vec`),
drawn at reset from the seeded simulator. Variation i of a task is drawn from `variation_seed(task,
i)`, which depends on the task's name (lerobot's task id), not on the suite or the run seed: episode
i of a task starts from the same scene in every suite and every run, as episode i of a LIBERO task
starts from official init state i. The run seed changes the policy's random stream only: episode i of a
task has the LIBERO protocol's seed (`envs.episodes.episode_seed`, 1009 x task + i + 1000003 x run seed),
which seeds the policy, never the placement.
"""

from __future__ import annotations

import functools
import importlib.util
import json
from dataclasses import dataclass
from pathlib import Path

from vlaquantbench.envs.episodes import TASK_SEED_STRIDE, EpisodeSpec, SuiteTasks, episode_seed
from vlaquantbench.envs.metaworld.benchmark import METAWORLD, METAWORLD_STEP_LIMIT
from vlaquantbench.errors import UserError

SUITES = METAWORLD.suites
# lerobot's difficulty group of each difficulty suite (`DIFFICULTY_TO_TASKS` keys).
DIFFICULTY_GROUPS = {f"metaworld_{group}": group for group in ("easy", "medium", "hard", "very_hard")}
# Meta-World's multi-task benchmarks: the `metaworld.env_dict` table of each suite.
MULTI_TASK_LISTS = {"metaworld_mt10": "MT10_V3", "metaworld_mt50": "MT50_V3"}
STEP_LIMIT = METAWORLD_STEP_LIMIT  # whatever the model (`envs.registry.SuiteSize.step_limit`)


@functools.cache
def lerobot_metaworld_config() -> dict:
    """lerobot 0.6.1's `envs/metaworld_config.json` (task descriptions, ids, difficulty groups, expert
    policy classes), read from the installed package without importing lerobot (torch) or Meta-World."""
    spec = importlib.util.find_spec("lerobot")
    if spec is None or not spec.submodule_search_locations:
        raise UserError("lerobot is not installed: run scripts/setup.sh")
    path = Path(spec.submodule_search_locations[0]) / "envs" / "metaworld_config.json"
    return json.loads(path.read_text())


def variation_seed(task_name: str, variation: int) -> int:
    """The seed Meta-World draws variation `variation` of a task's object and goal placement from: the protocol's
    run-seed-0 seed of that episode of the task's lerobot id, whatever the cell's run seed (the scene stays)."""
    return episode_seed(lerobot_metaworld_config()["TASK_NAME_TO_ID"][task_name], variation, run_seed=0)


def suite_task_names(name: str) -> tuple[str, ...]:
    """The task names of suite `name`, in its order; UserError naming the suite if it is unknown."""
    if name in DIFFICULTY_GROUPS:
        return tuple(lerobot_metaworld_config()["DIFFICULTY_TO_TASKS"][DIFFICULTY_GROUPS[name]])
    if name in MULTI_TASK_LISTS:
        import metaworld.env_dict  # seconds: imports every Meta-World env class

        return tuple(getattr(metaworld.env_dict, MULTI_TASK_LISTS[name]))
    raise UserError(f"unknown Meta-World suite {name!r}; expected one of {', '.join(SUITES)}")


@dataclass(frozen=True)
class MetaWorldTask:
    task_id: int  # index in its suite
    name: str  # Meta-World's env name, e.g. "drawer-close-v3"
    instruction: str  # lerobot's task description


class MetaWorldSuite(SuiteTasks):
    """The tasks of one Meta-World suite, in the suite's order."""

    step_limit = STEP_LIMIT

    def __init__(self, name: str):
        descriptions = lerobot_metaworld_config()["TASK_DESCRIPTIONS"]
        self.name = name
        self.tasks = tuple(
            MetaWorldTask(task_id=i, name=task, instruction=descriptions[task])
            for i, task in enumerate(suite_task_names(name))
        )

    def task_id(self, task_name: str) -> int:
        """The id of a task given by name; UserError naming it and the suite's tasks if it is not one."""
        for task in self.tasks:
            if task.name == task_name:
                return task.task_id
        raise UserError(f"unknown task {task_name!r} in Meta-World suite {self.name}; its tasks: "
                        f"{', '.join(t.name for t in self.tasks)}")

    def variation_seed(self, task_id: int, variation: int) -> int:
        if variation < 0:
            raise UserError(f"variation {variation} of {self.name} task {task_id} must not be negative")
        if variation >= TASK_SEED_STRIDE:  # the next task's seeds would start
            raise UserError(f"variation {variation} of {self.name} task {task_id} must be below {TASK_SEED_STRIDE}")
        return variation_seed(self.task(task_id).name, variation)

    def task_variation(self, spec: EpisodeSpec) -> tuple[float, ...]:
        """The placement episode `spec` starts from: what its worker reports at reset as `task_variation`,
        drawn here as the worker draws it, without a camera (milliseconds; each task's env built once)."""
        return _drawn_placement(self.task(spec.task_id).name, self.variation_seed(spec.task_id, spec.init_state_id))

    def episode_spec(self, task_id: int, episode: int, run_seed: int = 0) -> EpisodeSpec:
        """Episode i of a task starts from task variation i."""
        self.variation_seed(task_id, episode)
        return EpisodeSpec(task_id, episode, init_state_id=episode, seed=episode_seed(task_id, episode, run_seed))


@functools.cache
def _placement_simulator(task: str):
    from vlaquantbench.envs.metaworld.worker import SlotSimulator

    simulator = SlotSimulator(camera_size=None)
    simulator.load(task)
    return simulator


@functools.cache
def _drawn_placement(task: str, seed: int) -> tuple[float, ...]:
    simulator = _placement_simulator(task)
    simulator.reset(task, seed)
    return tuple(float(x) for x in simulator.task_variation())
