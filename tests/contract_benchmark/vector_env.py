"""N contract scenes stepped in parallel, one worker interpreter per slot (`vlaquantbench.envs.workers`)."""

from __future__ import annotations

from contract_benchmark.benchmark import ACTION_DIM, CAMERA_SIZE, NAME, SUCCESS_RADIUS
from contract_benchmark.suite import ContractSuite
from contract_benchmark.worker import EpisodeStart
from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.mujoco_pin import mujoco_versions
from vlaquantbench.envs.workers import REPLY_TIMEOUT_S, WorkerError, WorkerVectorEnv, check_worker_settings
from vlaquantbench.errors import UserError


class ContractWorkerError(WorkerError):
    """A contract worker failed or died."""


def simulator_versions(pinned: str | None = None) -> dict:
    """What a cell header records: the MuJoCo pin, checked (`envs.mujoco_pin`)."""
    return mujoco_versions("the contract scene", False, pinned)


class ContractVectorEnv(WorkerVectorEnv):
    """Observations: `state` (hand xyz, gripper 0), `environment_state` (Meta-World's 39-dim layout), `instruction`,
    `task`, `overhead` (the `main` camera) unless `camera_size` is None, and at reset `task_variation` (the goal)."""

    benchmark = NAME
    simulator = "contract scene"
    action_dim = ACTION_DIM
    worker_main = "import sys; from contract_benchmark.worker import main; main(sys.argv[1:])"
    worker_error = ContractWorkerError

    def __init__(self, suite: str | ContractSuite, num_envs: int, *, camera_size: int | None = CAMERA_SIZE,
                 mujoco: str | None = None, success_radius: float = SUCCESS_RADIUS,
                 reply_timeout_s: float = REPLY_TIMEOUT_S):
        check_worker_settings(num_envs, reply_timeout_s)
        if camera_size is not None and camera_size < 1:
            raise UserError(f"camera_size must be a positive number of pixels or None (no image), got {camera_size}")
        if not success_radius > 0:
            raise UserError(f"success_radius must be a positive distance in metres, got {success_radius}")
        self.suite = suite if isinstance(suite, ContractSuite) else ContractSuite(suite)
        self.versions = simulator_versions(pinned=mujoco)
        self.camera_size = camera_size
        self.success_radius = success_radius
        self.reply_timeout_s = reply_timeout_s
        self._start_workers(num_envs)

    def _worker_args(self) -> list[str]:
        return [str(self.camera_size or 0), repr(float(self.success_radius))]

    def _load_payload(self, task_id: int) -> str:
        return self.suite.task(task_id).name

    def _episode_start(self, spec: EpisodeSpec) -> EpisodeStart:
        task = self.suite.task(spec.task_id)
        return EpisodeStart(spec, task.name, task.instruction, self.suite.task_variation(spec))

    def _episode_label(self, spec: EpisodeSpec) -> str:
        return f"{self.suite.name} task {spec.task_id} episode {spec.episode} (goal {spec.init_state_id}, seed {spec.seed})"
