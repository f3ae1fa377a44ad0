"""Issue 32 item 4: the stopping rule live on the pi0.5 trained here (config/trained_sequential.yaml), read from
its committed records. The same cells were also run in full (config/trained_sequential_fixed.yaml): the live
run decided what the rule replayed on those full records predicts, at the same round, after the episodes the
runner's batching predicts, and every episode it ran is the full run's episode of the same task, episode and
seed with the same outcome. Snakemake renders both tables from the committed records and they say so."""

from __future__ import annotations

import subprocess
import sys

import pandas as pd
import pytest
import yaml

from paths import ROOT
from test_dag_trained_checkpoint import workflow_with_tables
from vlaquantbench.records import read_cell
from vlaquantbench.runner.journal import TIMING_FIELDS
from vlaquantbench.sequential import Design, live_episodes, retrospective

CONFIG = yaml.safe_load((ROOT / "config/trained_sequential.yaml").read_text())
LIVE, FIXED = ROOT / CONFIG["records_dir"], ROOT / "results/trained_sequential/fixed"
BASE = "metaworld/metaworld_mt50/pi05/"
BASELINE = BASE + CONFIG["study"]["sequential"]["against"]
DESTRUCTIVE, NEAR_BASELINE = BASE + "rtn-W2A2-e2e", BASE + "rtn-W4A8-e2e"
TASKS, CAP = len(CONFIG["study"]["tasks"]), CONFIG["study"]["episodes_per_task"]
DESIGN = Design(CONFIG["study"]["sequential"]["alpha"], CONFIG["study"]["sequential"]["margin_pp"])
KEY = ["task_id", "episode", "seed"]


def outcomes(episodes: pd.DataFrame) -> pd.DataFrame:
    """What an episode did (not how long it took), by its identity."""
    return episodes.drop(columns=[c for c in TIMING_FIELDS if c in episodes]).set_index(KEY).sort_index()


@pytest.mark.parametrize("ref", [DESTRUCTIVE, NEAR_BASELINE])
def test_the_live_decision_is_the_one_the_full_records_predict(ref):
    live, fixed = read_cell(LIVE / ref), read_cell(FIXED / ref)
    baseline = read_cell(FIXED / BASELINE)
    # The baseline runs in full in both studies: one cell, one hash.
    assert read_cell(LIVE / BASELINE).header["config_hash"] == baseline.header["config_hash"]
    assert "stopping" not in fixed.header and fixed.header["config"].get("sequential") is None
    predicted = retrospective([(ref, BASELINE)], {ref: fixed.episodes, BASELINE: baseline.episodes}, DESIGN)
    stopping = live.header["stopping"]
    assert (stopping["decision"], stopping["rounds_used"]) == (predicted.at[0, "decision"], predicted.at[0, "rounds_used"])
    assert live.header["config"]["sequential"]["against"] == {"ref": BASELINE, "config_hash": baseline.header["config_hash"]}
    workers = CONFIG["study"]["execution"]["num_envs"]
    assert len(live.episodes) == stopping["rounds_run"] * TASKS == live_episodes(predicted, workers)[0]
    # Every live episode is the full run's episode: same identity, same outcome, steps and actions' smoothness.
    ran, full = outcomes(live.episodes), outcomes(fixed.episodes)
    pd.testing.assert_frame_equal(ran, full.loc[ran.index])


def test_the_destructive_cell_stops_early_and_the_near_baseline_cell_runs_to_its_cap():
    destructive = read_cell(LIVE / DESTRUCTIVE).header["stopping"]
    near = read_cell(LIVE / NEAR_BASELINE).header["stopping"]
    assert destructive["decision"] == "worse" and destructive["rounds_run"] < CAP
    assert near["decision"] == "undecided" and near["rounds_run"] == CAP


@pytest.mark.slow
def test_snakemake_renders_the_live_table_and_the_retrospective_from_the_committed_records(tmp_path):
    """No episode runs: the live table's `stopped` column prints each cell's decision@episodes, and
    tables/sequential.csv (the rule on the full records) makes the same decisions."""
    checkout, _ = workflow_with_tables(tmp_path)
    # Only the study's records and manifests: whatever the run writes stays in the checkout.
    (checkout / "results").mkdir()
    (checkout / "results/trained_sequential").symlink_to(ROOT / "results/trained_sequential")
    (checkout / "manifests").mkdir()
    for name in ("trained_sequential_live.tsv", "trained_sequential_fixed.tsv"):
        (checkout / "manifests" / name).symlink_to(ROOT / "manifests" / name)
    fixed_config = ["config/trained_sequential_fixed.yaml"]

    def snakemake(target, *configs):
        result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", target, "--configfile",
                                 "config/trained_sequential.yaml", *configs], cwd=checkout, capture_output=True, text=True,
                                timeout=600)
        assert result.returncode == 0, result.stderr[-3000:]
        assert "rule rollout" not in result.stdout + result.stderr
        return (checkout / target).read_text()

    live = snakemake("tables/trained_sequential.tex")
    stops = {ref: read_cell(LIVE / ref).header["stopping"] for ref in (DESTRUCTIVE, NEAR_BASELINE)}
    for label, ref in (("RTN W2A2, end to end", DESTRUCTIVE), ("RTN W4A8, end to end", NEAR_BASELINE)):
        row = next(line for line in live.splitlines() if line.startswith(label))
        assert row.rstrip(" \\").endswith(f"{stops[ref]['decision'].replace('_', chr(92) + '_')}@{stops[ref]['episodes_used']}")
    assert next(line for line in live.splitlines() if line.startswith("Full precision")).rstrip(" \\").endswith("--")

    snakemake("tables/sequential.tex", *fixed_config)
    table = pd.read_csv(checkout / "tables/sequential.csv").set_index("cell")
    for ref, stopping in stops.items():
        assert (table.at[ref, "decision"], table.at[ref, "episodes_used"]) == (stopping["decision"], stopping["episodes_used"])
        assert table.at[ref, "episodes_available"] == CAP * TASKS
