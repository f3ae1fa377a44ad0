"""What the Snakemake rules ask of a validated config, in one place.

A cell is named by a reference `<benchmark>/<suite>/<model>/<cell>` in the authors' naming
(e.g. `libero/libero_spatial/pi05/ablate-W4A4-ah-onlyself_attn`). With `records_dir` set, its
records are read from there (the authors' `<ref>.jsonl` or this project's `<ref>/` folder);
without it, the DAG produces the cell under `results/cells/<config-hash>/`.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from vlaquantbench.errors import UserError


@dataclass(frozen=True)
class WorkflowConfig:
    raw: dict[str, Any]
    basedir: Path

    @classmethod
    def from_snakemake(cls, config: dict[str, Any], basedir: str | Path) -> "WorkflowConfig":
        return cls(raw=config, basedir=Path(basedir))

    @property
    def records_dir(self) -> Path | None:
        value = self.raw.get("records_dir")
        return Path(value) if value else None

    @property
    def manifest(self) -> Path | None:
        value = self.raw.get("manifest")
        return Path(value) if value else None

    def table_definition(self, name: str) -> dict[str, Any]:
        path = self.basedir / "config" / "tables" / f"{name}.yaml"
        if not path.exists():
            raise UserError(f"unknown table {name!r}: no {path}")
        return yaml.safe_load(path.read_text())
