"""The simulator stack a LIBERO evaluation ran on, and the MuJoCo pin it must run on.

MuJoCo >= 3.4 changed box-box collisions, and with it how a stored LIBERO-Spatial initial state settles
(paper, Sec. "Evaluation-Stack Checks"), so evaluating on another version is refused unless the caller
overrides the pin explicitly, and the override is recorded with the versions.
"""

from __future__ import annotations

import importlib.metadata
import warnings

from vlaquantbench.errors import UserError

PINNED_MUJOCO = "3.3.2"  # the main environment's (envs/main.lock.txt); X-VLA's overlay pins 3.1.6


def simulator_versions(allow_mujoco_mismatch: bool = False, pinned: str | None = None) -> dict[str, str | bool]:
    """Versions for a cell header; raises UserError if MuJoCo is not the version the process's
    software environment pins (`vlaquantbench.software_env.active()`), or `pinned` (a cell's `runner.mujoco`)."""
    import mujoco

    from vlaquantbench.software_env import active

    found, pinned = mujoco.__version__, pinned or active().mujoco
    if found != pinned:
        message = (
            f"MuJoCo {found} is installed but LIBERO results are only comparable on MuJoCo {pinned} "
            f"(newer versions change box-box collisions and how init states settle)"
        )
        if not allow_mujoco_mismatch:
            raise UserError(f"{message}: pip install mujoco=={pinned}, or pass allow_mujoco_mismatch=True")
        warnings.warn(f"{message}; continuing because allow_mujoco_mismatch=True", stacklevel=2)
    return {
        "mujoco": found,
        "mujoco_pinned": pinned,
        "mujoco_pin_overridden": found != pinned,
        "robosuite": importlib.metadata.version("robosuite"),
        "hf_libero": importlib.metadata.version("hf-libero"),
    }
