"""How far a rerun of recorded cells reproduces them, episode by episode: for every cell folder under
`--rerun` that is a recorded cell of `--recorded` (same reference and config hash), the episodes whose
outcome and step count are equal, with both cells' hosts and code revisions.

    .venv/bin/python benchmarks/rerun_agreement.py --recorded results/methods_2026 --rerun results/cells \
        --out benchmarks/results/rerun_agreement_methods_2026.json

A cell rerun on its own host and code should agree on every episode (README, "What a cell's records
depend on"); another CPU or renderer moves last bits, which a closed loop amplifies.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from vlaquantbench.records import read_cell
from vlaquantbench.records.cell import HEADER_FILE

KEY = ["task_id", "episode", "seed"]


def agreement(recorded: Path, rerun: Path) -> list[dict]:
    rows = []
    for header in sorted(rerun.glob(f"*/{HEADER_FILE}")):
        again = read_cell(header.parent)
        original_folder = recorded / again.header["ref"]
        if not original_folder.is_dir():
            continue
        original = read_cell(original_folder)
        if original.header["config_hash"] != again.header["config_hash"]:
            continue  # another cell of the same name (another study's episodes or settings)
        merged = original.episodes.merge(again.episodes, on=KEY, suffixes=("_recorded", "_rerun"))
        equal = {field: int((merged[f"{field}_recorded"] == merged[f"{field}_rerun"]).sum())
                 for field in ("success", "steps")}
        rows.append({
            "ref": again.header["ref"], "config_hash": again.header["config_hash"],
            "episodes": len(merged), "equal": equal,
            "successes": {"recorded": int(original.episodes["success"].sum()), "rerun": int(again.episodes["success"].sum())},
            "host": {"recorded": original.header.get("host"), "rerun": again.header.get("host")},
            "code_revision": {"recorded": original.header.get("code_revision"), "rerun": again.header.get("code_revision")},
        })
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--recorded", type=Path, required=True, help="records folder (cell folders by reference)")
    parser.add_argument("--rerun", type=Path, required=True, help="folder of rerun cell folders (e.g. results/cells)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    rows = agreement(args.recorded, args.rerun)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(rows, indent=1) + "\n")
    for row in rows:
        print(f"{row['ref']}: {row['episodes']} episodes, equal {row['equal']}, successes {row['successes']}")


if __name__ == "__main__":
    main()
