"""A cell's crash-safe episode journal: `<cell dir>/journal.jsonl`.

Line 1 is the cell header as known before any episode runs; every further line is either one
finished episode (`kind: episode`) or the set of selected layers whose activation hooks have fired
so far (`kind: hooks`). Each append is flushed and fsync'd, so a `kill -9` loses at most the line
being written; a torn last line is dropped when the journal is reopened. A rerun resumes with the
episodes that are missing, and refuses to continue if its header disagrees with the journal's.

An episode recorded twice (two writers of one cell before `runner.lock` existed, or a journal
concatenated by hand) resumes when both lines agree but for their timing; lines that disagree are
refused, naming the file, the lines and what to delete.
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
# What the fast-vs-eager probe measured: a rerun's first chunk (and, on the CPU, the eager policy's
# spread under one-ulp input moves that sets the bound) may differ in the last bits on another machine,
# so only the probe's path, device and bound rule must match (a rerun that fails its bound is refused anyway).
PROBE_MEASUREMENTS = ("max_abs_diff", "rel_l2", "eager_ulp_spread")
# Which GPU of a model ran the cell (runner.gpus gives each job any free one): a rerun resumes on another
# device of the same name, whose arithmetic is the same; a device of another name is refused (README "GPUs").
DEVICE_SLOT = ("index", "uuid")
# The GPUs a host lists (`provenance.host`): a node with more or fewer of them resumes; its CPU model and
# rendering backend must match, as a CUDA device's name must (another CPU or renderer moves outcomes).
HOST_GPUS = ("gpus",)
# What two runs of one episode may record differently: how long it took, and the memory it took.
TIMING_FIELDS = ("wall_time_s", "policy_batch_latency_mean_s", "policy_latency_mean_s", "inference_latency_mean_s",
                 "peak_vram_gb")


def _compared(header: dict[str, Any]) -> dict[str, Any]:
    kept = {k: v for k, v in header.items() if k not in RESUMABLE_CHANGES}
    if isinstance(kept.get("config"), dict):
        kept["config"] = {k: v for k, v in kept["config"].items() if k not in RESUMABLE_CHANGES}
    probe = (kept.get("inference") or {}).get("fast_path_probe")
    if isinstance(probe, dict):
        probe = {k: v for k, v in probe.items() if k not in PROBE_MEASUREMENTS}
        kept["inference"] = {**kept["inference"], "fast_path_probe": probe}
    if isinstance(kept.get("device"), dict):
        kept["device"] = {k: v for k, v in kept["device"].items() if k not in DEVICE_SLOT}
    if isinstance(kept.get("host"), dict):
        kept["host"] = {k: v for k, v in kept["host"].items() if k not in HOST_GPUS}
    return kept


def header_differences(recorded: dict[str, Any], current: dict[str, Any]) -> list[str]:
    """Lines `key: recorded=... current=...` for every top-level field that differs, apart from the
    fields a resumed cell may change (`RESUMABLE_CHANGES`)."""
    recorded, current = _compared(recorded), _compared(current)
    lines = []
    for key in sorted(set(recorded) | set(current)):
        if key in ("device", "host") and key not in recorded:  # a journal begun before headers named them
            continue
        if recorded.get(key) != current.get(key):
            lines.append(f"{key}: recorded={json.dumps(recorded.get(key))} current={json.dumps(current.get(key))}")
    return lines


def _parsed(path: Path, number: int, line: bytes) -> dict[str, Any]:
    try:
        return json.loads(line)
    except json.JSONDecodeError as err:
        raise UserError(f"{path}:{number}: malformed journal line ({err.msg} at column {err.colno}); "
                        "move the journal away to start the cell afresh") from None


def _numbered(path: Path, lines: list[bytes]) -> list[tuple[int, dict[str, Any]]]:
    """(line number from 1, record) of a journal's whole, non-empty lines; a malformed one is refused by number."""
    return [(n, _parsed(path, n, line)) for n, line in enumerate(lines, 1) if line.strip()]


def unique_episodes(path: Path, numbered: list[tuple[int, dict[str, Any]]]) -> list[dict[str, Any]]:
    """The episode records of `numbered`, each episode once: a line repeating an earlier one but for
    its TIMING_FIELDS is dropped; lines that record one episode differently are refused, naming them."""
    first: dict[tuple, tuple[int, dict[str, Any]]] = {}
    conflicts = []
    for n, record in numbered:
        if record.get("kind") != "episode":
            continue
        key = tuple(record[k] for k in EPISODE_KEY)
        if key not in first:
            first[key] = n, record
            continue
        m, earlier = first[key]
        fields = sorted(k for k in set(earlier) | set(record)
                        if k not in TIMING_FIELDS and earlier.get(k) != record.get(k))
        if fields:
            values = "; ".join(f"{k}: {json.dumps(earlier.get(k))} vs {json.dumps(record.get(k))}" for k in fields)
            conflicts.append(f"lines {m} and {n}: {dict(zip(EPISODE_KEY, key))} ({values})")
    if conflicts:
        raise UserError(
            f"{path}: episodes recorded twice with different outcomes (two writers of the cell at once?):\n  "
            + "\n  ".join(conflicts)
            + f"\nDelete both lines of each pair from {path} to run those episodes again when the cell resumes "
            f"(or only the line you distrust), or move {Path(path).parent} away to rerun the whole cell."
        )
    return [{k: v for k, v in record.items() if k != "kind"} for _, record in first.values()]


def journal_episodes(path: Path) -> list[dict[str, Any]]:
    """The journal's episodes, each once, unchecked otherwise (no header comparison; for planning only);
    a torn last line does not count."""
    if not Path(path).exists():
        return []
    return unique_episodes(path, _numbered(path, Path(path).read_bytes().split(b"\n")[:-1]))


def recorded_episodes(path: Path) -> int:
    """Episodes a journal holds (0 if there is none); a torn last line does not count."""
    return len(journal_episodes(path))


def recorded_keys(path: Path) -> set[tuple]:
    """The EPISODE_KEYs of a journal's episodes, for planning only: the header is not checked
    (`CellJournal` does that before anything is recorded); episodes recorded twice differently are
    refused here already, before a model loads."""
    return {tuple(r[k] for k in EPISODE_KEY) for r in journal_episodes(path)}


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
        numbered = _numbered(self.path, complete)
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
        for number, record in numbered[1:]:
            if record["kind"] == "hooks":
                self.fired.update(record["fired"])
            elif record["kind"] == "episode":
                check(present(record), f"{self.path}:{number}")
        self.episodes = unique_episodes(self.path, numbered[1:])

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
