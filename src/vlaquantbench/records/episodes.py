"""The `Cell` record, whatever file it was read from: a provenance header plus one row per episode,
its columns and their dtypes (`normalize_episodes`), shared by the folder format (`records.cell`) and
the authors' importer (`records.authors`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from vlaquantbench.errors import UserError

EPISODE_KEY = ("task_id", "episode", "seed")
EPISODE_COLUMNS = ("suite", "task_id", "episode", "seed", "success", "steps", "init_state_id")
OPTIONAL_COLUMNS = (
    "task_name",
    "wall_time_s",
    "policy_latency_mean_s",  # the authors' records: one control call of one episode
    "policy_batch_latency_mean_s",  # this runner: one batched policy call (every episode in its batch)
    "inference_latency_mean_s",
    "peak_vram_gb",
    "subtasks_completed",
    "progress_score",
    "nonfinite_action",  # the policy output NaN/infinity; the episode ended before it (runner.loop)
    "task_variation",  # Meta-World: the object and goal placement the episode's seeded variation drew
    "action_rate",  # smoothness of the executed actions (records.smoothness)
    "jerk",
)
# Nullable dtypes: benchmarks without official init states (CALVIN, SIMPLER) leave init_state_id empty.
_DTYPES = {
    "suite": "string",
    "task_id": "int64",
    "episode": "int64",
    "seed": "int64",
    "success": "bool",
    "steps": "int64",
    "init_state_id": "Int64",
    "task_name": "string",
    "wall_time_s": "float64",
    "policy_latency_mean_s": "float64",
    "policy_batch_latency_mean_s": "float64",
    "inference_latency_mean_s": "float64",
    "peak_vram_gb": "float64",
    "subtasks_completed": "float64",
    "progress_score": "float64",
    "nonfinite_action": "bool",
    "task_variation": "object",  # a list of floats per episode (parquet list<double>)
    "action_rate": "float64",
    "jerk": "float64",
}


@dataclass(frozen=True)
class Cell:
    header: dict[str, Any]
    episodes: pd.DataFrame
    path: Path

    @property
    def n_episodes(self) -> int:
        return len(self.episodes)

    @property
    def n_successes(self) -> int:
        return int(self.episodes["success"].sum())

    @property
    def n_nonfinite(self) -> int | None:
        """Episodes ended by a non-finite action; None for records that do not say (the authors')."""
        if "nonfinite_action" not in self.episodes.columns:
            return None
        return int(self.episodes["nonfinite_action"].sum())

    @property
    def quantized_layers(self) -> int:
        """Layers quantized over all components, from the header's `quant_report` (#L in the paper)."""
        report = self.header.get("quant_report") or {}
        return sum(int(entry["layers"]) for entry in report.values() if isinstance(entry, dict) and "layers" in entry)


def normalize_episodes(rows: pd.DataFrame | list[dict[str, Any]], source: Path) -> pd.DataFrame:
    """Episode table with the required columns, known dtypes and unique (task_id, episode, seed).

    The casts are safe only on episodes the schema has passed (`check_rows`, the authors' importer):
    pandas casts the string "false" to True.
    """
    frame = rows if isinstance(rows, pd.DataFrame) else pd.DataFrame(rows)
    if frame.empty:
        raise UserError(f"{source}: the cell has no episodes")
    if "init_state_id" not in frame.columns:
        frame = frame.assign(init_state_id=pd.NA)
    missing = [column for column in EPISODE_COLUMNS if column not in frame.columns]
    if missing:
        raise UserError(f"{source}: episodes lack required column(s) {', '.join(missing)}")
    columns = list(EPISODE_COLUMNS) + [c for c in OPTIONAL_COLUMNS if c in frame.columns]
    try:
        frame = frame[columns].astype({c: _DTYPES[c] for c in columns}).reset_index(drop=True)
    except (TypeError, ValueError) as err:
        raise UserError(f"{source}: an episode column has values of the wrong type ({err})") from err
    duplicated = frame.duplicated(list(EPISODE_KEY), keep=False)
    if duplicated.any():
        first = frame.loc[duplicated, list(EPISODE_KEY)].iloc[0].to_dict()
        raise UserError(f"{source}: duplicate episode key (task_id, episode, seed) = {tuple(first.values())}")
    return frame
