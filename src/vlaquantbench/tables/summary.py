"""`summary.csv`: one row per cell with the authors' summary columns and number formatting."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import pandas as pd

from vlaquantbench.atomic import atomic_write
from vlaquantbench.records import Cell, read_checked_cell
from vlaquantbench.stats import wilson_interval

# The authors' results/summary.csv columns, in order.
SUMMARY_COLUMNS = (
    "benchmark", "suite", "model", "cell", "method", "preset", "scope", "seed", "checkpoint",
    "episodes", "successes", "success_rate", "ci_low", "ci_high", "mean_subtasks", "mean_progress",
)  # fmt: skip
# This project's, after them where any cell was stopped by the sequential rule (study.sequential): its decision
# and the episodes its test used (empty for a fixed-design cell). A fixed-design study's file keeps the authors' format.
STOPPING_COLUMNS = ("sequential_decision", "sequential_episodes_used")
_MEANS = {"mean_subtasks": "subtasks_completed", "mean_progress": "progress_score"}


def summary_row(ref: str, cell: Cell) -> dict[str, object]:
    benchmark, suite, model, name = ref.split("/")
    n, k = cell.n_episodes, cell.n_successes
    low, high = wilson_interval(k, n)
    row: dict[str, object] = {
        "benchmark": benchmark,
        "suite": suite,
        "model": model,
        "cell": name,
        **{field: cell.header.get(field) for field in ("method", "preset", "scope", "seed", "checkpoint")},
        "episodes": n,
        "successes": k,
        "success_rate": round(100.0 * k / n, 2),
        "ci_low": round(float(low), 2),
        "ci_high": round(float(high), 2),
    }
    stopping = cell.header.get("stopping") or {}
    row["sequential_decision"] = stopping.get("decision")
    row["sequential_episodes_used"] = stopping.get("episodes_used")
    for column, field in _MEANS.items():
        values = cell.episodes[field].dropna() if field in cell.episodes else ()
        row[column] = round(float(values.mean()), 3) if len(values) else None
    return row


def summarize(cells: Mapping[str, Cell]) -> pd.DataFrame:
    # The authors list cells in the order of their record file paths (`<ref>.jsonl`), where
    # `rtn-W4A4-ah-x.jsonl` sorts before `rtn-W4A4-ah.jsonl`; keeping it makes rows comparable line by line.
    ordered = sorted(cells.items(), key=lambda item: f"{item[0]}.jsonl")
    stopped = any(cell.header.get("stopping") for cell in cells.values())
    frame = pd.DataFrame([summary_row(ref, cell) for ref, cell in ordered],
                         columns=list(SUMMARY_COLUMNS) + list(STOPPING_COLUMNS if stopped else ()))
    # A count, empty for the fixed-design cells (not a float column because of them).
    return frame.astype({"sequential_episodes_used": "Int64"}) if stopped else frame


def write_summary(cell_paths: Mapping[str, str | Path], output: str | Path) -> Path:
    """Read every cell (reference -> record path) and write the summary CSV with CRLF line ends, as the authors do."""
    frame = summarize({ref: read_checked_cell(ref, path) for ref, path in cell_paths.items()})
    with atomic_write(output, newline="") as handle:
        frame.to_csv(handle, index=False, lineterminator="\r\n")
    return Path(output)
