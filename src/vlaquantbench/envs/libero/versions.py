"""The simulator stack a LIBERO evaluation ran on, and the MuJoCo pin it must run on (`envs.mujoco_pin`)."""

from __future__ import annotations

import importlib.metadata

from vlaquantbench.envs.mujoco_pin import mujoco_versions

PINNED_MUJOCO = "3.3.2"  # the main environment's (envs/main.lock.txt); X-VLA's overlay pins 3.1.6


def simulator_versions(allow_mujoco_mismatch: bool = False, pinned: str | None = None) -> dict[str, str | bool]:
    """Versions for a cell header; raises UserError if MuJoCo is not the version the process's
    software environment pins (`vlaquantbench.software_env.active()`), or `pinned` (a cell's `runner.mujoco`)."""
    return {
        **mujoco_versions("LIBERO", allow_mujoco_mismatch, pinned),
        "robosuite": importlib.metadata.version("robosuite"),
        "hf_libero": importlib.metadata.version("hf-libero"),
    }
