"""The contract suite: two reach tasks; episode i of a task starts from goal placement (variation) i, drawn from
the protocol's seed of that episode at run seed 0, so the run seed varies only the policy's random stream."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from contract_benchmark.benchmark import CONTRACT, SUITE
from vlaquantbench.envs.episodes import EpisodeSpec, SuiteTasks, episode_seed
from vlaquantbench.errors import UserError

HAND_START = (0.0, 0.0, 0.3)
GOAL_OFFSET = (0.15, 0.15, 0.1)  # a goal lies within +- these of the hand's start, per axis


@dataclass(frozen=True)
class ContractTask:
    task_id: int
    name: str  # a Meta-World reach task's name: the expert the `metaworld_expert` model picks
    instruction: str


TASKS = (ContractTask(0, "reach-v3", "reach the red goal"),
         ContractTask(1, "reach-wall-v3", "reach the red goal, rising over any wall"))


class ContractSuite(SuiteTasks):
    def __init__(self, name: str):
        if name not in CONTRACT.suites:
            raise UserError(f"unknown contract suite {name!r}; expected one of {', '.join(CONTRACT.suites)}")
        self.name = name
        self.tasks = TASKS if name == SUITE else ()

    def variation_seed(self, task_id: int, variation: int) -> int:
        size = CONTRACT.suites[self.name].init_states
        if not 0 <= variation < size:
            raise UserError(f"variation {variation} of {self.name} task {task_id} is outside 0..{size - 1}")
        return episode_seed(self.task(task_id).task_id, variation, run_seed=0)

    def task_variation(self, spec: EpisodeSpec) -> tuple[float, ...]:
        """The goal position episode `spec` starts from (what its worker reports at reset)."""
        rng = np.random.default_rng(self.variation_seed(spec.task_id, spec.init_state_id))
        offset = rng.uniform(-np.asarray(GOAL_OFFSET), np.asarray(GOAL_OFFSET))
        return tuple(float(x) for x in np.asarray(HAND_START) + offset)

    def episode_spec(self, task_id: int, episode: int, run_seed: int = 0) -> EpisodeSpec:
        self.variation_seed(task_id, episode)
        return EpisodeSpec(task_id, episode, init_state_id=episode, seed=episode_seed(task_id, episode, run_seed))
