"""The `training` section of a workflow config (rule train_policy), typed: built once where the config is
loaded (rules/training.smk, a benchmark that reads the section), checked by the rules of the config schema's
`training` property, the same ones the YAML is validated with. Defaults live here; the schema says what is
allowed."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

from vlaquantbench.config import validate


@dataclass(frozen=True)
class TrainingConfig:
    model: str  # the model folder whose `trained` and `task_tokenizer` modules build and save the policy
    output: str  # the checkpoint folder written (`models.trained_home`: policy/, tokenizer/, training.json)
    checkpoint_repo: str  # the name training.json gives the checkpoint
    tokenizer_repo: str  # the name its task tokenizer is saved and loaded under
    device: str
    seed: int
    steps: int
    batch_size: int
    log_every: int  # steps between log lines, each the one wait for the device in that span
    # The model folder's own settings (`models.<model>.trained.build_policy`: chunk, normalization, optimizer,
    # widths), checked by the schema's `training.policy`. Kept as the mapping the config gives, in its key
    # order: training.json records it verbatim, so the same section writes the same file.
    policy: dict[str, Any]
    time_limit_s: float | None = None  # None: no limit (the run ends at `steps`)
    precision: str = "float32"
    compile_mode: str | None = None  # None: eager
    cuda_graph: bool = False
    random_shift_px: int = 0

    def __post_init__(self):
        # A section built in code (a test, `dataclasses.replace`) is held to the YAML's rules too.
        validate(self.as_dict(), "config", f"training section (output {self.output!r})", subschema=("training",))

    @classmethod
    def from_dict(cls, raw: dict[str, Any], where: str = "workflow config") -> TrainingConfig:
        """The typed section; UserError `<where>: training.<field>: ...` for an unknown key or a value the
        schema refuses, before any field is read."""
        validate(raw, "config", where, subschema=("training",))
        return cls(**raw)

    def as_dict(self) -> dict[str, Any]:
        """The section with every default spelled out (what the rule hands its job: Snakemake reruns the
        training when it changes); `from_dict` reads it back."""
        return dataclasses.asdict(self)
