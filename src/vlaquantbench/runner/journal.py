"""A cell's crash-safe episode journal: `<cell dir>/journal.jsonl`.

Line 1 is the cell header as known before any episode runs; every further line is either one
finished episode (`kind: episode`) or the set of selected layers whose activation hooks have fired
so far (`kind: hooks`). Each append is flushed and fsync'd, so a `kill -9` loses at most the line
being written; a torn last line is dropped when the journal is reopened. A rerun resumes with the
episodes that are missing, and refuses to continue if its header disagrees with the journal's.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from vlaquantbench.errors import UserError
from vlaquantbench.records.schema import EpisodeCheck, present

EPISODE_KEY = ("task_id", "episode", "seed")
# Header fields a rerun may change and still resume: the code revision (the arithmetic is versioned by
# `quant_semantics`, which must match) and the cell's names (cells that run the same experiment under
# different names share one folder; see `cells.hashed_config`).
RESUMABLE_CHANGES = ("code_revision", "ref", "cell", "subset", "method")
# What the fast-vs-eager probe measured: on CUDA a rerun's first chunk may differ in the last bits, so
# only the probe's path, device and bound must match (a rerun that fails the bound is refused anyway).
PROBE_MEASUREMENTS = ("max_abs_diff", "rel_l2")


def _compared(header: dict[str, Any]) -> dict[str, Any]:
    kept = {k: v for k, v in header.items() if k not in RESUMABLE_CHANGES}
    if isinstance(kept.get("config"), dict):
        kept["config"] = {k: v for k, v in kept["config"].items() if k not in RESUMABLE_CHANGES}
    probe = (kept.get("inference") or {}).get("fast_path_probe")
    if isinstance(probe, dict):
        probe = {k: v for k, v in probe.items() if k not in PROBE_MEASUREMENTS}
        kept["inference"] = {**kept["inference"], "fast_path_probe": probe}
    return kept


def header_differences(recorded: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """Lines `key: recorded=... current=...` for every top-level field that differs, apart from the
    fields a resumed cell may change (`RESUMABLE_CHANGES`)."""
    recorded, current = _compared(recorded), _compared(current)
    lines = []
    for key in sorted(set(recorded) | set(current)):
        if recorded.get(key) != current.get(key):
            lines.append(f"{key}: recorded={json.dumps(recorded.get(key))} current={json.dumps(current.get(key))}")
    return lines


def _parsed(path: Path, number: int, line: bytes) -> dict[str, Any]:
    try:
        return json.loads(line)
    except json.JSONDecodeError as err:
        raise UserError(f"{path}:{number}: malformed journal line ({err.msg} at column {err.colno}); "
                        "move the journal away to start the cell afresh") from None


def _episode_lines(path: Path) -> list[dict[str, Any]]:
    """The journal's episode lines, unchecked (no header comparison); a torn last line does not count."""
    if not Path(path).exists():
        return []
    complete = Path(path).read_bytes().split(b"\n")[:-1]
    records = (_parsed(path, number, line) for number, line in enumerate(complete, start=1) if line.strip())
    return [r for r in records if r.get("kind") == "episode"]


def recorded_episodes(path: Path) -> int:
    """Episodes a journal holds (0 if there is none); a torn last line does not count."""
    return len(_episode_lines(path))


def recorded_keys(path: Path) -> set[tuple]:
    """The EPISODE_KEYs of a journal's episodes, for planning only: the header is not checked
    (`CellJournal` does that before anything is recorded)."""
    return {tuple(r[k] for k in EPISODE_KEY) for r in _episode_lines(path)}


class CellJournal:
    def __init__(self, path: Path, header: dict[str, Any]):
        """Open (or create) the journal at `path` for a cell whose header is `header`.

        Raises UserError, showing both values of every differing field, if the journal was
        started with another header; the journal is left untouched in that case.
        """
        self.path = Path(path)
        self.header = header
        self.episodes: list[dict[str, Any]] = []
        self.fired: set[str] = set()
        if self.path.exists():
            self._load()
        else:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._append([{"kind": "header", **header}])

    def _load(self) -> None:
        raw = self.path.read_bytes()
        lines = raw.split(b"\n")
        complete, torn = lines[:-1], lines[-1]
        if torn:  # a write cut short by a kill: drop it so the rerun appends after whole lines
            with open(self.path, "r+b") as handle:
                handle.truncate(len(raw) - len(torn))
                os.fsync(handle.fileno())
        numbered = [(number, _parsed(self.path, number, line)) for number, line in enumerate(complete, start=1) if line.strip()]
        records = [record for _, record in numbered]
        if not records or records[0].get("kind") != "header":
            raise UserError(f"{self.path}: journal has no header line; move it away to start the cell afresh")
        recorded = {k: v for k, v in records[0].items() if k != "kind"}
        differences = header_differences(recorded, self.header)
        if differences:
            raise UserError(
                f"{self.path}: the cell's existing records were made with another header; refusing to mix them "
                "(move the folder away to start afresh):\n  " + "\n  ".join(differences)
            )
        check = EpisodeCheck(recorded, f"{self.path}:{numbered[0][0]}")
        seen = set()
        for number, record in numbered[1:]:
            if record["kind"] == "hooks":
                self.fired.update(record["fired"])
            elif record["kind"] == "episode":
                check(present(record), f"{self.path}:{number}")
                key = tuple(record[k] for k in EPISODE_KEY)
                if key in seen:
                    raise UserError(f"{self.path}: duplicate episode {dict(zip(EPISODE_KEY, key))}")
                seen.add(key)
                self.episodes.append({k: v for k, v in record.items() if k != "kind"})

    def done_keys(self) -> set[tuple]:
        return {tuple(e[k] for k in EPISODE_KEY) for e in self.episodes}

    def record(self, episodes: list[dict[str, Any]], fired: set[str]) -> None:
        """Durably append finished episodes, preceded by the fired-hook set if it grew."""
        lines: list[dict[str, Any]] = []
        if not fired <= self.fired:
            self.fired |= fired
            lines.append({"kind": "hooks", "fired": sorted(self.fired)})
        lines.extend({"kind": "episode", **e} for e in episodes)
        self._append(lines)
        self.episodes.extend(episodes)

    def _append(self, records: list[dict[str, Any]]) -> None:
        payload = "".join(json.dumps(r, sort_keys=True) + "\n" for r in records).encode()
        with open(self.path, "ab") as handle:
            handle.write(payload)
            handle.flush()
            os.fsync(handle.fileno())
