"""Compare the records of the same cells run by two code versions: episodes (timing columns aside), the
header fields that differ, and every journaled episode's outcome, step count and action digest.

    .venv/bin/python benchmarks/compare_cell_records.py FOLDER_A FOLDER_B            # cell folders of equal names
    .venv/bin/python benchmarks/compare_cell_records.py ROOT_A ROOT_B HASH_A HASH_B  # one cell under two hashes

Run for issue 29 on the demo study's cells (main vs the simulator seam): `results/seam_libero_demo_equality.txt`.
"""

import json
import sys
from pathlib import Path

import pandas as pd

TIMING = ["wall_time_s", "policy_batch_latency_mean_s"]  # what two runs of one episode may record differently


def journal_outcomes(folder: Path) -> dict:
    lines = [json.loads(line) for line in (folder / "journal.jsonl").read_text().splitlines()[1:]]
    return {(r["task_id"], r["episode"]): (r["success"], r["steps"], r["actions_sha256"])
            for r in lines if r.get("kind") == "episode"}


def compare(a: Path, b: Path) -> None:
    episodes_a, episodes_b = pd.read_parquet(a / "episodes.parquet"), pd.read_parquet(b / "episodes.parquet")
    same = list(episodes_a.columns) == list(episodes_b.columns) and \
        episodes_a.drop(columns=TIMING).equals(episodes_b.drop(columns=TIMING))
    print(f"{a.name} {b.name}: {len(episodes_a)} episodes, equal but timing: {same}")
    header_a, header_b = (json.loads((folder / "header.json").read_text()) for folder in (a, b))
    differ = {k: (header_a.get(k), header_b.get(k)) for k in sorted(set(header_a) | set(header_b))
              if header_a.get(k) != header_b.get(k) and k != "config"}
    print(f"  header fields that differ (config aside): {differ}")
    config_a, config_b = header_a["config"], header_b["config"]
    print(f"  config fields that differ: { {k: (config_a.get(k), config_b.get(k)) for k in sorted(set(config_a) | set(config_b)) if config_a.get(k) != config_b.get(k)} }")
    outcomes_a = journal_outcomes(a)
    print(f"  journaled outcomes, steps and action digests equal: {outcomes_a == journal_outcomes(b)}")


if __name__ == "__main__":
    root_a, root_b = Path(sys.argv[1]), Path(sys.argv[2])
    if len(sys.argv) == 5:
        compare(root_a / sys.argv[3], root_b / sys.argv[4])
    else:
        for folder in sorted(root_a.iterdir()):
            compare(folder, root_b / folder.name)
