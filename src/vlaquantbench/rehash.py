"""Bring recorded cell headers to the current canonical cell config and its hash (`vqb rehash`).

A cell header records its canonical config (`config`) and the hash of it (`config_hash`), which names the cell's
folder under `results/cells/` and which a sequential cell's config names for the cell it stops against. When the
canonical form changes without changing what an episode does (a cell now carries only the env settings its
benchmark declares: `cells.cell_runner`; its model's client conventions on its benchmark are declared anew:
`models.client`), records made before keep their episodes, but their headers name a config and hash that the
current code would never build. `rehash` rewrites each header's config as `CellConfig` reads it back and writes it
now, under its model's current client conventions with its overrides taken against them (the header's `client` and
`overrides` with it), its hash, and the hash its `sequential.against` names (mapped through the same rewrite, so
the cell it stops against must be among the records); `vqb rehash` then rewrites the records' manifests (`vqb
manifest`), whose header rows carry each header's SHA-256. Nothing else in a header changes:
the episodes, the code revision that ran them and every measured value stay. Cells whose config is already
canonical are left byte for byte, so running it again changes nothing.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from vlaquantbench.cells import CellConfig, config_hash
from vlaquantbench.errors import UserError
from vlaquantbench.records import find_cells
from vlaquantbench.records.cell import HEADER_FILE, write_header


@dataclass(frozen=True)
class Rehashed:
    ref: str
    header: Path
    old_hash: str
    new_hash: str


def _header_path(record: Path) -> Path:
    """A cell's header.json (`find_cells` gives the cell's episodes file)."""
    path = record if record.is_dir() else record.parent
    header = path / HEADER_FILE
    if not header.is_file():
        raise UserError(f"{record}: no {HEADER_FILE} beside it: only cell folders carry a config hash to rewrite")
    return header


def rehash(records_dirs: list[str | Path]) -> list[Rehashed]:
    """Rewrite the headers of every cell under `records_dirs` to the current canonical config and hash (see the
    module); the cells whose hash changed. Several folders are rewritten together when a sequential cell of one stops
    against a cell of another. UserError, before any file is written, when a header's recorded hash is not the hash
    of its recorded config (an edited header), when a cell's folder is not its reference (a DAG folder named by its
    hash), or when a sequential cell's `against` hash is no recorded cell's."""
    headers = {}
    for folder in records_dirs:
        for ref, record in sorted(find_cells(folder).items()):
            path = _header_path(record)
            header = json.loads(path.read_text())
            if ref != header["ref"]:  # a DAG folder, results/cells/<config-hash>/: its name is the hash to change
                raise UserError(f"{path}: its folder {ref} is not its reference {header['ref']}: rehash rewrites records "
                                "folders keyed by reference (a records_dir); a folder named by its config hash would "
                                "keep the old one, so run its cell again instead")
            if config_hash(header["config"]) != header["config_hash"]:
                raise UserError(f"{path}: config_hash {header['config_hash']} is not the hash of its config "
                                f"({config_hash(header['config'])}): the header was edited; not rewritten")
            headers[path] = (ref, header)
    # Cells without a stopping rule first: a sequential cell's config names the new hash of the cell it stops against.
    configs, renamed = {}, {}
    for path, (_, header) in sorted(headers.items(), key=lambda item: "sequential" in item[1][1]["config"]):
        config = CellConfig.from_dict(header["config"]).under_current_client().to_dict()
        against = config.get("sequential", {}).get("against")
        if against is not None:
            if against["config_hash"] not in renamed:
                raise UserError(f"{path}: its sequential.against {against['ref']} ({against['config_hash']}) is not among "
                                f"the records given ({', '.join(map(str, records_dirs))}): give its folder too")
            against["config_hash"] = renamed[against["config_hash"]]
        configs[path] = config
        renamed[header["config_hash"]] = config_hash(config)
    changed = []
    for path, (ref, header) in headers.items():
        new_hash = renamed[header["config_hash"]]
        if configs[path] == header["config"] and new_hash == header["config_hash"]:
            continue
        write_header(path.parent, {**header, "config": configs[path], "config_hash": new_hash,
                                   "client": configs[path]["client"], "overrides": configs[path]["overrides"]})
        changed.append(Rehashed(ref, path, header["config_hash"], new_hash))
    return changed
