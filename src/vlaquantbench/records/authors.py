"""Importer for the authors' published layout `results/<benchmark>/<suite>/<model>/<cell>.jsonl`.

Line 1 is the run header (`"kind": "header"`); every further line is one episode
(`"kind": "episode"`). Episode fields sit at top level or under `extra` (e.g. `extra.init_state_id`);
optional fields (latency, `task_name`, CALVIN `subtasks_completed`, VLABench `progress_score`) may
be absent from some or all lines.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from vlaquantbench.errors import UserError
from vlaquantbench.records.episodes import EPISODE_COLUMNS, EPISODE_KEY, OPTIONAL_COLUMNS, Cell, normalize_episodes
from vlaquantbench.records.schema import EpisodeCheck
from vlaquantbench.textfiles import read_parsed

_FIELDS = EPISODE_COLUMNS + OPTIONAL_COLUMNS
_REQUIRED = tuple(c for c in EPISODE_COLUMNS if c != "init_state_id")


def _parse_line(path: Path, number: int, line: str) -> dict[str, Any]:
    try:
        record = json.loads(line)
    except json.JSONDecodeError as err:
        raise UserError(f"{path}:{number}: truncated or malformed JSON line ({err.msg} at column {err.colno})") from err
    if not isinstance(record, dict):
        raise UserError(f"{path}:{number}: expected a JSON object, got {type(record).__name__}")
    return record


def _episode_row(path: Path, number: int, record: dict[str, Any]) -> dict[str, Any]:
    extra = record.get("extra") or {}
    row = {field: record.get(field, extra.get(field)) for field in _FIELDS}
    missing = [field for field in _REQUIRED if row[field] is None]
    if missing:
        raise UserError(f"{path}:{number}: episode lacks required field(s) {', '.join(missing)}")
    return {field: value for field, value in row.items() if value is not None}


def read_authors_jsonl(path: str | Path) -> Cell:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: record file not found")
    lines = read_parsed(path, str.splitlines, "UTF-8 text")
    if not lines or not lines[0].strip():
        raise UserError(f"{path}:1: header line missing (file is empty)")
    header = _parse_line(path, 1, lines[0])
    if header.get("kind") != "header":
        raise UserError(f"{path}:1: header line missing (first line has kind={header.get('kind')!r})")
    header = {key: value for key, value in header.items() if key != "kind"}
    check = EpisodeCheck(header, f"{path}:1")
    rows: list[dict[str, Any]] = []
    seen: dict[tuple[int, int, int], int] = {}
    for number, line in enumerate(lines[1:], start=2):
        if not line.strip():
            continue
        record = _parse_line(path, number, line)
        if record.get("kind") != "episode":
            raise UserError(f"{path}:{number}: expected an episode line, got kind={record.get('kind')!r}")
        row = _episode_row(path, number, record)
        check(row, f"{path}:{number}")
        key = tuple(int(row[field]) for field in EPISODE_KEY)
        if key in seen:
            raise UserError(
                f"{path}:{number}: duplicate episode key (task_id, episode, seed) = {key}, first on line {seen[key]}"
            )
        seen[key] = number
        rows.append(row)
    return Cell(header=header, episodes=normalize_episodes(rows, path), path=path)
