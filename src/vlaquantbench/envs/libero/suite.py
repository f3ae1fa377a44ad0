"""A LIBERO suite as the authors evaluated it: tasks, official init states, seeds (step limits: each model's
client, `models/<model>/client.py`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlaquantbench.envs.episodes import TASK_SEED_STRIDE, EpisodeSpec, SuiteTasks, episode_seed
from vlaquantbench.envs.libero.benchmark import LIBERO
from vlaquantbench.envs.libero.offline import load_libero
from vlaquantbench.errors import UserError

SUITES = LIBERO.suites

__all__ = ["SUITES", "TASK_SEED_STRIDE", "EpisodeSpec", "LiberoSuite", "LiberoTask", "all_instructions", "episode_seed"]


def all_instructions() -> list[str]:
    """Every LIBERO suite's task instructions, sorted: the prompts of the released LIBERO checkpoints, on which the
    models' hub fixtures train their stand-in tokenizers."""
    return sorted({t.instruction for s in SUITES for t in LiberoSuite(s).tasks})


@dataclass(frozen=True)
class LiberoTask:
    task_id: int
    name: str
    instruction: str
    bddl_file: Path
    init_states_file: Path


class LiberoSuite(SuiteTasks):
    """The tasks of one LIBERO suite, in LIBERO's default task order."""

    def __init__(self, name: str):
        if name not in SUITES:
            raise UserError(f"unknown LIBERO suite {name!r}; expected one of {', '.join(SUITES)}")
        libero = load_libero()
        from libero.libero import benchmark

        bddl_root = Path(libero.get_libero_path("bddl_files"))
        init_root = Path(libero.get_libero_path("init_states"))
        tasks = benchmark.get_benchmark(name)().tasks
        self.name = name
        self.tasks = tuple(
            LiberoTask(
                task_id=i,
                name=task.name,
                instruction=task.language,
                bddl_file=bddl_root / task.problem_folder / task.bddl_file,
                init_states_file=init_root / task.problem_folder / task.init_states_file,
            )
            for i, task in enumerate(tasks)
        )
        self._init_states: dict[int, np.ndarray] = {}

    def init_states(self, task_id: int) -> np.ndarray:
        """The official initial states of a task: one flattened MuJoCo state per row."""
        if task_id not in self._init_states:
            import torch

            # The files are pickled numpy arrays; torch >= 2.6 refuses them unless weights_only=False.
            states = torch.load(self.task(task_id).init_states_file, weights_only=False)
            self._init_states[task_id] = np.asarray(states)
        return self._init_states[task_id]

    def init_state(self, task_id: int, init_state_id: int) -> np.ndarray:
        states = self.init_states(task_id)
        if not 0 <= init_state_id < len(states):
            raise UserError(
                f"init_state_id {init_state_id} is out of range for {self.name} task {task_id} "
                f"({len(states)} official init states: 0..{len(states) - 1})"
            )
        return states[init_state_id]

    def episode_spec(self, task_id: int, episode: int, run_seed: int = 0) -> EpisodeSpec:
        """Episode i of a task starts from official init state i."""
        self.init_state(task_id, episode)
        return EpisodeSpec(task_id, episode, init_state_id=episode, seed=episode_seed(task_id, episode, run_seed))
