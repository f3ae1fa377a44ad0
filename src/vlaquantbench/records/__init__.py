"""Per-episode records of a cell: this project's folder format and the authors' `.jsonl` layout.

A cell of this project is a folder `<dir>/header.json` + `<dir>/episodes.parquet`; the authors
published `<benchmark>/<suite>/<model>/<cell>.jsonl` (a header line, then one line per episode).
`read_cell` accepts either and returns the same `Cell`.
"""

from vlaquantbench.records.cell import (
    check_declared_episodes,
    contrast_mismatch,
    episode_gaps,
    find_cells,
    read_cell,
    read_checked_cell,
    record_files,
    write_cell,
)
from vlaquantbench.records.episodes import EPISODE_COLUMNS, OPTIONAL_COLUMNS, Cell

__all__ = [
    "EPISODE_COLUMNS",
    "OPTIONAL_COLUMNS",
    "Cell",
    "check_declared_episodes",
    "contrast_mismatch",
    "episode_gaps",
    "find_cells",
    "read_cell",
    "read_checked_cell",
    "record_files",
    "write_cell",
]
