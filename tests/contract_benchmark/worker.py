"""One contract scene in its own interpreter, driven by ContractVectorEnv over a socket (`envs.workers.serve`).

ContractVectorEnv starts it as `main([FD, CAMERA_SIZE, SUCCESS_RADIUS])` (camera 0: render no image). The scene is MuJoCo XML written
here: a sphere ("hand") on three slide joints with position actuators, no gravity, and a goal site. An action is
Meta-World's: xyz moves the actuators' target by `ACTION_SCALE` per unit (clipped to [-1, 1]), the fourth
(gripper) entry is ignored. Success: the hand within the success radius (the benchmark's env setting) of the goal."""

from __future__ import annotations

import os
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from contract_benchmark.benchmark import HORIZON_STEPS, STATE_DIM
from contract_benchmark.suite import HAND_START
from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.workers import become_worker, serve

SCENE = """
<mujoco model="contract_reach">
  <option timestep="0.002" gravity="0 0 0"/>
  <worldbody>
    <light pos="0 0 2" dir="0 0 -1"/>
    <geom type="plane" size="1 1 0.01" rgba="0.8 0.8 0.8 1"/>
    <camera name="main" pos="0 -1.0 0.8" xyaxes="1 0 0 0 0.6 0.8"/>
    <body name="hand" pos="{x} {y} {z}">
      <joint name="x" type="slide" axis="1 0 0" damping="20"/>
      <joint name="y" type="slide" axis="0 1 0" damping="20"/>
      <joint name="z" type="slide" axis="0 0 1" damping="20"/>
      <geom type="sphere" size="0.03" mass="0.5" rgba="0.2 0.3 0.9 1" contype="0" conaffinity="0"/>
    </body>
    <!-- placed at each reset; not at the world frame, so MuJoCo computes its pose instead of sharing the body's -->
    <site name="goal" pos="{x} {y} {z}" size="0.03" rgba="0.9 0.1 0.1 1"/>
  </worldbody>
  <actuator>
    <position joint="x" kp="200"/>
    <position joint="y" kp="200"/>
    <position joint="z" kp="200"/>
  </actuator>
</mujoco>
""".format(x=HAND_START[0], y=HAND_START[1], z=HAND_START[2])
ACTION_SCALE = 0.02  # metres of target motion per unit action (Meta-World moves its mocap 0.01)
SUBSTEPS = 10  # physics steps per policy step (0.02 s)


@dataclass(frozen=True)
class EpisodeStart:
    spec: EpisodeSpec
    task: str
    instruction: str
    goal: tuple[float, ...]


class SlotScene:
    def __init__(self, camera_size: int | None, success_radius: float):
        import mujoco

        self.mujoco = mujoco
        self.camera_size = camera_size
        self.success_radius = success_radius
        self.model = mujoco.MjModel.from_xml_string(SCENE)
        self.data = mujoco.MjData(self.model)
        self.renderer = mujoco.Renderer(self.model, camera_size, camera_size) if camera_size else None
        self.task, self.instruction, self.steps = "", "", 0
        self.previous = np.zeros(3)

    def load(self, task: str) -> None:
        """One scene serves every task: nothing to build."""

    def start(self, start: EpisodeStart) -> dict:
        self.mujoco.mj_resetData(self.model, self.data)
        self.model.site_pos[self.model.site("goal").id] = start.goal
        self.mujoco.mj_forward(self.model, self.data)
        self.task, self.instruction, self.steps = start.task, start.instruction, 0
        self.previous = self.hand.copy()
        observation = self._observation()
        observation["task_variation"] = np.asarray(start.goal, dtype=np.float64)
        return observation

    @property
    def hand(self) -> np.ndarray:
        return self.data.body("hand").xpos.copy()

    @property
    def goal(self) -> np.ndarray:
        return self.data.site("goal").xpos.copy()

    def chunk(self, actions: np.ndarray) -> tuple[dict, int, bool]:
        if len(actions) == 0:
            raise ValueError("a chunk needs at least one action")
        applied, success = 0, False
        for action in actions:
            if self.steps >= HORIZON_STEPS:
                raise ValueError(f"the episode is over: {HORIZON_STEPS} steps is the contract scene's horizon")
            self.previous = self.hand
            self.data.ctrl[:] = self.data.ctrl + ACTION_SCALE * np.clip(action[:3], -1.0, 1.0)
            self.mujoco.mj_step(self.model, self.data, nstep=SUBSTEPS)
            self.steps += 1
            applied += 1
            success = bool(np.linalg.norm(self.hand - self.goal) < self.success_radius)
            if success:
                break
        return self._observation(), applied, success

    def step(self, action: np.ndarray) -> tuple[dict, bool]:
        observation, _, success = self.chunk(action[None])
        return observation, success

    def _observation(self) -> dict:
        # Meta-World's layout: hand (3), gripper (1), two object slots (14), the previous frame's 18, the goal (3)
        frame = lambda hand: np.concatenate([hand, [0.0], np.zeros(14)])  # noqa: E731
        environment_state = np.concatenate([frame(self.hand), frame(self.previous), self.goal])
        observation = {"state": environment_state[:STATE_DIM], "environment_state": environment_state,
                       "instruction": self.instruction, "task": self.task}
        if self.renderer is not None:
            self.renderer.update_scene(self.data, camera="main")
            observation["overhead"] = self.renderer.render().copy()
        return observation

    def close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None


def main(argv: list[str]) -> None:
    become_worker()
    os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering; set before MuJoCo loads
    fd, camera_size, success_radius = int(argv[0]), int(argv[1]), float(argv[2])

    def open_simulator():
        scene = SlotScene(camera_size or None, success_radius)
        return {"load": scene.load, "reset": scene.start, "step": scene.step, "chunk": scene.chunk}, scene.close

    serve(Connection(fd), open_simulator)
