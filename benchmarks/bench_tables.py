"""Time regenerating the paper's tables and figures from the authors' reference data on this machine's CPUs.

Measures, in one run: reading + summarizing all cells (tables/summary.csv), rendering every table of
config/tables in process (the 30 task-clustered bootstraps included; cells without records from the
authors' summary, latency and fidelity files from config `sources`) and the scope-recovery figure;
`snakemake paper` from scratch (every table and figure, the goal: < 60 s on 2 cores); and, side by
side, the batched bootstrap against the call-by-call loop of the same procedure (same numbers).

    .venv/bin/python benchmarks/bench_tables.py   # writes benchmarks/results/tables_cpu.json
"""

from __future__ import annotations

import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from vlaquantbench.figures import load_figure, plot_scope_recovery
from vlaquantbench.records import find_cells, read_cell
from vlaquantbench.stats import task_clustered_bootstrap
from vlaquantbench.tables import load_table, write_summary, write_table
from vlaquantbench.workflow import WorkflowConfig

ROOT = Path(__file__).resolve().parents[1]
REFERENCE = ROOT.parent / "shared" / "reference"
RECORDS = REFERENCE / "records"
# The reference config's measurement folders (latency, fidelity, replay, diagnostics), resolved from the checkout.
SOURCES = {name: (ROOT / folder).resolve()
           for name, folder in yaml.safe_load((ROOT / "config" / "reference.yaml").read_text())["sources"].items()}
REPEATS = 3
GOAL_S = 30.0


def loop_bootstrap(a, b, draws=5000, seed=0):
    """The two-stage bootstrap written draw by draw, call by call (the paper's procedure; same numbers)."""
    rng = np.random.default_rng(seed)
    tasks = sorted(a["task_id"].unique())
    groups = [[cell.loc[cell["task_id"] == t, "success"].to_numpy(dtype=float) for t in tasks] for cell in (a, b)]
    differences = []
    for _ in range(draws):
        values = []
        for pick in rng.integers(0, len(tasks), len(tasks)):
            x, y = groups[0][pick], groups[1][pick]
            values.append(x[rng.integers(0, len(x), len(x))].mean() - y[rng.integers(0, len(y), len(y))].mean())
        differences.append(100.0 * np.mean(values))
    return np.percentile(differences, [2.5, 97.5])


def timed(fn) -> float:
    samples = []
    for _ in range(REPEATS):
        start = time.perf_counter()
        fn()
        samples.append(time.perf_counter() - start)
    return statistics.median(samples)


def cpu_of_children() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def snakemake_end_to_end(workdir: Path, *extra: str) -> dict:
    """`snakemake paper` from scratch in a fresh workdir whose ../shared is the reference data: wall time, the CPU
    time of Snakemake and all its jobs (what 2 quiet cores must do: about wall x 2 at best), jobs run, load."""
    workdir.mkdir(parents=True)
    (workdir / "manifests").symlink_to(ROOT / "manifests")
    if not (workdir.parent / "shared").exists():
        (workdir.parent / "shared").symlink_to(REFERENCE.parent)
    command = [sys.executable, "-m", "snakemake", "paper", "--cores", "2", "--snakefile", str(ROOT / "Snakefile"),
               "--directory", str(workdir), "--configfile", str(ROOT / "config" / "reference.yaml"), *extra]  # fmt: skip
    load_before, cpu_before, start = os.getloadavg()[0], cpu_of_children(), time.perf_counter()
    run = subprocess.run(command, check=True, capture_output=True, text=True)
    wall, cpu = time.perf_counter() - start, cpu_of_children() - cpu_before
    return {"wall_s": round(wall, 1), "cpu_s": round(cpu, 1), "jobs": run.stderr.count("Finished job"),
            "load_average_1min_before": round(load_before, 2), "load_average_1min_after": round(os.getloadavg()[0], 2)}


def job_start_up() -> dict:
    """What every table job pays before it renders: a Python process running Snakemake's script preamble and
    the imports of workflow/scripts/paper_table.py (median of REPEATS; CPU time and wall time)."""
    imports = ("import snakemake.script; from vlaquantbench.manifest import verified; "
               "from vlaquantbench.rule_log import job_log; from vlaquantbench.tables import write_table")
    walls, cpus = [], []
    for _ in range(REPEATS):
        cpu_before, start = cpu_of_children(), time.perf_counter()
        subprocess.run([sys.executable, "-c", imports], check=True)
        walls.append(time.perf_counter() - start)
        cpus.append(cpu_of_children() - cpu_before)
    return {"wall_s": round(statistics.median(walls), 2), "cpu_s": round(statistics.median(cpus), 2)}


def main() -> dict:
    cell_paths = find_cells(RECORDS)
    tables = sorted((ROOT / "config" / "tables").glob("*.yaml"))
    figure = load_figure(ROOT / "config" / "figures" / "scope_recovery.yaml")
    with tempfile.TemporaryDirectory() as out:
        out = Path(out)

        def summarize_all():
            write_summary(cell_paths, out / "summary.csv")

        workflow = WorkflowConfig.from_snakemake({"sources": {k: str(v) for k, v in SOURCES.items()}}, ROOT)

        def render_all():
            for path in tables:
                definition = load_table(path)
                files = {ref: cell_paths[ref] for ref in definition.refs() if ref in cell_paths}
                write_table(definition, files | workflow.table_sources(path.stem), out / f"{path.stem}.tex",
                            summary=REFERENCE / "authors-summary.csv", html_output=out / f"{path.stem}.html")
            plot_scope_recovery(figure, {ref: cell_paths[ref] for ref in figure.refs() if ref in cell_paths},
                                out / "scope_recovery.pdf", summary=REFERENCE / "authors-summary.csv")

        summary_s, render_s = timed(summarize_all), timed(render_all)
        start_up = job_start_up()
        paper = snakemake_end_to_end(out / "run" / "checkout")

    a = read_cell(cell_paths["libero/libero_spatial/pi05/rtn-W4A4-ah"]).episodes
    b = read_cell(cell_paths["libero/libero_spatial/pi05/ablate-W4A4-ah-down_attn_adarms"]).episodes
    vectorized_s = timed(lambda: task_clustered_bootstrap(a, b))
    loop_s = timed(lambda: loop_bootstrap(a, b))
    result = {
        "cells": len(cell_paths),
        "tables": [path.stem for path in tables] + ["scope_recovery (figure)"],
        "summarize_all_cells_s": round(summary_s, 3),
        "render_every_table_s": round(render_s, 3),
        "total_s": round(summary_s + render_s, 3),
        "goal_s": GOAL_S,
        "snakemake_paper_from_scratch_s": paper["wall_s"],
        "snakemake_paper_goal_s": 60.0,
        "snakemake_paper": paper,  # wall, CPU of Snakemake and its jobs, jobs, load around the run
        "table_job_start_up": start_up,  # per job: Python + Snakemake's script preamble + the script's imports
        "bootstrap_one_contrast_vectorized_s": round(vectorized_s, 4),
        "bootstrap_one_contrast_loop_s": round(loop_s, 4),
        "bootstrap_speedup": round(loop_s / vectorized_s, 1),
        "repeats": REPEATS,
        "statistic": "median wall time",
        "cpu_count": os.cpu_count(),
        "load_average_1min_at_end": round(os.getloadavg()[0], 2),  # the machine is shared: times are upper bounds
        "python": platform.python_version(),
        "machine": platform.processor() or platform.machine(),
    }
    output = ROOT / "benchmarks" / "results" / "tables_cpu.json"
    output.parent.mkdir(parents=True, exist_ok=True)
    output.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return result


if __name__ == "__main__":
    main()
