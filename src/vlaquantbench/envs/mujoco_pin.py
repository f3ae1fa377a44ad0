"""The MuJoCo pin every MuJoCo benchmark runs on, checked when a cell reads its simulator versions.

MuJoCo >= 3.4 changed box-box collisions, and with it how a stored initial state settles
(paper, Sec. "Evaluation-Stack Checks"), so evaluating on another version than the software environment's
(or the cell's `runner.mujoco`) is refused unless the caller overrides the pin explicitly, and the
override is recorded with the versions.
"""

from __future__ import annotations

import warnings

from vlaquantbench.errors import UserError


def mujoco_versions(simulator: str, allow_mujoco_mismatch: bool = False, pinned: str | None = None) -> dict[str, str | bool]:
    """`mujoco`, `mujoco_pinned`, `mujoco_pin_overridden` for a cell header; UserError if MuJoCo is not the
    version the process's software environment pins (`vlaquantbench.software_env.active()`), or `pinned`."""
    import mujoco

    from vlaquantbench.software_env import active

    found, pinned = mujoco.__version__, pinned or active().mujoco
    if found != pinned:
        message = (
            f"MuJoCo {found} is installed but {simulator} results are only comparable on MuJoCo {pinned} "
            f"(newer versions change box-box collisions and how init states settle)"
        )
        if not allow_mujoco_mismatch:
            raise UserError(f"{message}: pip install mujoco=={pinned}, or pass allow_mujoco_mismatch=True")
        warnings.warn(f"{message}; continuing because allow_mujoco_mismatch=True", stacklevel=3)
    return {"mujoco": found, "mujoco_pinned": pinned, "mujoco_pin_overridden": found != pinned}
