"""What every benchmark's episodes share: the spec a vector env's slot runs, and its seed."""

from __future__ import annotations

from dataclasses import dataclass

from vlaquantbench.errors import UserError

# Per-episode seed = SEED_STRIDE * task_id + episode + run seed (the authors' LIBERO records).
SEED_STRIDE = 1009


@dataclass(frozen=True)
class EpisodeSpec:
    """One episode to run in a slot of a vector env.

    `init_state_id` picks the episode's scene: LIBERO's official init state of that index, or
    Meta-World's task variation of that index (`envs.metaworld.suite.variation_seed`). `seed` seeds
    the simulator and the policy's random stream."""

    task_id: int
    episode: int
    init_state_id: int
    seed: int


def episode_seed(task_id: int, episode: int, run_seed: int = 0) -> int:
    return SEED_STRIDE * task_id + episode + run_seed


class SuiteTasks:
    """What every benchmark's suite shares: its `name`, its `tasks` (each with a `task_id`, its index)
    and its episodes; a suite defines `episode_spec(task_id, episode, run_seed)`. Step limits are the
    models' (`models.client.step_limit`), resolved into each cell's config when the DAG is built."""

    name: str
    tasks: tuple

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r})"

    @property
    def n_tasks(self) -> int:
        return len(self.tasks)

    def task(self, task_id: int):
        if not 0 <= task_id < self.n_tasks:
            raise UserError(f"task_id {task_id} is out of range for {self.name} (0..{self.n_tasks - 1})")
        return self.tasks[task_id]

    def episode_spec(self, task_id: int, episode: int, run_seed: int = 0) -> EpisodeSpec:
        raise NotImplementedError

    def episodes(
        self, episodes_per_task: int, task_ids: list[int] | None = None, run_seed: int = 0
    ) -> list[EpisodeSpec]:
        """All episodes of a study on this suite, task by task."""
        ids = range(self.n_tasks) if task_ids is None else task_ids
        return [self.episode_spec(t, e, run_seed) for t in ids for e in range(episodes_per_task)]
