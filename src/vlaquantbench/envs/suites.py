"""Every benchmark's suites and their sizes, hard step limits and worker footprints, known without
importing a simulator (`envs` checks cell references with them while the workflow builds the DAG;
`envs.memory` sizes worker pools by them)."""

from __future__ import annotations

from dataclasses import dataclass

from vlaquantbench.envs.episodes import TASK_SEED_STRIDE


@dataclass(frozen=True)
class Horizon:
    """A simulator's hard limit on one episode: `steps` env steps, after which it refuses to step on (it raises
    from inside the simulator, naming no setting), the settle steps after a reset included where
    `counts_settle_steps` (a benchmark whose env settles, `runner.settle_steps`)."""

    steps: int
    source: str  # where the limit is set, in words
    counts_settle_steps: bool = False


@dataclass(frozen=True)
class SuiteSize:
    tasks: int  # task ids 0..tasks-1, in the benchmark's task order
    init_states: int  # initial states (LIBERO) or seeded task variations (Meta-World) per task, ids 0..init_states-1
    worker_gib: float  # memory of one simulator worker process (envs.memory), measured as noted below
    # Env steps the simulator takes in one episode before it refuses another (`Horizon`): the most steps any
    # setting may ask of an episode.
    horizon: Horizon
    # Policy steps before an unfinished episode counts as a failure, whatever the model (Meta-World's); None:
    # each model's client declares its own (LIBERO's, `models/<model>/client.py` STEP_LIMITS).
    step_limit: int | None = None


# worker_gib, LIBERO: the largest proportional set size (PSS, psutil's memory_full_info; shared libraries counted
# once across workers) of a LIBERO worker (camera 256, MuJoCo 3.3.2, MUJOCO_GL=egl) after an episode reset and a
# 10-action chunk, measured on the 2-core x86-64 development machine (2026-12-04): fresh workers on every task
# of the suite, and one worker that built each task in turn (rebuilding leaves up to 0.5 GiB behind: LIBERO-10
# task 4 holds 2.35 GiB fresh, 2.86 after the other nine), rounded up to 0.1 GiB. Spatial, Object, Goal, 10: fresh
# maxima 1.80, 1.94, 1.53, 2.35 GiB; after the cycle 1.85, 2.10, 1.68, 2.86. An idle worker interpreter holds 0.1 GiB. The
# 64-worker H200 benchmark's host held about 1.7 GB per worker (benchmarks/results/closed_loop_gpu_64_mem.log).
# Meta-World, the same way on MT10's first task: 0.16 GiB without a camera, 0.34 GiB rendering 224 px; 0.4 allowed.
# Its variations are seeds below TASK_SEED_STRIDE (`envs.metaworld.suite`); task counts are lerobot's groups and
# Meta-World's MT10 / MT50 lists.
# Meta-World's `max_path_length` (its envs refuse to step further), which lerobot's
# `MetaworldEnv._max_episode_steps` and so lerobot-eval's rollouts use.
METAWORLD_STEP_LIMIT = 500
# LIBERO's `OffScreenRenderEnv` (robosuite) ends an episode at its horizon, 1000 env steps after the reset, and
# refuses any further step ("executing action in terminated episode"): the settle steps count.
LIBERO_HORIZON = Horizon(1000, "LIBERO's env horizon, settle steps included: robosuite refuses to step on",
                         counts_settle_steps=True)
METAWORLD_HORIZON = Horizon(METAWORLD_STEP_LIMIT, "Meta-World's max_path_length: it refuses to step on")
_METAWORLD_TASKS = {"metaworld_easy": 28, "metaworld_medium": 11, "metaworld_hard": 6, "metaworld_very_hard": 5,
                    "metaworld_mt10": 10, "metaworld_mt50": 50}
BENCHMARK_SUITES = {
    "libero": {
        "libero_spatial": SuiteSize(tasks=10, init_states=50, worker_gib=1.9, horizon=LIBERO_HORIZON),
        "libero_object": SuiteSize(tasks=10, init_states=50, worker_gib=2.1, horizon=LIBERO_HORIZON),
        "libero_goal": SuiteSize(tasks=10, init_states=50, worker_gib=1.7, horizon=LIBERO_HORIZON),
        "libero_10": SuiteSize(tasks=10, init_states=50, worker_gib=2.9, horizon=LIBERO_HORIZON),
    },
    "metaworld": {suite: SuiteSize(tasks=tasks, init_states=TASK_SEED_STRIDE, worker_gib=0.4, horizon=METAWORLD_HORIZON,
                              step_limit=METAWORLD_STEP_LIMIT)
                  for suite, tasks in _METAWORLD_TASKS.items()},
}
