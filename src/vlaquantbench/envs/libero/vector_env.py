"""N LIBERO environments stepped in parallel, one worker interpreter per slot (`envs.workers`: the
protocol every benchmark's vector env offers the closed-loop runner).

A LIBERO worker seeds the simulator, loads the episode's official init state and settles with
`settle_steps` no-op actions before its first observation; both camera views render at
`camera_size`.
"""

from __future__ import annotations

from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.libero.benchmark import ACTION_DIM, CAMERA_SIZE, CONTROL_MODES, SETTLE_STEPS
from vlaquantbench.envs.libero.offline import config_dir
from vlaquantbench.envs.libero.suite import LiberoSuite
from vlaquantbench.envs.libero.versions import simulator_versions
from vlaquantbench.envs.libero.worker import EpisodeStart
from vlaquantbench.envs.workers import REPLY_TIMEOUT_S, SlotReply, WorkerError, WorkerVectorEnv, check_worker_settings
from vlaquantbench.errors import UserError

__all__ = ["ACTION_DIM", "CAMERA_SIZE", "CONTROL_MODES", "SETTLE_STEPS", "LiberoVectorEnv", "LiberoWorkerError",
           "SlotReply"]


class LiberoWorkerError(WorkerError):
    """A LIBERO worker failed or died; the message names the slot, task and episode and carries its traceback."""


class LiberoVectorEnv(WorkerVectorEnv):
    """`reset(specs)` starts episodes in the slots given; `step(actions)` advances every live slot
    (`envs.workers.WorkerVectorEnv`). Use as a context manager, or call `close()`.
    """

    benchmark = "libero"
    simulator = "LIBERO"
    action_dim = ACTION_DIM
    worker_main = "import sys; from vlaquantbench.envs.libero.worker import main; main(sys.argv[1:])"
    worker_error = LiberoWorkerError

    def __init__(
        self,
        suite: str | LiberoSuite,
        num_envs: int,
        *,
        camera_size: int = CAMERA_SIZE,
        settle_steps: int = SETTLE_STEPS,
        control_mode: str = "delta",
        mujoco: str | None = None,  # None: the active software environment's pin
        allow_mujoco_mismatch: bool = False,
        reply_timeout_s: float = REPLY_TIMEOUT_S,
    ):
        check_worker_settings(num_envs, reply_timeout_s)
        if camera_size < 1:
            raise UserError(f"camera_size must be a positive number of pixels, got {camera_size}")
        if settle_steps < 0:
            raise UserError(f"settle_steps must not be negative, got {settle_steps}")
        if control_mode not in CONTROL_MODES:
            raise UserError(f"control_mode must be one of {', '.join(CONTROL_MODES)}, got {control_mode!r}")
        self.suite = suite if isinstance(suite, LiberoSuite) else LiberoSuite(suite)
        self.versions = simulator_versions(allow_mujoco_mismatch, pinned=mujoco)
        self.camera_size = camera_size
        self.settle_steps = settle_steps
        self.control_mode = control_mode
        self.reply_timeout_s = reply_timeout_s
        config_dir()  # the workers inherit LIBERO_CONFIG_PATH and MUJOCO_GL
        self._start_workers(num_envs)

    def __enter__(self) -> LiberoVectorEnv:
        return self

    def _worker_args(self) -> list[str]:
        return [str(self.camera_size), str(self.settle_steps), self.control_mode]

    def _load_payload(self, task_id: int) -> str:
        return str(self.suite.task(task_id).bddl_file)

    def _episode_start(self, spec: EpisodeSpec) -> EpisodeStart:
        task = self.suite.task(spec.task_id)
        init_state = self.suite.init_state(spec.task_id, spec.init_state_id)
        return EpisodeStart(spec, str(task.bddl_file), task.instruction, init_state)

    def _episode_label(self, spec: EpisodeSpec) -> str:
        task = self.suite.tasks[spec.task_id]
        return (f"{self.suite.name} task {spec.task_id} ({task.name}) episode {spec.episode}"
                f" (init state {spec.init_state_id}, seed {spec.seed})")
