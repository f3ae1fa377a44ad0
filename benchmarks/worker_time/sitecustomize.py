"""Times where LIBERO workers spend their time, in every interpreter started with this folder on
PYTHONPATH and WORKER_TIME_DIR set (`closed_loop.py` sets both for its workers).

Wraps, on import, robosuite's render context (`render`: scene update and draw calls; `read_pixels`:
the read that waits for the GPU; `__init__`: a GL context and its MuJoCo context, made at every hard
reset), robosuite's `reset` and `step` (a control step; with the MuJoCo physics steps inside it,
`physics`), LIBERO's `set_init_state` and the worker's `SlotSimulator.start` and
`.chunk`; each call's start (perf_counter, comparable across processes), wall and thread CPU seconds
go to WORKER_TIME_DIR/PID.npy (rewritten every 4,000 records and at exit). Measurement only: the wrapped
methods run unchanged.
"""

import atexit
import importlib.abc
import importlib.util
import os
import sys
import time

DIR = os.environ.get("WORKER_TIME_DIR")
KINDS = ("render", "read_pixels", "start", "chunk", "reset", "render_context", "set_init_state", "step", "physics")
STEP, PHYSICS = KINDS.index("step"), KINDS.index("physics")
HOOKS = {  # module -> (class, method, kind)
    "robosuite.utils.binding_utils": [("MjRenderContext", "render", 0), ("MjRenderContext", "read_pixels", 1),
                                      ("MjRenderContext", "__init__", 5), ("MjSim", "step", PHYSICS)],
    "vlaquantbench.envs.libero.worker": [("SlotSimulator", "start", 2), ("SlotSimulator", "chunk", 3)],
    "robosuite.environments.base": [("MujocoEnv", "reset", 4), ("MujocoEnv", "step", STEP)],
    "libero.libero.envs.env_wrapper": [("ControlEnv", "set_init_state", 6)],
}
records: list[tuple[int, float, float, float]] = []  # kind, start, wall s, thread CPU s
dumped = [0]  # records written so far


def dump() -> None:
    import numpy as np

    if records:
        np.save(os.path.join(DIR, f"{os.getpid()}.npy"), np.array(records, dtype=np.float64))
        dumped[0] = len(records)


physics = [0.0, 0.0]  # wall and thread-CPU seconds of every MjSim.step so far


def summed(fn, kind: int):
    """MuJoCo's physics steps (25 per control step) are summed, not recorded one by one: each control
    step's record ("step") is followed by one of the physics inside it ("physics")."""

    def wrapper(*args, **kwargs):
        began, cpu = time.perf_counter(), time.thread_time()
        try:
            return fn(*args, **kwargs)
        finally:
            physics[0] += time.perf_counter() - began
            physics[1] += time.thread_time() - cpu

    return wrapper


def timed(fn, kind: int):
    def wrapper(*args, **kwargs):
        began, cpu = time.perf_counter(), time.thread_time()
        physics_before = tuple(physics)
        try:
            return fn(*args, **kwargs)
        finally:
            records.append((kind, began, time.perf_counter() - began, time.thread_time() - cpu))
            if kind == STEP:
                records.append((PHYSICS, began, physics[0] - physics_before[0], physics[1] - physics_before[1]))
            if len(records) - dumped[0] >= 4000:
                dump()

    return wrapper


class Finder(importlib.abc.MetaPathFinder):
    """Loads each hooked module as usual, then wraps its methods."""

    busy = False

    def find_spec(self, name, path, target=None):
        if name not in HOOKS or Finder.busy:
            return None
        Finder.busy = True
        try:
            spec = importlib.util.find_spec(name)
        finally:
            Finder.busy = False
        load = spec.loader.exec_module

        def exec_module(module):
            load(module)
            for class_name, method, kind in HOOKS[name]:
                cls = getattr(module, class_name)
                setattr(cls, method, (summed if kind == PHYSICS else timed)(getattr(cls, method), kind))

        spec.loader.exec_module = exec_module
        return spec


if DIR:
    sys.meta_path.insert(0, Finder())
    atexit.register(dump)
