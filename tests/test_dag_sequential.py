"""A real `snakemake tables/lattice.tex tables/summary.csv` on the demo study with `study.sequential` on
(issue 32): the baseline's records are built first (a declared input of the other cell's rollout), the
cell stops once decided, the DAG takes the stopped cell as complete, the tables say that it stopped and
why, and a margin the test cannot reach runs the cell to its cap. (Resuming a stopped cell from its journal:
tests/test_runner_stopping.py.)"""

import json
import re

import pandas as pd
import pytest
import yaml

from file_audit import audited_env, job_audits, undeclared
from test_dag_rollout import job_counts, snakemake, workflow_copy

pytestmark = pytest.mark.slow

BASELINE = "libero/libero_spatial/pi05/rtn-BASELINE-e2e"
CELL = "libero/libero_spatial/pi05/rtn-W4A4-ah"
TARGETS = ("tables/lattice.tex", "tables/summary.csv")


def sequential_study(checkout, margin_pp):
    """The demo config on one task, a cap of 4 episodes of 4 steps, the rule at alpha 0.5 and `margin_pp`;
    the lattice reduced to the all-layers row with the stop and the jerk as columns."""
    config_path = checkout / "config" / "config.yaml"
    config = yaml.safe_load(config_path.read_text())
    config["study"].update(tasks=1, episodes_per_task=4, sequential={"alpha": 0.5, "margin_pp": margin_pp})
    config["study"]["runner"].update(max_steps=4, camera_size=64, flow_steps=2)
    config_path.write_text(yaml.safe_dump(config))
    table_path = checkout / config["study"]["tables_dir"] / "lattice.yaml"
    table = yaml.safe_load(table_path.read_text())
    table["rows"] = [row for row in table["rows"] if row["cell"] == CELL]
    table["align"] += "rr"
    table["header"][-1] += ["stopped", "jerk"]
    table["values"] += [{"stat": "stopped", "cell": "cell"}, {"stat": "mean_ci", "cell": "cell", "field": "jerk"}]
    table_path.write_text(yaml.safe_dump(table))


def headers(checkout):
    """(folder, header) of every cell folder."""
    return [(path.parent, json.loads(path.read_text())) for path in (checkout / "results" / "cells").glob("*/header.json")]


def test_sequential_demo_study_stops_a_cell_and_the_dag_and_tables_know(tmp_path):
    checkout = workflow_copy(tmp_path)
    # Random weights never succeed: every paired difference is 0, which a 80 pp margin calls not worse
    # after 2 rounds at alpha 0.5 (two workers: one batch of two rounds).
    sequential_study(checkout, margin_pp=80)
    audit = tmp_path / "audit"
    first = snakemake(checkout, *TARGETS, env=audited_env(audit))
    assert job_counts(first)["rollout"] == 2
    assert undeclared(audit, checkout) == {}  # the cell's rollout read the baseline's records as a declared input
    cells = {header["ref"]: (folder, header) for folder, header in headers(checkout)}
    baseline_folder, baseline = cells[BASELINE]
    folder, header = cells[CELL]
    assert "stopping" not in baseline and "sequential" not in baseline["config"]
    assert header["config"]["sequential"]["against"] == {"ref": BASELINE, "config_hash": baseline["config_hash"]}
    rollouts = [job for job in job_audits(audit) if job["rule"] == "rollout"]
    assert [job["declared"]["input"][-2:] for job in rollouts if len(job["declared"]["input"]) > 1] == [
        [str(baseline_folder / "episodes.parquet"), str(baseline_folder / "header.json")]]
    stopping = header["stopping"]
    assert (stopping["decision"], stopping["rounds_used"], stopping["rounds_run"]) == ("not_worse", 2, 2)
    assert len(pd.read_parquet(folder / "episodes.parquet")) == 2  # of a cap of 4
    table = (checkout / "tables" / "lattice.tex").read_text()
    assert r"not\_worse@2" in table
    assert re.search(r" & \d+\.\d{3} \[\d+\.\d{3},\d+\.\d{3}\] \\\\", table)  # the mean jerk and its interval
    summary = pd.read_csv(checkout / "tables" / "summary.csv").set_index("cell")
    assert summary.loc["rtn-W4A4-ah", ["episodes", "sequential_decision", "sequential_episodes_used"]].tolist() == [
        2, "not_worse", 2]
    assert pd.isna(summary.loc["rtn-BASELINE-e2e", "sequential_decision"])
    assert "Nothing to be done" in snakemake(checkout, "-n", *TARGETS)  # the stopped cell is complete

    # A 5 pp margin cannot be reached in 4 episodes: the cell (a new config, hence folder) runs to its cap;
    # the baseline is not run again.
    config_path = checkout / "config" / "config.yaml"
    config_path.write_text(config_path.read_text().replace("margin_pp: 80", "margin_pp: 5"))
    baseline_mtime = (baseline_folder / "episodes.parquet").stat().st_mtime_ns
    assert job_counts(snakemake(checkout, *TARGETS))["rollout"] == 1
    assert (baseline_folder / "episodes.parquet").stat().st_mtime_ns == baseline_mtime
    (capped,) = [h for f, h in headers(checkout) if h["ref"] == CELL and f != folder]
    assert (capped["stopping"]["decision"], capped["stopping"]["rounds_run"]) == ("undecided", 4)
    assert r"undecided@4" in (checkout / "tables" / "lattice.tex").read_text()
