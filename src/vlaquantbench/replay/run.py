"""One configuration's replay output on disk: `<config>.json` (summary in the authors' layout)
beside `<config>.npz` (per-trajectory arrays keyed `<record>/<array>`).

Arrays per trajectory (record):
  chunks       [calls, horizon, action_dims]  predicted normalized chunks
  actions      [steps, action_dims]           executed environment actions, cached ones included
  flow_states  [calls, flow_steps, horizon, state_dims]  state entering each denoising step
  downproj     [calls, layers, len(DOWNPROJ_COLUMNS)]      down_proj input statistics per call
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlaquantbench.atomic import atomic_write, write_text
from vlaquantbench.errors import UserError
from vlaquantbench.textfiles import read_parsed

ARRAYS = ("chunks", "actions", "flow_states", "downproj")


def arrays_file(summary_path: str | Path) -> Path:
    """Where a replay's arrays live by default: `<config>.npz` beside `<config>.json`."""
    return Path(summary_path).with_suffix(".npz")


@dataclass
class ReplayRun:
    summary: dict
    arrays: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)  # record -> name -> array

    @property
    def name(self) -> str:
        return self.summary["config"]

    def record_names(self) -> list[str]:
        return [r["record"] for r in self.summary["records"]]

    def stacked(self, array: str) -> np.ndarray:
        """One array concatenated over trajectories in record order (chunks nest in trajectories)."""
        return np.concatenate([self.arrays[r][array] for r in self.record_names()])

    def save(self, summary_path: str | Path, arrays_path: str | Path | None = None) -> Path:
        """Write the summary to `summary_path` (named `<config>.json`) and the arrays to `arrays_path`
        (default: `arrays_file(summary_path)`); returns the summary's path."""
        summary_path = Path(summary_path)
        if summary_path.stem != self.name:
            raise UserError(f"replay output {summary_path} must be named after its configuration {self.name!r}")
        flat = {f"{rec}/{k}": v for rec, arrays in self.arrays.items() for k, v in arrays.items()}
        with atomic_write(arrays_path or arrays_file(summary_path), "wb") as handle:
            np.savez_compressed(handle, **flat)
        return write_text(summary_path, json.dumps(self.summary, indent=1))

    @classmethod
    def load(cls, summary_path: str | Path, arrays_path: str | Path | None = None) -> "ReplayRun":
        summary_path = Path(summary_path)
        summary = read_parsed(summary_path, json.loads, "JSON")
        npz = Path(arrays_path or arrays_file(summary_path))
        if not npz.exists():
            raise UserError(f"replay {summary_path} has no arrays file {npz}")
        arrays: dict[str, dict[str, np.ndarray]] = {}
        with np.load(npz) as data:
            for key in data.files:
                record, name = key.rsplit("/", 1)
                arrays.setdefault(record, {})[name] = data[key]
        missing = [r for r in (x["record"] for x in summary["records"]) if r not in arrays]
        if missing:
            raise UserError(f"{npz} lacks arrays for records {missing}")
        return cls(summary, arrays)


