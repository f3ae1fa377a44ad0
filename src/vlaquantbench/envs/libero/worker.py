"""One LIBERO environment in its own interpreter, driven by LiberoVectorEnv over a socket.

LiberoVectorEnv starts it as `main([FD, CAMERA_SIZE, SETTLE_STEPS, CONTROL_MODE])` in a fresh interpreter. Requests are
`(command, payload)` pairs; every request gets one reply, `("ok", result)` or `("error", traceback)`.
`reset` starts an episode, `step` applies one action, `chunk` applies a sequence of actions here, in
the worker, and replies once with the observation after the last one: a chunk costs one round trip
instead of one per action, no intermediate observation crosses the socket, and each camera renders
only the image that observation carries (`SlotSimulator.chunk`; a start's settle no-ops likewise).
"""

from __future__ import annotations

from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from vlaquantbench.envs.episodes import EpisodeSpec
from vlaquantbench.envs.libero.offline import load_libero
from vlaquantbench.envs.workers import become_worker, serve

# LIBERO's no-op: arm still (zero delta pose), gripper open (-1). Used to let objects settle after an
# init state is loaded, as lerobot's LiberoEnv (num_steps_wait=10) and openpi's LIBERO client do.
DUMMY_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)


def sampled_again(timer: float, period: float, substep: float, substeps_left: int) -> bool:
    """Whether a robosuite observable that samples now samples again within `substeps_left` more substeps.

    Mirrors `robosuite.utils.observables.Observable.update` without delay, with the same float
    operations: each substep adds `substep` to the timer; a timer at or past `period` wraps, and the
    substep after a wrap samples. `timer` is the value of the substep sampling now. Which substep of
    a step samples depends on the timer's history (a reset's forced updates advance it; float drift
    can move it across a step's boundary), so it is followed, not assumed."""
    for _ in range(substeps_left):
        if timer >= period:
            return True
        timer += substep
    return False


@dataclass(frozen=True)
class EpisodeStart:
    """What a worker needs to start an episode; the parent resolves task files and the init state."""

    spec: EpisodeSpec
    bddl_file: str
    instruction: str
    init_state: np.ndarray


def rotate_180(image: np.ndarray) -> np.ndarray:
    # LIBERO's cameras render upside down relative to the training data the policies saw.
    return np.ascontiguousarray(image[::-1, ::-1])


def format_observation(raw: dict, instruction: str) -> dict:
    """Contract 6: both views rotated 180 degrees, state = eef pos + axis-angle + gripper qpos."""
    from robosuite.utils.transform_utils import quat2axisangle

    state = np.concatenate(
        [raw["robot0_eef_pos"], quat2axisangle(raw["robot0_eef_quat"].copy()), raw["robot0_gripper_qpos"]]
    )
    return {
        "agentview": rotate_180(raw["agentview_image"]),
        "wrist": rotate_180(raw["robot0_eye_in_hand_image"]),
        "state": state.astype(np.float32),
        "instruction": instruction,
    }


class SlotSimulator:
    """The env of one slot; rebuilt only when the next episode belongs to another task."""

    def __init__(self, camera_size: int, settle_steps: int, control_mode: str = "delta"):
        self.camera_size = camera_size
        self.settle_steps = settle_steps
        self.control_mode = control_mode
        self._env = None
        self._bddl_file: str | None = None
        self._instruction = ""
        # While actions run as one chunk (a policy's chunk, or the settle no-ops of a start): (simulation
        # time at its start, its substeps). A camera then renders only the sample that no later sample
        # of the chunk overwrites.
        self._chunk: tuple[float, int] | None = None

    def load(self, bddl_file: str) -> None:
        """Build the env of a task (unless it is the one built): what `start` does first, so that a
        runner can have it done while it loads its policy. Building takes no seed or state."""
        if bddl_file != self._bddl_file:
            self.close()
            from libero.libero.envs import OffScreenRenderEnv

            self._env = OffScreenRenderEnv(
                bddl_file_name=bddl_file,
                camera_heights=self.camera_size,
                camera_widths=self.camera_size,
            )
            self._bddl_file = bddl_file

    def start(self, start: EpisodeStart) -> dict:
        self.load(start.bddl_file)
        self._instruction = start.instruction
        # Seed first, then load the indexed init state: the seed never picks a different init state.
        self._env.seed(start.spec.seed)
        self._env.reset()
        self._gate_camera_renders()  # a hard reset re-creates the sensors
        raw = self._env.set_init_state(start.init_state)
        if self.settle_steps:
            # Rendered as a chunk: only the settled observation's images are rendered.
            raw, _, _ = self._apply(np.tile(DUMMY_ACTION, (self.settle_steps, 1)), stop_on_success=False)
        for robot in self._env.env.robots:  # the settle no-ops are deltas in every mode
            robot.controller.use_delta = self.control_mode == "delta"
        return format_observation(raw, self._instruction)

    def step(self, action: np.ndarray) -> tuple[dict, bool]:
        raw, _, done, _ = self._env.step(action)
        # LIBERO's done flag is its task-success predicate.
        return format_observation(raw, self._instruction), bool(done)

    def chunk(self, actions: np.ndarray) -> tuple[dict, int, bool]:
        """Apply `actions` in order, stopping early on success: (observation, actions applied, success).

        Each camera renders once, the sample that the final observation carries, so the observation
        equals stepping every action with rendering on; after an early success its images may be an
        earlier sample's (the episode is over: no policy sees them)."""
        if len(actions) == 0:
            raise ValueError("a chunk needs at least one action")
        raw, applied, done = self._apply(actions, stop_on_success=True)
        return format_observation(raw, self._instruction), applied, done

    def _apply(self, actions: np.ndarray, stop_on_success: bool) -> tuple[dict, int, bool]:
        """Step `actions` with each camera rendering only the last sample it takes: (robosuite's last
        observation, actions applied, LIBERO's success flag after the last)."""
        robosuite_env = self._env.env
        # Substeps per step as robosuite's step loop counts them.
        substeps = len(actions) * int(robosuite_env.control_timestep / robosuite_env.model_timestep)
        self._chunk = (robosuite_env.sim.data.time, substeps)
        applied, done = 0, False
        try:
            for action in actions:
                raw, _, done, _ = self._env.step(action)
                applied += 1
                if done and stop_on_success:
                    break
        finally:
            self._chunk = None
        return raw, applied, bool(done)

    def _overwritten_later(self, observable) -> bool:
        """Whether the sample `observable` takes now is replaced by another before the running chunk ends."""
        if self._chunk is None:
            return False
        began, substeps = self._chunk
        robosuite_env = self._env.env
        done = round((robosuite_env.sim.data.time - began) / robosuite_env.model_timestep)
        return sampled_again(observable._time_since_last_sample, observable._sampling_timestep,
                             robosuite_env.model_timestep, substeps - done)

    def _gate_camera_renders(self) -> None:
        """Wrap each camera sensor: inside a chunk, a sample that a later one overwrites returns the cached
        image instead of rendering. Prediction needs the sampling instants fixed: no sampling delay."""
        from robosuite.utils.observables import NO_DELAY, sensor

        robosuite_env = self._env.env
        for name, observable in robosuite_env._observables.items():
            if observable.modality != "image":
                continue
            if observable._delayer is not NO_DELAY:
                raise ValueError(f"camera observable {name!r} samples with a delay: its renders cannot be "
                                 "skipped exactly; configure it without one")
            render = observable._sensor

            @sensor(modality="image")
            def gated(obs_cache, name=name, render=render, observable=observable):
                if name in obs_cache and self._overwritten_later(observable):
                    return obs_cache[name]
                return render(obs_cache)

            robosuite_env.modify_observable(name, "sensor", gated)

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        self._env = None
        self._bddl_file = None


def serve_libero(conn: Connection, camera_size: int, settle_steps: int, control_mode: str = "delta") -> None:
    def open_simulator():
        load_libero()
        import libero.libero.envs  # noqa: F401  (robosuite and MuJoCo load before the start-up reply)

        simulator = SlotSimulator(camera_size, settle_steps, control_mode)
        handlers = {"load": simulator.load, "reset": simulator.start, "step": simulator.step, "chunk": simulator.chunk}
        return handlers, simulator.close

    serve(conn, open_simulator)


def main(argv: list[str]) -> None:
    become_worker()
    fd, camera_size, settle_steps = (int(arg) for arg in argv[:3])
    serve_libero(Connection(fd), camera_size, settle_steps, argv[3])
