"""Meta-World declares itself (`envs.registry`): lerobot's task groups and MT10 / MT50, their sizes, its
500-step limit, worker footprint, env settings (`MetaWorldSettings`), action and state sizes and scripted experts, whose demonstrations the
trained policy learns from. No simulator import: the workflow reads this while it builds the DAG."""

from __future__ import annotations

from dataclasses import dataclass, field

from vlaquantbench.envs.episodes import TASK_SEED_STRIDE
from vlaquantbench.envs.registry import Benchmark, Horizon, ScriptedExpert, SuiteSize, register_benchmark

# worker_gib: measured as LIBERO's (envs/libero/benchmark.py), on MT10's first task: 0.16 GiB without a camera, 0.34 GiB rendering 224 px; 0.4 allowed.
# Its variations are seeds below TASK_SEED_STRIDE (`envs.metaworld.suite`); task counts are lerobot's groups and
# Meta-World's MT10 / MT50 lists.
# Meta-World's `max_path_length` (its envs refuse to step further), which lerobot's
# `MetaworldEnv._max_episode_steps` and so lerobot-eval's rollouts use.
METAWORLD_STEP_LIMIT = 500
# lerobot's MetaworldEnv renders Meta-World's default 480 x 480 frames (its policies' processors resize).
CAMERA_SIZE = 480
# lerobot's `MetaworldEnv.fps` (lerobot.envs.configs, which is not light to import): the frame rate of a
# dataset recorded from Meta-World.
LEROBOT_FPS = 80
ACTION_DIM = 4  # end-effector xyz delta and gripper effort, each in [-1, 1] (lerobot's action space)
STATE_DIM = 4  # lerobot's `agent_pos`: hand xyz and gripper opening


@dataclass(frozen=True)
class MetaWorldSettings:
    """Meta-World's env settings: what a cell's runner config may set for a Meta-World cell, each the keyword-only
    parameter of `MetaWorldVectorEnv` of the same name. It has no settle steps and no controller mode: a config
    that sets `settle_steps` or `control_mode` for a Meta-World cell is refused (`envs.check_settings`)."""

    # `corner2`, square, in pixels (a cell's where its config sets none); None: no image rendered
    camera_size: int | None = field(default=CAMERA_SIZE, metadata={"schema": {"minimum": 16}})
    mujoco: str | None = None  # the MuJoCo version the cell must run on (None: the software environment's pin)


METAWORLD_HORIZON = Horizon(METAWORLD_STEP_LIMIT, "Meta-World's max_path_length: it refuses to step on")
_TASKS = {"metaworld_easy": 28, "metaworld_medium": 11, "metaworld_hard": 6, "metaworld_very_hard": 5,
          "metaworld_mt10": 10, "metaworld_mt50": 50}
METAWORLD = register_benchmark(Benchmark(
    name="metaworld",
    suites={suite: SuiteSize(tasks=tasks, init_states=TASK_SEED_STRIDE, worker_gib=0.4, horizon=METAWORLD_HORIZON,
                             step_limit=METAWORLD_STEP_LIMIT)
            for suite, tasks in _TASKS.items()},
    suite_class="vlaquantbench.envs.metaworld.suite:MetaWorldSuite",
    env_class="vlaquantbench.envs.metaworld.vector_env:MetaWorldVectorEnv",
    simulator_versions="vlaquantbench.envs.metaworld.vector_env:simulator_versions",
    cameras={"main": "image"},  # corner2, as lerobot's Meta-World env renders it; no wrist camera
    settings=MetaWorldSettings,
    action_dim=ACTION_DIM,
    state_dim=STATE_DIM,
    scripted_expert=ScriptedExpert(
        model="metaworld_expert",  # metaworld.policies' hand-written controllers, one a task
        suite="metaworld_mt50",  # every task there has its expert
        fps=LEROBOT_FPS,
        robot_type="sawyer",
        state_names=("hand_x", "hand_y", "hand_z", "gripper"),  # lerobot's `agent_pos`
        # End-effector position deltas and the gripper effort. The experts' xyz gains overshoot (up to ~5), which
        # `SawyerXYZEnv.set_xyz_action` clips to [-1, 1]: the demonstrations record the clipped action.
        action_names=("dx", "dy", "dz", "gripper"),
    ),
))
