"""One Meta-World environment in its own interpreter, driven by MetaWorldVectorEnv over a socket.

MetaWorldVectorEnv starts it as `main([FD, CAMERA_SIZE])` (CAMERA_SIZE 0: render no image). Requests
are those of `envs.workers.serve`: `load` builds a task's env, `reset` starts an episode, `step`
applies one action, `chunk` applies a sequence here and replies once with the observation after the
last one, so a camera renders only the image the reply carries.

The env is built as lerobot 0.6.1's `MetaworldEnv` builds it (`lerobot/envs/metaworld.py`): Meta-World's
class of the task with MT1's task set (`SlotSimulator.load`), the `corner2` camera moved to lerobot's position,
the object and goal placement then drawn from the seeded simulator at every reset (not frozen), the
image flipped on both axes, `agent_pos` the first 4 entries of Meta-World's observation (hand
position, gripper opening), success Meta-World's `info["success"]`.
"""

from __future__ import annotations

import os
import pickle
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.metaworld.benchmark import STATE_DIM
from vlaquantbench.envs.workers import become_worker, serve

CAMERA = "corner2"
# lerobot moves `corner2` here (its `MetaworldEnv._ensure_env`): the view its datasets were recorded with.
CORNER2_POSITION = (0.75, 0.075, 0.7)


@dataclass(frozen=True)
class EpisodeStart:
    """What a worker needs to start an episode; the parent resolves the task and the variation's seed."""

    spec: EpisodeSpec
    task: str  # Meta-World's env name
    instruction: str
    variation_seed: int


def flip_image(image: np.ndarray) -> np.ndarray:
    # `corner2` renders with both image axes inverted relative to lerobot's datasets (lerobot's note).
    return np.ascontiguousarray(np.flip(image, (0, 1)))


class SlotSimulator:
    """The env of one slot; rebuilt only when the next episode belongs to another task."""

    def __init__(self, camera_size: int | None):
        self.camera_size = camera_size
        self._env = None
        self._task: str | None = None
        self._instruction = ""

    def load(self, task: str) -> None:
        """Build the env of a task (unless it is the one built). Building takes no seed."""
        if task == self._task:
            return
        self.close()
        from metaworld import Task
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS, ML1_args_kwargs

        render = {"render_mode": "rgb_array", "camera_name": CAMERA, "width": self.camera_size,
                  "height": self.camera_size} if self.camera_size else {"render_mode": None}
        env_class = ALL_V3_ENVIRONMENTS[task]
        env = env_class(**render)
        # The task lerobot sets (`MT1(task, seed=42).train_tasks[0]`), built here rather than by MT1: MT1
        # builds a second env and resets it 50 times to sample goals (2-3 s a task on a loaded 2-core
        # machine, most of an expert benchmark's time) for a placement that the first seeded reset
        # replaces. What `set_task` keeps of MT1's task is the task's own kwargs and MT1's
        # `partially_observable=False` (the goal in the observation); tests/test_metaworld_env.py
        # checks the observation against lerobot's env.
        kwargs = {k: v for k, v in ML1_args_kwargs[task]["kwargs"].items() if k != "task_id"}
        env.set_task(Task(env_name=task, data=pickle.dumps(
            {**kwargs, "env_cls": env_class, "rand_vec": None, "partially_observable": False})))
        env.model.cam_pos[env.model.camera(CAMERA).id] = CORNER2_POSITION
        # Draw each reset's placement from the env's seeded generator instead of the task's frozen one.
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        self._env, self._task = env, task

    def start(self, start: EpisodeStart) -> dict:
        raw = self.reset(start.task, start.variation_seed)
        self._instruction = start.instruction
        observation = self._observation(raw)
        observation["task_variation"] = self.task_variation()
        return observation

    def reset(self, task: str, variation_seed: int) -> np.ndarray:
        """Meta-World's observation after a reset of `task` to the placement `variation_seed` draws."""
        self.load(task)
        self._env.seed(variation_seed)
        raw, _ = self._env.reset()
        return raw

    def task_variation(self) -> np.ndarray:
        """The object and goal placement (Meta-World's `rand_vec`) the last reset drew."""
        return np.array(self._env._last_rand_vec, dtype=np.float64)

    def step(self, action: np.ndarray) -> tuple[dict, bool]:
        observation, _, success = self.chunk(action[None])
        return observation, success

    def chunk(self, actions: np.ndarray) -> tuple[dict, int, bool]:
        """Apply `actions` in order, stopping early on success: (observation, actions applied, success)."""
        if len(actions) == 0:
            raise ValueError("a chunk needs at least one action")
        applied, success = 0, False
        for action in actions:
            raw, _, _, _, info = self._env.step(action)
            applied += 1
            success = bool(info["success"])
            if success:
                break
        return self._observation(raw), applied, success

    def _observation(self, raw: np.ndarray) -> dict:
        observation = {
            "state": raw[:STATE_DIM].astype(np.float64),
            # Meta-World's whole observation (hand, gripper, object poses, goal): what its scripted
            # experts read, as lerobot's `environment_state`.
            "environment_state": raw.astype(np.float64),
            "instruction": self._instruction,
            "task": self._task,
        }
        if self.camera_size:
            observation["image"] = flip_image(self._env.render())
        return observation

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        self._env = None
        self._task = None


def serve_metaworld(conn: Connection, camera_size: int | None) -> None:
    def open_simulator():
        import metaworld  # noqa: F401  (Meta-World and MuJoCo load before the start-up reply)

        simulator = SlotSimulator(camera_size)
        handlers = {"load": simulator.load, "reset": simulator.start, "step": simulator.step, "chunk": simulator.chunk}
        return handlers, simulator.close

    serve(conn, open_simulator)


def main(argv: list[str]) -> None:
    become_worker()
    # Headless rendering (what lerobot's and LIBERO's evaluations use); set before MuJoCo loads.
    os.environ.setdefault("MUJOCO_GL", "egl")
    fd, camera_size = (int(arg) for arg in argv[:2])
    serve_metaworld(Connection(fd), camera_size or None)
