"""The simulator seam's refactor (from 7d3a252) changes no episode: the LIBERO demo and the Meta-World main
job give the same outcome, steps and action digest, episode by episode, before it and after.

    nice -n 19 .venv/bin/python benchmarks/seam_equality.py [--before 7d3a252^] [--after HEAD]

Each revision is checked out as a git worktree in a temporary folder (this venv linked in, PYTHONPATH=its
src) and runs, one Snakemake at a time with --cores 2 (2 simulator workers):
  LIBERO     snakemake --cores 2 tables/lattice.tex --configfile config/config.yaml  (random-weight demo)
  Meta-World snakemake --cores 2 tables/lattice.tex --configfile config/main.yaml    (the main job: the
             Snakefile merges config/main.yaml over config/config.yaml, as it does with no --configfile)
Both checkouts run AFTER's config files (BEFORE has no config/main.yaml; its config/config.yaml also names
settle_steps: 10, the default at both) and AFTER's checkpoints/pi05_metaworld (retrained since BEFORE).
A revision older than 40d3947 reads trained checkpoints from a Hugging Face cache folder, not a plain one:
there the same files are written into that layout by the revision's own hub.cache.write_snapshot.

Cells are matched by their header's ref, as a config hash may change between revisions (Meta-World's do: a cell
now hashes only the env settings its benchmark declares, and pi0.5's Meta-World client), episodes by (task_id,
episode, init_state_id, seed). success and steps come from episodes.parquet; the action digest (actions_sha256,
SHA-256 of every executed action) from the cell's journal.jsonl, as episodes.parquet keeps only the columns of
records.episodes, which leave it out. Writes benchmarks/results/seam_equality.json and
.log; exits 1 when any episode differs or is missing on one side.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

from vlaquantbench.runner.journal import journal_episodes

REPO = Path(__file__).resolve().parents[1]
RUNS = {"libero": "config/config.yaml", "metaworld": "config/main.yaml"}
CONFIGS = ("config/config.yaml", "config/main.yaml", "config/main/tables/lattice.yaml",
           "config/demo/tables/lattice.yaml")
CHECKPOINT = "checkpoints/pi05_metaworld"
PLAIN_CHECKPOINTS = "40d3947"  # from this commit on, a trained checkpoint is a plain folder
KEY = ("task_id", "episode", "init_state_id", "seed")
FIELDS = ("success", "steps", "actions_sha256")
HUB_LAYOUT = """import json, shutil, sys
from pathlib import Path
from vlaquantbench.hub.cache import write_snapshot
plain, home = map(Path, sys.argv[1:])
training = json.loads((plain / "training.json").read_text())
write_snapshot(home / "hub", training["checkpoint"], training["revision"], plain / "policy")
write_snapshot(home / "hub", training["tokenizer"]["repo"], training["tokenizer"]["revision"], plain / "tokenizer")
shutil.copyfile(plain / "training.json", home / "training.json")
"""


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=REPO, check=True, capture_output=True, text=True).stdout.strip()


def environment(tree: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(tree / "src"), "PATH": f"{tree / '.venv/bin'}:{os.environ['PATH']}"}


def checkout(revision: str, tree: Path, after: Path | None) -> str:
    """A worktree of `revision`; with `after`, given that checkout's config files and trained checkpoint.
    Returns how the checkpoint is laid out there."""
    git("worktree", "add", "--detach", str(tree), revision)
    (tree / ".venv").symlink_to(sys.prefix)
    if after is None:
        return "its own plain folder"
    for name in CONFIGS:
        (tree / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(after / name, tree / name)
    shutil.rmtree(tree / CHECKPOINT, ignore_errors=True)
    if subprocess.run(["git", "merge-base", "--is-ancestor", PLAIN_CHECKPOINTS, revision], cwd=REPO).returncode == 0:
        shutil.copytree(after / CHECKPOINT, tree / CHECKPOINT)
        return "AFTER's plain folder, copied"
    subprocess.run([f"{tree}/.venv/bin/python", "-c", HUB_LAYOUT, str(after / CHECKPOINT), str(tree / CHECKPOINT)],
                   cwd=tree, env=environment(tree), check=True)
    return "AFTER's files in a Hugging Face cache folder (its hub.cache.write_snapshot), the layout it reads"


def run(tree: Path, configfile: str, log: Path) -> float:
    (tree / "tables/lattice.tex").unlink(missing_ok=True)  # both runs build it: each run builds its own
    start = time.monotonic()
    with log.open("w") as out:
        done = subprocess.run([".venv/bin/snakemake", "--cores", "2", "tables/lattice.tex", "--configfile", configfile],
                              cwd=tree, env=environment(tree), stdout=out, stderr=subprocess.STDOUT)
    if done.returncode:
        sys.exit(f"{tree}: snakemake --configfile {configfile} failed:\n{log.read_text()[-3000:]}")
    return round(time.monotonic() - start, 1)


def episodes(tree: Path, benchmark: str) -> tuple[dict, dict]:
    """{(ref, *KEY): {field: value}} of the benchmark's cells, and {ref: config hash}."""
    found, hashes = {}, {}
    for header_file in sorted((tree / "results/cells").glob("*/header.json")):
        header = json.loads(header_file.read_text())
        if header["benchmark"] != benchmark:
            continue
        hashes[header["ref"]] = header["config_hash"]
        digests = {(e["task_id"], e["episode"], e["seed"]): e["actions_sha256"]
                   for e in journal_episodes(header_file.parent / "journal.jsonl")}
        for row in pd.read_parquet(header_file.parent / "episodes.parquet").to_dict("records"):
            found[(header["ref"], *(int(row[k]) for k in KEY))] = {
                "success": bool(row["success"]), "steps": int(row["steps"]),
                "actions_sha256": digests[(row["task_id"], row["episode"], row["seed"])]}
    return found, hashes


def compare(before: dict, after: dict) -> list[dict]:
    differences = []
    for key in sorted(before.keys() | after.keys()):
        episode = dict(zip(("ref", *KEY), key))
        if key not in before or key not in after:
            differences.append({**episode, "only_in": "before" if key in before else "after"})
        elif fields := {f: {"before": before[key][f], "after": after[key][f]} for f in FIELDS
                        if before[key][f] != after[key][f]}:
            differences.append({**episode, "fields": fields})
    return differences


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--before", default="7d3a252^")
    parser.add_argument("--after", default="HEAD")
    args = parser.parse_args()
    revisions = {"before": git("rev-parse", args.before), "after": git("rev-parse", args.after)}
    lines, report = [], {"revisions": {side: {"given": getattr(args, side), "commit": commit}
                                       for side, commit in revisions.items()},
                         "episode_key": ["ref", *KEY], "fields": list(FIELDS), "benchmarks": {}}

    def say(line: str) -> None:
        print(line, flush=True)
        lines.append(line)

    with tempfile.TemporaryDirectory(prefix="seam_equality_") as tmp:
        trees = {side: Path(tmp) / side for side in ("after", "before")}
        try:
            layouts = {"after": checkout(revisions["after"], trees["after"], None)}
            layouts["before"] = checkout(revisions["before"], trees["before"], trees["after"])
            report["checkpoint"] = {CHECKPOINT: layouts}
            for benchmark, configfile in RUNS.items():
                wall = {}
                for side in ("before", "after"):
                    wall[side] = run(trees[side], configfile, Path(tmp) / f"{side}_{benchmark}.log")
                    say(f"{benchmark} {side} ({revisions[side][:7]}): snakemake done in {wall[side]} s")
                (before, before_hashes), (after, after_hashes) = (episodes(trees[side], benchmark)
                                                                  for side in ("before", "after"))
                differences = compare(before, after)
                report["benchmarks"][benchmark] = {
                    "command": f"snakemake --cores 2 tables/lattice.tex --configfile {configfile}",
                    "cells": {ref: {"before": before_hashes.get(ref), "after": after_hashes.get(ref)}
                              for ref in sorted(before_hashes.keys() | after_hashes.keys())},
                    "episodes": {"before": len(before), "after": len(after)},
                    "successes": {"before": sum(e["success"] for e in before.values()),
                                  "after": sum(e["success"] for e in after.values())},
                    "equal": len(before.keys() & after.keys()) - sum("fields" in d for d in differences),
                    "differences": differences,
                    "snakemake_wall_s": wall,
                }
                entry = report["benchmarks"][benchmark]
                say(f"{benchmark}: {len(entry['cells'])} cells, {entry['episodes']['after']} episodes after, "
                    f"{entry['episodes']['before']} before; {entry['equal']} equal, {len(differences)} differ")
        finally:
            for tree in trees.values():
                if tree.exists():
                    git("worktree", "remove", "--force", str(tree))
    differing = sum(len(b["differences"]) for b in report["benchmarks"].values())
    say(f"{'EQUAL' if not differing else 'DIFFERENT'}: {differing} episode(s) differ")
    out = REPO / "benchmarks/results/seam_equality"
    out.with_suffix(".json").write_text(json.dumps(report, indent=1) + "\n")
    out.with_suffix(".log").write_text("\n".join(lines) + "\n")
    return 1 if differing else 0


if __name__ == "__main__":
    sys.exit(main())
