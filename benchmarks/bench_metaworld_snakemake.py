"""Meta-World's scripted experts through Snakemake, as a user runs them: episodes per hour end to end.

    .venv/bin/python benchmarks/bench_metaworld_snakemake.py [--episodes-per-task 3] [--cores 2]

Runs `snakemake --cores 2 tables/expert.tex --configfile=config/demo/metaworld_expert.yaml` (every
metaworld_easy task, `--episodes-per-task` variations each) in a fresh checkout of symlinks under a
temporary folder, so no earlier result is reused: the checkpoint stamp, the rollout job (runner, journal,
two worker processes, records) and the table. Episodes per hour count the whole command (Snakemake's DAG,
the job's interpreter start and imports, the workers' start) and, separately, the rollout job alone (its
start to its records, from the Snakemake log's job timestamps). Wall time depends on what else runs on the
machine, so the load average before and after is recorded. Writes
`benchmarks/results/metaworld_experts_snakemake.json`.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd
import yaml

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "metaworld_experts_snakemake.json"
CONFIG = "config/demo/metaworld_expert.yaml"
# Snakemake's log: a job's start (`[<date>]` before `rule rollout:`) and its end (`Finished jobid: N (Rule: rollout)`).
_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]$")


def rollout_seconds(log: str) -> float:
    """Seconds from the rollout job's start to its end, from the `[date]` lines of Snakemake's log."""
    stamp, started, ended = None, None, None
    for line in log.splitlines():
        match = _STAMP.match(line.strip())
        if match:
            stamp = datetime.datetime.strptime(match.group(1), "%a %b %d %H:%M:%S %Y")
        elif line.strip() == "localrule rollout:":
            started = stamp
        elif "(Rule: rollout)" in line:
            ended = stamp
    if started is None or ended is None:
        raise RuntimeError("the Snakemake log shows no rollout job's start and end")
    return (ended - started).total_seconds()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes-per-task", type=int, default=None, help=f"default: {CONFIG}'s")
    parser.add_argument("--cores", type=int, default=2)
    parser.add_argument("--out", default=str(RESULTS))
    args = parser.parse_args()
    config = yaml.safe_load((ROOT / CONFIG).read_text())
    if args.episodes_per_task:
        config["study"]["episodes_per_task"] = args.episodes_per_task
    with tempfile.TemporaryDirectory(prefix="vqb-mw-bench-") as tmp:
        checkout = Path(tmp) / "checkout"
        checkout.mkdir()
        for item in ("Snakefile", "rules", "workflow", "manifests", "config", "src"):
            (checkout / item).symlink_to(ROOT / item)
        configfile = Path(tmp) / "metaworld_expert.yaml"
        configfile.write_text(yaml.safe_dump(config))
        load_before = os.getloadavg()
        started = time.perf_counter()
        run = subprocess.run([sys.executable, "-m", "snakemake", "--cores", str(args.cores), "tables/expert.tex",
                              f"--configfile={configfile}"], cwd=checkout, capture_output=True, text=True)
        total_s = time.perf_counter() - started
        load_after = os.getloadavg()
        if run.returncode != 0:
            sys.exit(f"snakemake failed:\n{run.stderr[-3000:]}")
        (episodes_file,) = (checkout / "results" / "cells").glob("*/episodes.parquet")
        episodes = pd.read_parquet(episodes_file)
        header = json.loads((episodes_file.parent / "header.json").read_text())
        job_s = rollout_seconds(run.stdout + run.stderr)
    result = {
        "command": f"snakemake --cores {args.cores} tables/expert.tex --configfile={CONFIG}",
        "suite": header["suite"],
        "versions": {k: header["versions"][k] for k in ("metaworld", "mujoco")},
        "tasks": int(episodes["task_id"].nunique()),
        "episodes_per_task": config["study"]["episodes_per_task"],
        "episodes": len(episodes),
        "success_rate": round(float(episodes["success"].mean()), 3),
        "steps": int(episodes["steps"].sum()),
        "total_s": round(total_s, 1),
        "rollout_job_s": job_s,
        "episodes_per_hour": round(len(episodes) / total_s * 3600),
        "episodes_per_hour_rollout_job": round(len(episodes) / job_s * 3600),
        "machine": {"cpus": os.cpu_count(), "load_average_before": [round(x, 2) for x in load_before],
                    "load_average_after": [round(x, 2) for x in load_after], "platform": platform.platform(),
                    "date_utc": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")},
    }
    Path(args.out).write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps(result, indent=1))


if __name__ == "__main__":
    main()
