"""Cells known only from a per-cell summary (the authors' `summary.csv` columns), not from episodes.

The paper reports many cells whose per-episode records are not published here; their counts come
from the authors' summary. A `SummaryCell` offers what a table can honestly compute from one
summary row (episodes, successes, CALVIN mean subtasks, VLABench mean progress) and refuses the
rest (layer counts, bootstrap contrasts) by name.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any

import pandas as pd

from vlaquantbench.errors import UserError

KEY_COLUMNS = ("benchmark", "suite", "model", "cell")
REQUIRED_COLUMNS = (*KEY_COLUMNS, "episodes", "successes")
HEADER_COLUMNS = ("method", "preset", "scope", "seed", "checkpoint")
MEAN_COLUMNS = ("mean_subtasks", "mean_progress")


@dataclass(frozen=True)
class SummaryCell:
    ref: str
    n_episodes: int
    n_successes: int
    means: dict[str, float] = field(default_factory=dict)  # mean_subtasks / mean_progress where recorded
    header: dict[str, Any] = field(default_factory=dict)
    path: Path = Path()
    episodes = None  # no per-episode records
    n_nonfinite = None  # not recorded

    @property
    def quantized_layers(self) -> int:
        raise UserError(f"cell {self.ref}: layer counts need its run header; the summary {self.path} has none")


def read_summary(path: str | Path) -> dict[str, SummaryCell]:
    """Every row of a summary CSV as a `SummaryCell`, keyed by `<benchmark>/<suite>/<model>/<cell>`."""
    return dict(_read(Path(path).resolve()))


@lru_cache(maxsize=None)
def _read(path: Path) -> tuple[tuple[str, SummaryCell], ...]:
    if not path.is_file():
        raise UserError(f"summary {path} does not exist")
    try:
        frame = pd.read_csv(path)
    except (ValueError, pd.errors.ParserError) as err:  # pandas' messages name no file
        raise UserError(f"summary {path} is not a readable CSV file ({err})") from None
    missing = [column for column in REQUIRED_COLUMNS if column not in frame.columns]
    if missing:
        raise UserError(f"summary {path} lacks column(s) {', '.join(missing)}")
    cells = []
    for number, row in enumerate(frame.to_dict("records"), start=2):
        ref = "/".join(str(row[column]) for column in KEY_COLUMNS)
        try:
            episodes, successes = int(row["episodes"]), int(row["successes"])
        except (TypeError, ValueError) as err:
            raise UserError(f"{path}:{number}: cell {ref} has non-integer episodes/successes ({err})") from err
        if not 0 <= successes <= episodes or episodes == 0:
            raise UserError(f"{path}:{number}: cell {ref} has {successes} successes of {episodes} episodes")
        means = {column: float(row[column]) for column in MEAN_COLUMNS if column in row and pd.notna(row[column])}
        header = {column: row[column] for column in HEADER_COLUMNS if column in row}
        cells.append((ref, SummaryCell(ref, episodes, successes, means, {**header, "source": "summary"}, path)))
    return tuple(cells)
