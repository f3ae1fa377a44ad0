"""Manifests: a TSV of record files with episodes, successes, SHA-256 and outcomes, frozen next to a study.

Paths are relative to the records folder, so a manifest stays valid wherever the records are copied.
`outcomes` lists each episode's success (1/0) in file order, so a changed record is explained: which
episodes or successes changed, and on which line. Building a manifest refuses a cell whose episodes
do not match what its header declares. Verification stops on the first record that is unlisted,
missing, or whose contents changed.
"""

from __future__ import annotations

import csv
import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

from vlaquantbench.atomic import atomic_write
from vlaquantbench.errors import UserError
from vlaquantbench.records import Cell, check_declared_episodes, episode_gaps, find_cells, read_cell, record_files

COLUMNS = ("path", "episodes", "successes", "sha256", "outcomes")
REQUIRED = COLUMNS[:4]  # manifests written before `outcomes` existed still verify
EXPLAINED = 5  # changed episodes named in an error, at most


@dataclass(frozen=True)
class ManifestRow:
    path: str
    episodes: int | None  # None for a cell folder's header.json
    successes: int | None
    sha256: str
    outcomes: str | None = None  # "1"/"0" per episode in file order


def _outcomes(cell: Cell) -> str:
    return "".join("1" if ok else "0" for ok in cell.episodes["success"])


def sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def manifest_rows(records_dir: str | Path, cells: Iterable[str | Path] | None = None) -> list[ManifestRow]:
    """One row per record file of `cells` (paths under `records_dir`; default: every cell found there)."""
    root = Path(records_dir)
    cell_paths = [Path(p) for p in cells] if cells is not None else list(find_cells(root).values())
    rows = []
    for cell_path in cell_paths:
        cell = check_declared_episodes(read_cell(cell_path))
        for file in record_files(cell_path):
            counted = file.suffix != ".json"
            rows.append(
                ManifestRow(
                    path=file.relative_to(root).as_posix(),
                    episodes=cell.n_episodes if counted else None,
                    successes=cell.n_successes if counted else None,
                    sha256=sha256_file(file),
                    outcomes=_outcomes(cell) if counted else None,
                )
            )
    return sorted(rows, key=lambda row: row.path)


def write_manifest(records_dir: str | Path, output: str | Path, cells: Iterable[str | Path] | None = None) -> Path:
    return _write_rows(manifest_rows(records_dir, cells), output)


def _write_rows(rows: list[ManifestRow], output: str | Path) -> Path:
    with atomic_write(output, newline="") as handle:
        writer = csv.writer(handle, delimiter="\t", lineterminator="\n")
        writer.writerow(COLUMNS)
        for row in rows:
            values = (row.path, row.episodes, row.successes, row.sha256, row.outcomes)
            writer.writerow(["" if value is None else value for value in values])
    return output


def read_manifest(path: str | Path) -> dict[str, ManifestRow]:
    path = Path(path)
    if not path.is_file():
        raise UserError(f"manifest {path} not found")
    with open(path, newline="") as handle:
        reader = csv.DictReader(handle, delimiter="\t")
        if tuple(reader.fieldnames or ()) not in (COLUMNS, REQUIRED):
            raise UserError(f"manifest {path}: expected columns {', '.join(REQUIRED)}[, outcomes], got {reader.fieldnames}")
        return {
            row["path"]: ManifestRow(
                path=row["path"],
                episodes=int(row["episodes"]) if row["episodes"] else None,
                successes=int(row["successes"]) if row["successes"] else None,
                sha256=row["sha256"],
                outcomes=row.get("outcomes") or None,
            )
            for row in reader
        }


def _episode_lines(file: Path) -> list[str]:
    """Where each episode sits in `file`: `line N` of an authors' .jsonl, `row N` of a parquet table."""
    if file.suffix == ".jsonl":
        lines = file.read_text().splitlines()
        return [f"line {number}" for number, line in enumerate(lines[1:], start=2) if line.strip()]
    return [f"row {number}" for number in range(1, read_cell(file).n_episodes + 1)]


def explain_change(file: Path, listed: ManifestRow) -> str:
    """What differs between record `file` and its manifest row: episodes, successes, which lines."""
    if listed.episodes is None:
        return "the run header changed"
    try:
        cell = read_cell(file)
    except UserError as err:
        return f"the record no longer reads ({err})"
    changes = []
    if cell.n_episodes != listed.episodes:
        changes.append(f"{cell.n_episodes} episodes instead of {listed.episodes}")
        changes += episode_gaps(cell)
    if cell.n_successes != listed.successes:
        changes.append(f"{cell.n_successes} successes instead of {listed.successes}")
    now = _outcomes(cell)
    if listed.outcomes and len(listed.outcomes) == len(now):
        where = _episode_lines(file)
        flipped = [i for i, (was, is_) in enumerate(zip(listed.outcomes, now)) if was != is_]
        for i in flipped[:EXPLAINED]:
            episode = cell.episodes.iloc[i]
            changes.append(
                f"{where[i]} (task {episode['task_id']}, episode {episode['episode']}): success "
                f"{'true' if listed.outcomes[i] == '1' else 'false'} -> {'true' if now[i] == '1' else 'false'}"
            )
        if len(flipped) > EXPLAINED:
            changes.append(f"{len(flipped) - EXPLAINED} more changed outcomes")
    return "; ".join(changes) or "episodes and successes unchanged: another field of an episode or the header changed"



def verify_manifest(
    manifest: str | Path, records_dir: str | Path, cells: Iterable[str | Path] | None = None
) -> list[ManifestRow]:
    """Check every record file of `cells` (default: all cells in `records_dir`) against `manifest`.

    Raises UserError naming the first record file that is listed but missing, unlisted, or changed;
    returns the verified rows.
    """
    root = Path(records_dir)
    listed = read_manifest(manifest)
    cell_paths = [Path(p) for p in cells] if cells is not None else list(find_cells(root).values())
    for row in listed.values():
        if not (root / row.path).is_file():
            raise UserError(f"record {root / row.path} listed in manifest {manifest} is missing")
    verified = []
    for file in sorted(f for cell_path in cell_paths for f in record_files(cell_path)):
        relative = file.relative_to(root).as_posix()
        if not file.is_file():
            raise UserError(f"record {file} is missing")
        if relative not in listed:
            raise UserError(f"record {file} is not listed in manifest {manifest}")
        if sha256_file(file) != listed[relative].sha256:
            raise UserError(
                f"record {file} does not match manifest {manifest} (SHA-256 differs: {explain_change(file, listed[relative])})"
            )
        verified.append(listed[relative])
    return verified


def verified(manifests: list[str], records_dir: str | Path, cells: list[str]) -> list[str]:
    """`cells` (record paths), once every one of their files matches the frozen manifest (`manifests`: it,
    or nothing when none is frozen): what a rendering job reads, checked in the same job that writes its
    output. The job reads the cells through `read_checked_cell`, which checks their schema and headers."""
    for manifest in manifests:
        verify_manifest(manifest, records_dir, cells)
    return cells


def write_file_manifest(root: str | Path, output: str | Path) -> Path:
    """A manifest of every data file under `root` but `output` (a dataset rather than cell records: its
    rows carry a path and a SHA-256 only), in the same TSV format as a records manifest."""
    root = Path(root)
    files = _data_files(root, Path(output))
    return _write_rows([ManifestRow(path, None, None, sha256_file(root / path)) for path in files], output)


def _data_files(root: Path, manifest: Path) -> list[str]:
    """Paths under `root`, relative, of its files but `manifest` and hidden bookkeeping (Snakemake's
    `.snakemake_timestamp` in a directory output)."""
    return sorted(f.relative_to(root).as_posix() for f in root.rglob("*")
                  if f.is_file() and f.resolve() != manifest.resolve() and not f.name.startswith("."))


def verify_file_manifest(manifest: str | Path, root: str | Path) -> list[ManifestRow]:
    """Check the files under `root` against a `write_file_manifest` manifest: UserError naming the first
    file that is listed but missing, present but unlisted, or changed; returns the verified rows."""
    root, manifest = Path(root), Path(manifest)
    listed = read_manifest(manifest)
    present = set(_data_files(root, manifest))
    if missing := sorted(set(listed) - present):
        raise UserError(f"file {root / missing[0]} listed in manifest {manifest} is missing")
    if unlisted := sorted(present - set(listed)):
        raise UserError(f"file {root / unlisted[0]} is not listed in manifest {manifest}")
    for path, row in sorted(listed.items()):
        if sha256_file(root / path) != row.sha256:
            raise UserError(f"file {root / path} does not match manifest {manifest} (SHA-256 differs)")
    return [listed[path] for path in sorted(listed)]
