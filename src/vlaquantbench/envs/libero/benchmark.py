"""LIBERO declares itself (`envs.registry`): its four suites, their sizes and worker footprints, its
horizon, its env settings (`LiberoSettings`) and its action and state sizes (`LiberoSettings`). No simulator import: the workflow reads this while it builds the DAG."""

from __future__ import annotations

from dataclasses import dataclass, field

from vlaquantbench.envs.registry import Benchmark, Horizon, SuiteSize, register_benchmark

# No-op steps after loading an init state, as in lerobot's LiberoEnv and openpi's LIBERO client.
SETTLE_STEPS = 10
CAMERA_SIZE = 256  # the render size of lerobot's and openpi's LIBERO evaluation
# "delta": actions are end-effector pose deltas (LIBERO's default); "absolute": absolute targets, the
# worker switching the controller to `use_delta=False` after the settle steps, as X-VLA's client does.
CONTROL_MODES = ("delta", "absolute")
ACTION_DIM = 7  # end-effector position and axis-angle deltas (or targets), and the gripper command
STATE_DIM = 8  # end-effector position (3), axis-angle (3) and the gripper's two finger joints (`worker.format_observation`)


@dataclass(frozen=True)
class LiberoSettings:
    """LIBERO's env settings: what a cell's runner config (`study.runner`, `study.models.<model>.runner`) may set
    for a LIBERO cell, each the keyword-only parameter of `LiberoVectorEnv` of the same name; the defaults are a
    LIBERO cell's where its config sets none (and its model's client neither: controller mode, MuJoCo pin)."""

    # both views, square, in pixels; below 16 the policies' processors have nothing to resize
    camera_size: int = field(default=CAMERA_SIZE, metadata={"schema": {"minimum": 16}})
    # no-op steps after loading an init state, before the first observation
    settle_steps: int = field(default=SETTLE_STEPS, metadata={"schema": {"minimum": 0}})
    # the arm controller; a cell's comes from its model's client unless its config sets it
    control_mode: str = field(default="delta", metadata={"schema": {"enum": list(CONTROL_MODES)}})
    mujoco: str | None = None  # the MuJoCo version the cell must run on (None: the software environment's pin)

# worker_gib, LIBERO: the largest proportional set size (PSS, psutil's memory_full_info; shared libraries counted
# once across workers) of a LIBERO worker (camera 256, MuJoCo 3.3.2, MUJOCO_GL=egl) after an episode reset and a
# 10-action chunk, measured on the 2-core x86-64 development machine (2026-12-04): fresh workers on every task
# of the suite, and one worker that built each task in turn (rebuilding leaves up to 0.5 GiB behind: LIBERO-10
# task 4 holds 2.35 GiB fresh, 2.86 after the other nine), rounded up to 0.1 GiB. Spatial, Object, Goal, 10: fresh
# maxima 1.80, 1.94, 1.53, 2.35 GiB; after the cycle 1.85, 2.10, 1.68, 2.86. An idle worker interpreter holds 0.1 GiB. The
# 64-worker H200 benchmark's host held about 1.7 GB per worker (benchmarks/results/closed_loop_gpu_64_mem.log).
# LIBERO's `OffScreenRenderEnv` (robosuite) ends an episode at its horizon, 1000 env steps after the reset, and
# refuses any further step ("executing action in terminated episode"): the settle steps count.
LIBERO_HORIZON = Horizon(1000, "LIBERO's env horizon, settle steps included: robosuite refuses to step on",
                         counts_settle_steps=True)
LIBERO = register_benchmark(Benchmark(
    name="libero",
    suites={
        "libero_spatial": SuiteSize(tasks=10, init_states=50, worker_gib=1.9, horizon=LIBERO_HORIZON),
        "libero_object": SuiteSize(tasks=10, init_states=50, worker_gib=2.1, horizon=LIBERO_HORIZON),
        "libero_goal": SuiteSize(tasks=10, init_states=50, worker_gib=1.7, horizon=LIBERO_HORIZON),
        "libero_10": SuiteSize(tasks=10, init_states=50, worker_gib=2.9, horizon=LIBERO_HORIZON),
    },
    suite_class="vlaquantbench.envs.libero.suite:LiberoSuite",
    env_class="vlaquantbench.envs.libero.vector_env:LiberoVectorEnv",
    simulator_versions="vlaquantbench.envs.libero.versions:simulator_versions",
    cameras={"main": "agentview", "wrist": "wrist"},  # both rotated 180 degrees, as LIBERO's clients read them
    settings=LiberoSettings,
    action_dim=ACTION_DIM,
    state_dim=STATE_DIM,
))
