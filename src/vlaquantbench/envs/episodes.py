"""What every benchmark's episodes share: the spec a vector env's slot runs, and its seed."""

from __future__ import annotations

from dataclasses import dataclass

from vlaquantbench.errors import UserError

# The authors' evaluation protocol (their records, run seeds 0, 1 and 2): episode e of task t in run seed s
# has seed TASK_SEED_STRIDE * t + e + RUN_SEED_STRIDE * s. Both strides are primes. A task's episodes stay below
# the next task's seeds while e < TASK_SEED_STRIDE (a benchmark's seeded variations are bounded so), and a run's seeds
# stay below the next run's while TASK_SEED_STRIDE * tasks <= RUN_SEED_STRIDE (up to 991 tasks): two run seeds share
# no episode seed, so a second run seed repeats every episode on fresh random streams.
TASK_SEED_STRIDE = 1009
RUN_SEED_STRIDE = 1_000_003


@dataclass(frozen=True)
class EpisodeSpec:
    """One episode to run in a slot of a vector env.

    `init_state_id` picks the episode's scene: the benchmark's official init state of that index, or its
    seeded task variation of that index, whatever the run seed. `seed` (`episode_seed`) seeds the policy's
    random stream and, where the benchmark seeds its simulator per episode, the simulator's: under
    the fixed init states a run seed varies those streams, not the scene."""

    task_id: int
    episode: int
    init_state_id: int
    seed: int


def episode_seed(task_id: int, episode: int, run_seed: int = 0) -> int:
    """The protocol's seed of episode `episode` of task `task_id` in run seed `run_seed`: what the runner, every
    suite's episode specs and the record check (`records.schema.EpisodeCheck`) use."""
    return TASK_SEED_STRIDE * task_id + episode + RUN_SEED_STRIDE * run_seed


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
