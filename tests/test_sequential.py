"""Sequential evaluation (issue 32): the stopping rule on the authors' records, its error rate under their
task heterogeneity, the `vqb sequential` command and the tab:sequential Snakemake target."""

import csv
import json

import numpy as np
import pytest
from test_tables_workflow import layout, snakemake

from vlaquantbench.cli import main
from vlaquantbench.records import find_cells, read_cell
from vlaquantbench.sequential import (
    CSV_COLUMNS,
    DECISIONS,
    Design,
    interleaved_order,
    live_episodes,
    paired_rounds,
    retrospective,
    saved_fraction,
    simulate_false_decisions,
    stopping_rule,
)
from vlaquantbench.tables import load_table
from vlaquantbench.tables.sequential import sequential_contrasts
from paths import ROOT, RECORDS

SPATIAL = "libero/libero_spatial/pi05"
BASELINE = f"{SPATIAL}/rtn-BASELINE-e2e"
TABLES = ("clustered", "lattice")


@pytest.fixture(scope="module")
def paper_contrasts():
    """The contrasts of tab:clustered and tab:lattice and their cells' episodes, from the records."""
    contrasts = sequential_contrasts([load_table(ROOT / "config" / "tables" / f"{name}.yaml") for name in TABLES])
    cells = find_cells(RECORDS)
    return contrasts, {ref: read_cell(cells[ref]).episodes for pair in contrasts for ref in pair}


def test_interleaved_order_balances_every_prefix_over_tasks():
    episodes = read_cell(RECORDS / "libero/libero_spatial/xvla/rtn-BASELINE-e2e.jsonl").episodes  # 19 per task
    ordered = interleaved_order(episodes.sample(frac=1.0, random_state=0))
    assert len(ordered) == len(episodes) == 190
    # Round k is episode k of every task, tasks in order: each prefix of whole rounds has every task equally.
    assert ordered["task_id"].tolist() == list(range(10)) * 19
    assert ordered["episode"].tolist() == [k for k in range(19) for _ in range(10)]


def test_paired_rounds_stop_at_the_last_complete_round_and_refuse_other_tasks():
    spatial = read_cell(RECORDS / f"{BASELINE}.jsonl").episodes
    partial = spatial[~((spatial["task_id"] == 3) & (spatial["episode"] >= 12))]  # task 3 stops after 12 episodes
    assert paired_rounds(partial, spatial).shape == (12, 10)
    obj = read_cell(RECORDS / "libero/libero_object/pi05/rtn-W4A4-ah.jsonl").episodes
    obj = obj.assign(task_id=obj["task_id"] + 10)
    with pytest.raises(Exception, match="record different tasks"):
        paired_rounds(obj, spatial, ("object", "spatial"))


def test_paper_contrasts_meet_the_issue_targets(paper_contrasts):
    contrasts, episodes = paper_contrasts
    assert len(contrasts) == 40  # 30 of tab:clustered + 14 of tab:lattice, 4 shared
    table = retrospective(contrasts, episodes)
    assert list(table.columns) == list(CSV_COLUMNS)
    assert set(table["decision"]) <= set(DECISIONS) and set(table["full_sample_decision"]) <= set(DECISIONS)
    assert table["agrees"].all(), table.loc[~table["agrees"], ["cell", "baseline", "decision", "full_sample_decision"]]
    assert saved_fraction(table) >= 0.5
    by_pair = table.set_index(["cell", "baseline"])
    # 1.5% against 99.0%: decided after two rounds; 99.0% against 99.0%: never `worse`.
    assert by_pair.loc[(f"{SPATIAL}/ablate-W4A4-ah-attn_adarms", BASELINE), "episodes_used"] == 20
    assert by_pair.loc[(f"{SPATIAL}/ablate-W4A4-ah-attn_adarms", BASELINE), "decision"] == "worse"
    assert by_pair.loc[(f"{SPATIAL}/ablate-W4A4-ah-only_gate", BASELINE), "decision"] != "worse"
    assert (table["episodes_used"] <= table["episodes_available"]).all()
    # Live, a cell's batches of whole rounds fill its workers: with up to one per task it runs what the test
    # used; with 32 (batches of 4 rounds) a decision after 2 rounds runs 4, and near-cap ones stop at the cap.
    assert live_episodes(table, 10).tolist() == table["episodes_used"].tolist()
    live = live_episodes(table, 32)
    assert live[by_pair.index.get_loc((f"{SPATIAL}/ablate-W4A4-ah-attn_adarms", BASELINE))] == 40
    assert (live >= table["episodes_used"]).all() and (live <= table["episodes_available"]).all()


def test_rule_never_decides_on_no_evidence_and_stops_on_a_clear_difference():
    tied = np.zeros((20, 10))
    assert stopping_rule(tied, Design(margin_pp=1.0)).decision == "undecided"  # margin too narrow for 200 ties
    assert stopping_rule(tied).decision == "not_worse"
    broken = -np.ones((20, 10))
    result = stopping_rule(broken)
    # The first round only informs the bets (none is placed without data): decided after the second.
    assert (result.decision, result.episodes_used, result.rounds_used) == ("worse", 20, 2)
    assert result.log_capital_worse >= np.log(20)


def test_false_decision_rate_under_the_records_task_heterogeneity(paper_contrasts):
    contrasts, episodes = paper_contrasts
    design = Design()
    result = simulate_false_decisions([(episodes[a], episodes[b]) for a, b in contrasts], 250, design, seed=1)
    assert result["zero_difference"]["contrasts"] >= 10_000
    assert result["zero_difference"]["rate"] <= design.alpha
    assert result["margin_boundary"]["contrasts"] >= 9_000
    assert result["margin_boundary"]["rate"] <= design.alpha
    committed = json.loads((ROOT / "benchmarks" / "results" / "sequential_null.json").read_text())
    assert committed["zero_difference"]["rate"] <= committed["design"]["alpha"]


def _folder(tmp_path, names):
    folder = tmp_path / "records" / SPATIAL
    folder.mkdir(parents=True)
    for name in names:
        (folder / f"{name}.jsonl").symlink_to(RECORDS / SPATIAL / f"{name}.jsonl")
    return tmp_path / "records"


def test_cli_contrasts_every_other_cell_with_the_baseline(tmp_path, capsys):
    records = _folder(tmp_path, ["rtn-BASELINE-e2e", "ablate-W4A4-ah-attn_adarms", "ablate-W4A4-ah-only_gate", "rtn-W4A4-ah"])
    out = tmp_path / "sequential.csv"
    assert main(["sequential", str(records), "--baseline", "rtn-BASELINE-e2e", "--alpha", "0.05", "--csv", str(out)]) == 0
    rows = {row["cell"]: row for row in csv.DictReader(out.open())}
    assert set(rows) == {f"{SPATIAL}/{name}" for name in ("ablate-W4A4-ah-attn_adarms", "ablate-W4A4-ah-only_gate", "rtn-W4A4-ah")}
    assert {row["baseline"] for row in rows.values()} == {BASELINE}
    assert rows[f"{SPATIAL}/ablate-W4A4-ah-attn_adarms"]["decision"] == "worse"
    assert rows[f"{SPATIAL}/rtn-W4A4-ah"]["full_sample_decision"] == "worse"
    assert all(int(row["episodes_used"]) <= int(row["episodes_available"]) == 200 for row in rows.values())
    # A stricter level needs at least as many episodes for the same decision.
    strict = tmp_path / "strict.csv"
    assert main(["sequential", str(records), "--baseline", BASELINE, "--alpha", "0.001", "--csv", str(strict)]) == 0
    for row in csv.DictReader(strict.open()):
        assert int(row["episodes_used"]) >= int(rows[row["cell"]]["episodes_used"])


def test_cli_names_a_bad_baseline_and_a_bad_level(tmp_path, capsys):
    records = _folder(tmp_path, ["rtn-BASELINE-e2e", "rtn-W4A4-ah"])
    out = tmp_path / "sequential.csv"
    assert main(["sequential", str(records), "--baseline", "rtn-BASELINE", "--csv", str(out)]) == 2
    assert "--baseline 'rtn-BASELINE' is no cell there" in capsys.readouterr().err
    assert main(["sequential", str(records), "--baseline", "rtn-BASELINE-e2e", "--alpha", "0", "--csv", str(out)]) == 2
    assert "alpha must lie in (0, 1)" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
def test_snakemake_builds_the_sequential_table_from_the_reference_records(tmp_path, paper_contrasts):
    workdir = layout(tmp_path, RECORDS)
    run = snakemake(workdir, "tables/sequential.tex")
    assert run.returncode == 0, run.stderr[-3000:]
    rows = list(csv.DictReader((workdir / "tables" / "sequential.csv").open()))
    assert len(rows) == 40 and set(CSV_COLUMNS) <= set(rows[0])
    contrasts, episodes = paper_contrasts
    assert [(row["cell"], row["baseline"]) for row in rows] == contrasts
    expected = retrospective(contrasts, episodes)
    assert [int(row["episodes_used"]) for row in rows] == expected["episodes_used"].tolist()
    tex = (workdir / "tables" / "sequential.tex").read_text()
    assert r"\label{tab:sequential}" in tex and "0 contrasts contradict" in tex
    assert (workdir / "figures" / "sequential_episodes.pdf").read_bytes().startswith(b"%PDF")
    assert (workdir / "logs" / "tables" / "sequential.log").is_file()
