"""`summary.csv`: one row per cell with the authors' summary columns and number formatting."""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import pandas as pd

from vlaquantbench.atomic import atomic_write
from vlaquantbench.errors import UserError
from vlaquantbench.records import Cell, read_checked_cell
from vlaquantbench.sequential import contrast_at_stop, ran_in_full, rate_at_stop
from vlaquantbench.stats import wilson_interval

# The authors' results/summary.csv columns, in order.
SUMMARY_COLUMNS = (
    "benchmark", "suite", "model", "cell", "method", "preset", "scope", "seed", "checkpoint",
    "episodes", "successes", "success_rate", "ci_low", "ci_high", "mean_subtasks", "mean_progress",
)  # fmt: skip
# This project's, after them where any cell ran under the sequential rule (study.sequential): its decision, the
# episodes its test used, and its success rate and its difference (pp) with the cell it was tested against, paired
# over the rounds the test read, each with its anytime-valid 95% confidence sequence there (`anytime_cs`); all
# empty for a fixed-design cell. `ci_low`/`ci_high` are the authors' fixed-sample Wilson bounds, empty for a cell
# the rule stopped before its cap. A fixed-design study's file keeps the authors' format.
STOPPING_COLUMNS = ("sequential_decision", "sequential_episodes_used", "rate_anytime_cs_low", "rate_anytime_cs_high",
                    "sequential_against", "delta_at_stop_pp", "delta_anytime_cs_low_pp", "delta_anytime_cs_high_pp")
_MEANS = {"mean_subtasks": "subtasks_completed", "mean_progress": "progress_score"}


def _at_stop(ref: str, cell: Cell, cells: Mapping[str, Cell]) -> dict[str, object]:
    """The STOPPING_COLUMNS of a cell (empty for a fixed-design one)."""
    stopping = cell.header.get("stopping")
    if not stopping:
        return {}
    against = stopping["against"]  # its reference
    if against not in cells:
        raise UserError(f"cell {ref} ran under the stopping rule against {against}, which is not among the summary's cells")
    rate = rate_at_stop(cell.episodes, cell.header)
    contrast = contrast_at_stop(cell.episodes, cell.header, cells[against].episodes)
    return {"sequential_decision": stopping["decision"], "sequential_episodes_used": stopping["episodes_used"],
            "rate_anytime_cs_low": round(rate.low, 2), "rate_anytime_cs_high": round(rate.high, 2),
            "sequential_against": against.rsplit("/", 1)[1], "delta_at_stop_pp": round(contrast.estimate, 2),
            "delta_anytime_cs_low_pp": round(contrast.low, 2), "delta_anytime_cs_high_pp": round(contrast.high, 2)}


def summary_row(ref: str, cell: Cell, cells: Mapping[str, Cell]) -> dict[str, object]:
    benchmark, suite, model, name = ref.split("/")
    n, k = cell.n_episodes, cell.n_successes
    # Wilson's is a fixed-sample interval: none for a cell whose sample size its data chose.
    low, high = wilson_interval(k, n) if ran_in_full(cell.header) else (None, None)
    row: dict[str, object] = {
        "benchmark": benchmark,
        "suite": suite,
        "model": model,
        "cell": name,
        **{field: cell.header.get(field) for field in ("method", "preset", "scope", "seed", "checkpoint")},
        "episodes": n,
        "successes": k,
        "success_rate": round(100.0 * k / n, 2),
        "ci_low": None if low is None else round(float(low), 2),
        "ci_high": None if high is None else round(float(high), 2),
        **_at_stop(ref, cell, cells),
    }
    for column, field in _MEANS.items():
        values = cell.episodes[field].dropna() if field in cell.episodes else ()
        row[column] = round(float(values.mean()), 3) if len(values) else None
    return row


def summarize(cells: Mapping[str, Cell]) -> pd.DataFrame:
    # The authors list cells in the order of their record file paths (`<ref>.jsonl`), where
    # `rtn-W4A4-ah-x.jsonl` sorts before `rtn-W4A4-ah.jsonl`; keeping it makes rows comparable line by line.
    ordered = sorted(cells.items(), key=lambda item: f"{item[0]}.jsonl")
    stopped = any(cell.header.get("stopping") for cell in cells.values())
    frame = pd.DataFrame([summary_row(ref, cell, cells) for ref, cell in ordered],
                         columns=list(SUMMARY_COLUMNS) + list(STOPPING_COLUMNS if stopped else ()))
    # A count, empty for the fixed-design cells (not a float column because of them).
    return frame.astype({"sequential_episodes_used": "Int64"}) if stopped else frame


def write_summary(cell_paths: Mapping[str, str | Path], output: str | Path) -> Path:
    """Read every cell (reference -> record path) and write the summary CSV with CRLF line ends, as the authors do."""
    frame = summarize({ref: read_checked_cell(ref, path) for ref, path in cell_paths.items()})
    with atomic_write(output, newline="") as handle:
        frame.to_csv(handle, index=False, lineterminator="\r\n")
    return Path(output)
