"""Meta-World cells through the closed-loop runner, on the real simulator (CPU): the scripted experts (the
`metaworld_expert` model) as a cell succeed on every task, their records carry the simulator's provenance and
each episode's task variation, the records do not depend on how many workers ran them, a kill -9 resumes
exactly, and a bad suite or task is refused while the DAG is built."""

from __future__ import annotations

import json
import subprocess
import sys

import pandas as pd
import pytest
import yaml

from paths import ROOT
from vlaquantbench.cells import cell_config, config_hash
from vlaquantbench.errors import UserError
from vlaquantbench.records import read_cell
from vlaquantbench.records.cell import JOURNAL_FILE
from vlaquantbench.runner.cell import run_cell
from vlaquantbench.runner.journal import TIMING_FIELDS
from vlaquantbench.tables.definition import TableDefinition
from vlaquantbench.tables.latex import render_latex

pytestmark = pytest.mark.slow

REF = "metaworld/metaworld_easy/metaworld_expert/rtn-BASELINE-e2e"
# Five metaworld_easy tasks (button-press, button-press-topdown, button-press-topdown-wall, button-press-wall,
# coffee-button), four variations each: all 20 succeeded when the seam was added (metaworld 3.0.0).
STUDY = {"models": {"metaworld_expert": {"variant": "full"}}, "tasks": 5, "episodes_per_task": 4}
TIMING = list(TIMING_FIELDS)  # measured, not outcomes: they differ between any two runs


def journal_episodes(folder) -> dict:
    lines = [json.loads(line) for line in (folder / JOURNAL_FILE).read_text().splitlines()[1:]]
    return {(r["task_id"], r["episode"]): r for r in lines if r.get("kind") == "episode"}


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    cfg = cell_config(REF, STUDY)
    folders = {}
    for workers in (1, 4):
        folders[workers] = tmp_path_factory.mktemp(f"experts{workers}") / config_hash(cfg)
        run_cell(cfg, folders[workers], num_envs=workers, progress=False)
    return cfg, folders


def test_the_experts_as_a_cell_succeed_on_every_task_with_the_simulator_in_the_header(runs):
    cfg, folders = runs
    cell = read_cell(folders[1])  # the records pass the schema the header bounds
    episodes = cell.episodes
    assert len(episodes) == 20 and episodes["task_name"].nunique() == 5
    for task, outcomes in episodes.groupby("task_name"):
        assert outcomes["success"].mean() >= 0.8, (task, outcomes[["episode", "success", "steps"]].to_dict("records"))
    header = cell.header
    assert (header["benchmark"], header["suite"], header["max_steps"]) == ("metaworld", "metaworld_easy", 500)
    assert header["versions"]["metaworld"] == "3.0.0" and header["versions"]["mujoco_pinned"] == "3.3.2"
    assert header["config_hash"] == config_hash(cfg) and header["config"] == cfg
    # Each episode records the placement its seeded variation drew, as a LIBERO episode its init state.
    variations = [tuple(v) for v in episodes["task_variation"]]
    assert len(set(variations)) == 20 and all(len(v) > 0 for v in variations)
    assert (episodes["init_state_id"] == episodes["episode"]).all()


def test_the_records_do_not_depend_on_how_many_workers_ran_them(runs):
    _, folders = runs
    one, four = read_cell(folders[1]).episodes, read_cell(folders[4]).episodes
    pd.testing.assert_frame_equal(one.drop(columns=TIMING, errors="ignore"), four.drop(columns=TIMING, errors="ignore"))
    digests = {n: {k: r["actions_sha256"] for k, r in journal_episodes(folders[n]).items()} for n in (1, 4)}
    assert digests[1] == digests[4] and len(set(digests[1].values())) == 20


def test_a_kill_9_in_the_middle_of_the_episodes_resumes_exactly(tmp_path):
    """tests/soak_kill9.py kills the running cell's process group right after its first journaled
    episodes, lets it resume, and compares with an uninterrupted run: nothing lost, nothing run twice."""
    out = tmp_path / "soak.json"
    soak = subprocess.run(
        [sys.executable, str(ROOT / "tests" / "soak_kill9.py"), "--ref", REF, "--max-steps", "suite", "--tasks",
         "0", "1", "2", "3", "--episodes-per-task", "3", "--kills", "1", "--write-kills", "0", "--anchor-p", "0", "0", "1",
         "--window", "0.2", "--seed", "1", "--out", str(out)],
        timeout=600,
    )
    result = json.loads(out.read_text())
    assert result["kills"] == 1 and result["kills_by_phase"] == {"append": 1} and result["episodes"] == 12
    assert result["lost_episodes"] == 0 and result["duplicated_episodes"] == 0
    assert result["outcomes_and_digests_equal"] and result["records_equal_but_timing"] and result["headers_equal"]
    assert soak.returncode == 0


@pytest.mark.parametrize(("study", "message"), [
    ({"tasks": [3, 30]}, "study.tasks: 30 is outside 0..27 (metaworld_easy has 28 tasks)"),
    ({"episodes_per_task": 1010}, "1010 episodes per task, but metaworld_easy has 1009"),
], ids=["task", "variations"])
def test_a_bad_task_is_refused_while_the_dag_is_built_naming_it(tmp_path, study, message):
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "manifests", "config", "src"):
        (checkout / item).symlink_to(ROOT / item)
    config = yaml.safe_load((ROOT / "config/demo/metaworld_expert.yaml").read_text())
    config["study"].update(study)
    path = tmp_path / "metaworld_expert.yaml"
    path.write_text(yaml.safe_dump(config))
    result = subprocess.run([sys.executable, "-m", "snakemake", "-n", "tables/expert.tex", "--cores", "1",
                             f"--configfile={path}"], cwd=checkout, capture_output=True, text=True, timeout=300)
    output = result.stdout + result.stderr
    table = checkout / "config/demo/metaworld/expert.yaml"
    assert result.returncode != 0 and f"{table}: cell {REF!r}: " in output and message in output, output[-3000:]


def test_a_table_row_reads_one_tasks_episodes_of_a_cell(runs):
    _, folders = runs
    cells = {REF: read_cell(folders[1])}
    raw = {"caption": "experts", "align": "lrr", "header": [["Task", "Episodes", "SR"]], "cells": {"experts": REF},
           "values": [{"stat": "episodes", "cell": "experts"}, {"stat": "rate", "cell": "experts"}],
           "rows": [{"label": "coffee", "task": "coffee-button-v3"}, {"label": "all"}]}
    latex = render_latex(TableDefinition.from_dict("expert", raw), cells)
    assert "coffee & 4 & 100.0" in latex and "all & 20 & 100.0" in latex
    raw["rows"] = [{"label": "reach", "task": "reach-v3"}]
    with pytest.raises(UserError, match=f"cell {REF}: no episode of task 'reach-v3' \\(row 'reach'\\); its tasks: "
                                        "button-press-topdown-v3"):
        render_latex(TableDefinition.from_dict("expert", raw), cells)


def test_the_user_command_renders_success_per_task_and_the_summary(tmp_path):
    """`snakemake tables/expert.tex tables/summary.csv --configfile=config/demo/metaworld_expert.yaml`, one
    variation per task: the cell runs through the workflow's rollout job and both outputs list it."""
    checkout = tmp_path / "checkout"
    checkout.mkdir()
    for item in ("Snakefile", "rules", "workflow", "manifests", "config", "src"):
        (checkout / item).symlink_to(ROOT / item)
    config = yaml.safe_load((ROOT / "config/demo/metaworld_expert.yaml").read_text())
    config["study"]["episodes_per_task"] = 1
    path = tmp_path / "metaworld_expert.yaml"
    path.write_text(yaml.safe_dump(config))
    result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "tables/expert.tex", "tables/summary.csv",
                             f"--configfile={path}"], cwd=checkout, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-3000:]
    table = (checkout / "tables/expert.tex").read_text()
    assert table.count(" & 1 & ") == 28 and "all tasks & 28 & " in table
    summary = pd.read_csv(checkout / "tables/summary.csv")
    assert summary[["benchmark", "suite", "model", "cell", "episodes"]].values.tolist() == [
        ["metaworld", "metaworld_easy", "metaworld_expert", "rtn-BASELINE-e2e", 28]]


SEED_REPEATS = {run_seed: f"metaworld/metaworld_easy/metaworld_expert/{prefix}rtn-BASELINE-e2e"
                for run_seed, prefix in ((0, ""), (1, "seed1-"), (2, "seed2-"))}  # fmt: skip


def test_seed_repeats_run_the_same_scenes_on_their_own_seeds_through_the_workflow(tmp_path):
    """A table of the experts at run seeds 0/1/2 and fig:scope_recovery with seeds 1 and 2 as open markers, through
    Snakemake with no summary: the DAG runs the three cells, and both read them from their records. Each run seed
    starts the same task variations on the protocol's seeds; the experts ignore the policy's random stream, so
    their episodes repeat exactly."""
    checkout = tmp_path / "checkout"
    (checkout / "config" / "figures").mkdir(parents=True)
    for item in ("Snakefile", "rules", "workflow", "manifests", "src"):
        (checkout / item).symlink_to(ROOT / item)
    for item in (ROOT / "config").iterdir():
        if item.name != "figures":
            (checkout / "config" / item.name).symlink_to(item)
    baseline = SEED_REPEATS[0]
    (checkout / "config" / "figures" / "scope_recovery.yaml").write_text(yaml.safe_dump({
        "baseline": baseline, "isolated": [{"label": "experts", "cell": baseline}],
        "nested": [{"label": "experts", "cell": baseline, "repeats": [SEED_REPEATS[1], SEED_REPEATS[2]]}]}))
    tables = tmp_path / "tables"
    tables.mkdir()
    (tables / "expert_seeds.yaml").write_text(yaml.safe_dump({
        "caption": "Experts at three run seeds ({episodes}).", "align": "lr", "header": [["", "seeds 0 / 1 / 2"]],
        "values": [{"stat": "rates", "cells": ["seed0", "seed1", "seed2"]}],
        "rows": [{"label": "experts", **{f"seed{run_seed}": ref for run_seed, ref in SEED_REPEATS.items()}}]}))
    config = yaml.safe_load((ROOT / "config/demo/metaworld_expert.yaml").read_text())
    config["study"].update(tasks=2, episodes_per_task=2)
    config.update(tables=["expert_seeds"], tables_dir=str(tables))
    path = tmp_path / "metaworld_expert.yaml"
    path.write_text(yaml.safe_dump(config))
    result = subprocess.run([sys.executable, "-m", "snakemake", "--cores", "2", "tables/expert_seeds.tex",
                             "figures/scope_recovery.pdf", f"--configfile={path}"], cwd=checkout, capture_output=True,
                            text=True, timeout=600)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    assert (checkout / "figures" / "scope_recovery.pdf").read_bytes().startswith(b"%PDF")
    assert "figures/scope_recovery.pdf: 3 cells from records, the rest from None" in (
        checkout / "logs" / "figures" / "scope_recovery.log").read_text()

    folders = {run_seed: checkout / "results" / "cells" / config_hash(cell_config(ref, config["study"]))
               for run_seed, ref in SEED_REPEATS.items()}  # fmt: skip
    assert len(set(folders.values())) == 3
    cells = {run_seed: read_cell(folder) for run_seed, folder in folders.items()}
    rates = " / ".join(f"{100 * cell.n_successes / cell.n_episodes:.1f}" for cell in cells.values())
    assert f"experts & {rates}" in (checkout / "tables" / "expert_seeds.tex").read_text()
    for run_seed, cell in cells.items():
        episodes = cell.episodes
        assert cell.header["seed"] == run_seed and len(episodes) == 4
        assert episodes["seed"].tolist() == [1009 * t + e + 1_000_003 * run_seed for t, e in zip(episodes["task_id"], episodes["episode"])]
        same = ["task_id", "episode", "init_state_id", "success", "steps"]
        pd.testing.assert_frame_equal(episodes[same], cells[0].episodes[same])
        assert [tuple(v) for v in episodes["task_variation"]] == [tuple(v) for v in cells[0].episodes["task_variation"]]
    assert cells[1].episodes["seed"].tolist()[:2] == [1_000_003, 1_000_004]
