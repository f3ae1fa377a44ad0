"""This project's cell folder (`header.json` + `episodes.parquet`): reading, writing and finding cells;
`read_cell` also reads the authors' `.jsonl` (`records.authors`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from vlaquantbench.atomic import atomic_write, write_text
from vlaquantbench.errors import UserError
from vlaquantbench.records.authors import read_authors_jsonl
from vlaquantbench.records.episodes import EPISODE_KEY, Cell, normalize_episodes
from vlaquantbench.records.schema import EpisodeCheck, declared_tasks, present
from vlaquantbench.textfiles import read_parsed

HEADER_FILE = "header.json"
EPISODES_FILE = "episodes.parquet"
# The run's journal of finished episodes (runner.journal), kept beside them until the cell completes.
JOURNAL_FILE = "journal.jsonl"
AUTHORS_SUFFIX = ".jsonl"

def episode_gaps(cell: Cell) -> list[str]:
    """What the header declares but the episodes lack: per task, episode indices 0..n-1 with no hole and
    n at most the header's `episodes_per_task`; where the header lists its tasks (this project's cells,
    under `config.tasks`), every listed task present with exactly `episodes_per_task` episodes.

    A cell may hold fewer episodes per task than declared when its protocol ran fewer (the authors' X-VLA
    cells have 19 or 20 per task under `episodes_per_task: 20`): the tables state such counts from the data.
    A cell whose header records a sequential stop (`stopping`) must hold exactly `stopping.rounds_run`
    episodes on every task; a short cell without one is a gap as before.
    """
    declared = cell.header.get("episodes_per_task")
    tasks = declared_tasks(cell.header)  # this project's cells list them
    gaps = []
    # A cell the sequential rule stopped (runner.stopping) holds its whole rounds run: that many per task.
    stopping = cell.header.get("stopping")
    per_task = declared
    if stopping:
        per_task = stopping["rounds_run"]
        if not stopping["rounds_used"] <= per_task <= int(declared):
            gaps.append(f"stopping: {stopping['rounds_used']} rounds used and {per_task} run do not fit "
                        f"episodes_per_task {declared}")
    by_task = cell.episodes.groupby("task_id")["episode"].apply(lambda e: sorted(int(i) for i in e)).to_dict()
    for task in tasks or ():
        if int(task) not in by_task:
            gaps.append(f"task {task} (listed in the header) has no episodes")
    for task, episodes in sorted(by_task.items()):
        expected = range(int(per_task)) if (tasks or stopping) and per_task else range(episodes[-1] + 1)
        missing = sorted(set(expected) - set(episodes))
        if missing:
            gaps.append(f"task {task} lacks episode(s) {', '.join(map(str, missing))}")
        if declared is not None and len(episodes) > int(declared):
            gaps.append(f"task {task} has {len(episodes)} episodes, the header declares {declared} per task")
    return gaps


def check_declared_episodes(cell: Cell) -> Cell:
    """Refuse a cell whose episodes do not match what its header declares (see `episode_gaps`), naming the file."""
    gaps = episode_gaps(cell)
    if gaps:
        raise UserError(f"{cell.path}: episodes do not match the header: {'; '.join(gaps)}")
    return cell


def row_location(path: Path, number: int, row: dict[str, Any]) -> str:
    """Where episode `row` sits in a parquet file: `<path> row N (task t, episode e, seed s)`."""
    key = ", ".join(f"{'task' if field == 'task_id' else field} {row.get(field)}" for field in EPISODE_KEY)
    return f"{path} row {number} ({key})"


def check_rows(header: dict[str, Any], rows: list[dict[str, Any]], header_source: Path, path: Path) -> None:
    """Refuse the first row of `rows` (episodes of `path`) that breaks the episode schema its header bounds."""
    check = EpisodeCheck(header, header_source)
    for number, row in enumerate(rows, start=1):
        check(present(row), row_location(path, number, row))


def read_checked_cell(ref: str, path: str | Path) -> Cell:
    """Cell `ref` (`<benchmark>/<suite>/<model>/<cell>`) as a table or figure reads it: its episodes pass the
    schema, match what the header declares (`episode_gaps`), and the header names the ref's benchmark, suite
    and model. A rendering job checks its own records so that a refusal fails the job writing the output
    (and Snakemake removes that output)."""
    cell = check_declared_episodes(read_cell(path))
    if ":" in ref:  # a measurement file in the records' format (`<source>:<path>`, workflow.is_source_ref) names no cell
        return cell
    for field, expected in zip(("benchmark", "suite", "model"), ref.split("/")[:3]):
        if cell.header.get(field) != expected:
            raise UserError(f"{cell.path}: its header says {field} {cell.header.get(field)!r}, but it is read as cell {ref}")
    return cell


def read_cell(path: str | Path) -> Cell:
    """Read a cell from the authors' `.jsonl`, a cell folder, or the `episodes.parquet` inside one."""
    path = Path(path)
    if path.suffix == AUTHORS_SUFFIX:
        return read_authors_jsonl(path)
    folder = path.parent if path.name == EPISODES_FILE else path
    header_path, episodes_path = folder / HEADER_FILE, folder / EPISODES_FILE
    for required in (header_path, episodes_path):
        if not required.is_file():
            raise UserError(f"{path}: not a cell record: {required} is missing")
    header = read_parsed(header_path, json.loads, "JSON")
    table = _read_parquet(episodes_path)
    check_rows(header, table.to_pylist(), header_path, episodes_path)
    return Cell(header=header, episodes=normalize_episodes(table.to_pandas(), episodes_path), path=folder)


def _read_parquet(path: Path):
    """The parquet table at `path`; an unreadable file is a UserError naming it (pandas handed Arrow a buffer,
    so Arrow's message named `<Buffer>`, not the file)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        return pq.read_table(path)
    except (pa.ArrowException, OSError) as err:
        raise UserError(f"{path}: not a readable parquet file ({err})") from None


def write_cell(folder: str | Path, header: dict[str, Any], episodes: pd.DataFrame | list[dict[str, Any]]) -> Cell:
    """Write a cell folder atomically: each file goes to a temporary name first, then is renamed.
    Header and episodes are checked against the record schemas first: nothing is written if they fail.

    The episodes file is written last, so its presence (the file the workflow waits for) implies a
    complete header next to it.
    """
    folder = Path(folder)
    rows = episodes.to_dict("records") if isinstance(episodes, pd.DataFrame) else episodes
    check_rows(header, rows, folder / HEADER_FILE, folder / EPISODES_FILE)
    frame = normalize_episodes(episodes, folder / EPISODES_FILE)
    write_header(folder, header)
    with atomic_write(folder / EPISODES_FILE, "wb") as handle:
        frame.to_parquet(handle, index=False)
    return Cell(header=header, episodes=frame, path=folder)


def write_header(folder: str | Path, header: dict[str, Any]) -> Path:
    """Write a cell folder's header.json atomically, in the one layout every header has."""
    return write_text(Path(folder) / HEADER_FILE, json.dumps(header, indent=2, sort_keys=True) + "\n")


def record_files(path: str | Path) -> list[Path]:
    """The files that make up one cell's record (what a manifest lists for it)."""
    path = Path(path)
    if path.suffix == AUTHORS_SUFFIX:
        return [path]
    folder = path.parent if path.name == EPISODES_FILE else path
    return [folder / HEADER_FILE, folder / EPISODES_FILE]


def find_cells(records_dir: str | Path) -> dict[str, Path]:
    """Every cell under `records_dir`, keyed by reference (`<benchmark>/<suite>/<model>/<cell>`)."""
    root = Path(records_dir)
    if not root.is_dir():
        raise UserError(f"records_dir {root} is not a folder")
    cells = {p.relative_to(root).with_suffix("").as_posix(): p for p in root.rglob(f"*{AUTHORS_SUFFIX}")}
    for episodes in root.rglob(EPISODES_FILE):
        ref = episodes.parent.relative_to(root).as_posix()
        if ref in cells:
            raise UserError(f"{root}: cell {ref} is recorded twice ({cells[ref]} and {episodes})")
        cells[ref] = episodes
    return dict(sorted(cells.items()))


def contrast_mismatch(cell: Cell, baseline: Cell) -> str | None:
    """Why the records `cell` cannot be contrasted with `baseline`'s, None when they can: a contrast pairs only
    cells of one model, benchmark and suite, recorded on the same tasks, whose paired episodes (same task and
    index) ran with the same seeds, hence from the same scenes."""
    for field in ("model", "benchmark", "suite"):
        if cell.header.get(field) != baseline.header.get(field):
            return f"its {field} is {cell.header.get(field)}, the baseline's {baseline.header.get(field)}"
    tasks, baseline_tasks = (sorted(int(t) for t in c.episodes["task_id"].unique()) for c in (cell, baseline))
    if tasks != baseline_tasks:
        return f"it records tasks {tasks}, the baseline {baseline_tasks}"
    paired = cell.episodes.merge(baseline.episodes, on=["task_id", "episode"], suffixes=("", "_baseline"))
    differing = paired[paired["seed"] != paired["seed_baseline"]]
    if len(differing):
        first = differing.iloc[0]
        return (f"its episode seeds are not the baseline's (task {first['task_id']} episode {first['episode']}: "
                f"seed {first['seed']}, the baseline's {first['seed_baseline']})")
    return None
