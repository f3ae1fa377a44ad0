"""The contract benchmark declares itself (`vlaquantbench.envs.registry`): one suite of two tasks, five seeded goal
placements each, its own horizon and step limit, one camera, its env settings and its action and state sizes. No simulator import."""

from __future__ import annotations

from dataclasses import dataclass, field

from vlaquantbench.envs.registry import Benchmark, Horizon, SuiteSize, register_benchmark

NAME = "contract"
SUITE = "contract_reach"
HORIZON_STEPS = 60  # the worker refuses a step beyond it, as Meta-World refuses past max_path_length
STEP_LIMIT = 40  # policy steps before an unfinished episode fails, whatever the model
CAMERA_SIZE = 48
SUCCESS_RADIUS = 0.05  # metres: an episode succeeds once the hand is this close to the goal
ACTION_DIM = 4  # Meta-World's: xyz and a gripper entry (ignored)
STATE_DIM = 4  # hand xyz and the gripper (always 0): Meta-World's first four entries


@dataclass(frozen=True)
class ContractSettings:
    """The env settings a cell of this benchmark takes (keyword-only parameters of `ContractVectorEnv`)."""

    camera_size: int | None = CAMERA_SIZE  # the `main` camera, square, in pixels; None: no image rendered
    mujoco: str | None = None  # the MuJoCo version the cell must run on (None: the software environment's pin)
    # A setting of its own, which no runner option names: a config sets it as `study.runner.success_radius`.
    success_radius: float = field(default=SUCCESS_RADIUS, metadata={"schema": {"exclusiveMinimum": 0}})


CONTRACT = register_benchmark(Benchmark(
    name=NAME,
    suites={SUITE: SuiteSize(tasks=2, init_states=5, worker_gib=0.2,
                             horizon=Horizon(HORIZON_STEPS, "the contract scene's worker: it refuses to step on"),
                             step_limit=STEP_LIMIT)},
    suite_class="contract_benchmark.suite:ContractSuite",
    env_class="contract_benchmark.vector_env:ContractVectorEnv",
    simulator_versions="contract_benchmark.vector_env:simulator_versions",
    cameras={"main": "overhead"},  # a key no adapter knows: policies find the image by its role
    settings=ContractSettings,
    action_dim=ACTION_DIM,
    state_dim=STATE_DIM,
))
