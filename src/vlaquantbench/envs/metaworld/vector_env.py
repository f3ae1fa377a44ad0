"""N Meta-World environments stepped in parallel, one worker interpreter per slot (`envs.workers`:
the protocol every benchmark's vector env offers the closed-loop runner).

Rendering costs 80-115 ms a 224-pixel frame on a loaded 2-core CPU against about 1 ms a physics
step, so a worker renders only what a policy reads: with `camera_size=None` no image is rendered
at all (a policy that reads the state only, e.g. the scripted experts), and inside a chunk only the
observation the reply carries is rendered.
"""

from __future__ import annotations

import importlib.metadata

from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.metaworld.benchmark import ACTION_DIM, CAMERA_SIZE
from vlaquantbench.envs.metaworld.suite import MetaWorldSuite
from vlaquantbench.envs.metaworld.worker import EpisodeStart
from vlaquantbench.envs.mujoco_pin import mujoco_versions
from vlaquantbench.envs.workers import REPLY_TIMEOUT_S, WorkerError, WorkerVectorEnv, check_worker_settings
from vlaquantbench.errors import UserError


class MetaWorldWorkerError(WorkerError):
    """A Meta-World worker failed or died; the message names the slot, task and episode and carries its traceback."""


def simulator_versions(allow_mujoco_mismatch: bool = False, pinned: str | None = None) -> dict[str, str | bool]:
    """Versions for a cell header; UserError if MuJoCo is not the software environment's pin, or `pinned`
    (a cell's `runner.mujoco`), as for LIBERO (`envs.mujoco_pin`)."""
    return {**mujoco_versions("Meta-World", allow_mujoco_mismatch, pinned),
            **{name: importlib.metadata.version(name) for name in ("metaworld", "gymnasium")}}


class MetaWorldVectorEnv(WorkerVectorEnv):
    """`reset(specs)` starts episodes in the slots given; `step(actions)` advances every live slot
    (`envs.workers.WorkerVectorEnv`). Observations: `state` (lerobot's 4-dim `agent_pos`),
    `environment_state` (Meta-World's whole observation), `instruction`, `task` (the env name),
    `image` (`corner2`, `camera_size` pixels square, lerobot's orientation) unless `camera_size` is
    None, and at reset `task_variation` (the episode's object and goal placement).
    """

    benchmark = "metaworld"
    simulator = "Meta-World"
    action_dim = ACTION_DIM
    worker_main = "import sys; from vlaquantbench.envs.metaworld.worker import main; main(sys.argv[1:])"
    worker_error = MetaWorldWorkerError

    def __init__(
        self,
        suite: str | MetaWorldSuite,
        num_envs: int,
        *,
        camera_size: int | None = CAMERA_SIZE,
        mujoco: str | None = None,  # None: the active software environment's pin
        reply_timeout_s: float = REPLY_TIMEOUT_S,
    ):
        check_worker_settings(num_envs, reply_timeout_s)
        if camera_size is not None and camera_size < 1:
            raise UserError(f"camera_size must be a positive number of pixels or None (no image), got {camera_size}")
        self.suite = suite if isinstance(suite, MetaWorldSuite) else MetaWorldSuite(suite)
        self.versions = simulator_versions(pinned=mujoco)
        self.camera_size = camera_size
        self.reply_timeout_s = reply_timeout_s
        self._start_workers(num_envs)

    def __enter__(self) -> MetaWorldVectorEnv:
        return self

    def _worker_args(self) -> list[str]:
        return [str(self.camera_size or 0)]

    def _load_payload(self, task_id: int) -> str:
        return self.suite.task(task_id).name

    def _episode_start(self, spec: EpisodeSpec) -> EpisodeStart:
        task = self.suite.task(spec.task_id)
        return EpisodeStart(spec, task.name, task.instruction, self.suite.variation_seed(spec.task_id, spec.init_state_id))

    def _episode_label(self, spec: EpisodeSpec) -> str:
        task = self.suite.tasks[spec.task_id]
        return (f"{self.suite.name} task {spec.task_id} ({task.name}) episode {spec.episode}"
                f" (variation {spec.init_state_id}, seed {spec.seed})")
