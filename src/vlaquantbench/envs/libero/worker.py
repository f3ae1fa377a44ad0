"""One LIBERO environment in its own interpreter, driven by LiberoVectorEnv over a socket.

LiberoVectorEnv starts it as `main([FD, CAMERA_SIZE, SETTLE_STEPS, CONTROL_MODE])` in a fresh interpreter. Requests are
`(command, payload)` pairs; every request gets one reply, `("ok", result)` or `("error", traceback)`.
`reset` starts an episode, `step` applies one action, `chunk` applies a sequence of actions here, in
the worker, and replies once with the observation after the last one: a chunk costs one round trip
instead of one per action, and no intermediate observation crosses the socket.
"""

from __future__ import annotations

import signal
import traceback
from dataclasses import dataclass
from multiprocessing.connection import Connection

import numpy as np

from vlaquantbench.envs.libero.offline import load_libero
from vlaquantbench.envs.libero.suite import EpisodeSpec

# LIBERO's no-op: arm still (zero delta pose), gripper open (-1). Used to let objects settle after an
# init state is loaded, as lerobot's LiberoEnv (num_steps_wait=10) and openpi's LIBERO client do.
DUMMY_ACTION = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)
# "delta": actions are end-effector pose deltas (LIBERO's default); "absolute": absolute targets, the
# controller switched to `use_delta=False` after the settle steps, as X-VLA's client does.
CONTROL_MODES = ("delta", "absolute")


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
        raw = self._env.set_init_state(start.init_state)
        for _ in range(self.settle_steps):
            raw, _, _, _ = self._env.step(DUMMY_ACTION)
        for robot in self._env.env.robots:  # the settle no-ops are deltas in every mode
            robot.controller.use_delta = self.control_mode == "delta"
        return format_observation(raw, self._instruction)

    def step(self, action: np.ndarray) -> tuple[dict, bool]:
        raw, _, done, _ = self._env.step(action)
        # LIBERO's done flag is its task-success predicate.
        return format_observation(raw, self._instruction), bool(done)

    def chunk(self, actions: np.ndarray) -> tuple[dict, int, bool]:
        """Apply `actions` in order, stopping early on success: (observation, actions applied, success)."""
        if len(actions) == 0:
            raise ValueError("a chunk needs at least one action")
        applied, done = 0, False
        for action in actions:
            raw, _, done, _ = self._env.step(action)
            applied += 1
            if done:
                break
        return format_observation(raw, self._instruction), applied, bool(done)

    def close(self) -> None:
        if self._env is not None:
            self._env.close()
        self._env = None
        self._bddl_file = None


def serve(conn: Connection, camera_size: int, settle_steps: int, control_mode: str = "delta") -> None:
    try:
        load_libero()
        import libero.libero.envs  # noqa: F401  (robosuite and MuJoCo load before the start-up reply)
    except Exception:
        conn.send(("error", traceback.format_exc()))
        return
    simulator = SlotSimulator(camera_size, settle_steps, control_mode)
    handlers = {"load": simulator.load, "reset": simulator.start, "step": simulator.step, "chunk": simulator.chunk}
    conn.send(("ok", None))
    try:
        while True:
            try:
                command, payload = conn.recv()
            except EOFError:  # the parent is gone
                return
            if command == "close":
                return
            try:
                reply = ("ok", handlers[command](payload))
            except Exception:
                reply = ("error", traceback.format_exc())
            try:
                conn.send(reply)
            except OSError:  # the parent closed its end while we were working
                return
    finally:
        simulator.close()


def main(argv: list[str]) -> None:
    # Ctrl-C reaches the whole process group; the parent decides and closes its workers.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    fd, camera_size, settle_steps = (int(arg) for arg in argv[:3])
    serve(Connection(fd), camera_size, settle_steps, argv[3])
