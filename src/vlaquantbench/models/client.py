"""Each model's released LIBERO client conventions, and the cell values that deviate from them.

The paper evaluates every checkpoint under its own released inference client (Sec. 5): how many of
the predicted actions are executed before observing again, how many episodes a task gets, whether
LIBERO's arm controller takes delta or absolute end-effector poses, the MuJoCo version the client's
environment pins, and the fixed model seed of a deterministic head. Step limits per suite are the
other client constant; they live with the suite (`envs.libero.suite.STEP_LIMITS`).

A model's `client.py` declares `CLIENT`; `cells.cell_config` fills a cell's runner from it and
records every value the study sets differently under `overrides` in the cell config (and so in the
header). Adapters and the runner then check that what runs is what the cell says.
"""

from __future__ import annotations

import dataclasses
import importlib
from dataclasses import dataclass


@dataclass(frozen=True)
class ClientConventions:
    executed_chunk: int  # actions executed per predicted chunk
    episodes_per_task: int
    control_mode: str  # LIBERO arm controller: "delta" or "absolute" end-effector poses
    mujoco: str  # the MuJoCo version the client's environment pins
    model_seed: int | None = None  # fixed model seed of a deterministic head (None: per-episode streams)
    source: str = ""  # where the values come from

    def runner(self) -> dict:
        """The runner options these conventions set (hashed with the cell)."""
        return {"executed_chunk": self.executed_chunk, "control_mode": self.control_mode, "mujoco": self.mujoco}

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


def client_conventions(model: str) -> ClientConventions:
    """`CLIENT` of the model's `client.py`; UserError for an unknown model."""
    from vlaquantbench.models.registry import model_package

    return importlib.import_module(f"{model_package(model)}.client").CLIENT
